"""The camera geometry behind ``task_spec(task).state_mirror`` (label-consistent flip augmentation)."""

import dataclasses

import numpy as np
import pytest

from trakdis.envs import TASKS, ClothEnv, task_spec

SIZE = 64


def _project(P, pts):
    h = np.hstack([pts, np.ones((len(pts), 1))]) @ P.T
    return h[:, :2] / h[:, 2:3]


def _cloth_mask(img):
    return (img[..., 2].astype(int) - img[..., 0]) > 60


def _on_mask(mask, uv):
    ij = np.floor(uv).astype(int)
    inside = (ij >= 0).all(1) & (ij < SIZE).all(1)
    assert inside.all(), "projected cloth vertices fall outside the image"
    return mask[ij[:, 1], ij[:, 0]].mean()


@pytest.mark.parametrize("task", TASKS)
def test_flipped_image_matches_mirrored_state(task):
    env = ClothEnv(task=task, from_pixels=True, image_size=SIZE, include_vertices=True, horizon=5)
    obs, _ = env.reset(seed=11)
    P = env.camera_matrix()
    perm, sign = map(np.array, task_spec(task).state_mirror)
    mask = _cloth_mask(obs["pixels"])
    n = 12
    interior = np.arange(n * n).reshape(n, n)[1:-1, 1:-1].reshape(-1)  # away from antialiased edges
    verts = obs["vertices"].astype(float)[interior]
    # the picker markers (PICKER_MARKER_RADIUS, ~4.5 px at this size) hide the cloth under them
    pickers_uv = _project(P, obs["state"][12:].astype(float).reshape(-1, 3))
    dist = np.linalg.norm(_project(P, verts)[:, None] - pickers_uv[None], axis=-1).min(1)
    verts = verts[dist > 8.0]
    assert len(verts) > 50
    # the camera matrix agrees with the renderer: cloth vertices project onto cloth pixels
    assert _on_mask(mask, _project(P, verts)) > 0.95
    # ... and not by chance: shifted by a cloth width they miss it
    assert _on_mask(mask, _project(P, verts + [0.0, 0.35, 0.0]).clip(0, SIZE - 1)) < 0.5
    # flipped image <-> mirrored vertices (x -> -x)
    flipped = mask[:, ::-1]
    assert _on_mask(flipped, _project(P, verts * [-1, 1, 1])) > 0.95
    # mirrored reduced state projects where the flipped image has the matching points
    state = obs["state"].astype(float)
    mstate = state[perm] * sign
    uv = _project(P, state.reshape(-1, 3))
    muv = _project(P, mstate.reshape(-1, 3))
    blocks = perm.reshape(-1, 3)[:, 0] // 3
    np.testing.assert_allclose(muv[:, 0], SIZE - uv[blocks, 0], atol=1e-6)
    np.testing.assert_allclose(muv[:, 1], uv[blocks, 1], atol=1e-6)
    # corner labels keep their image meaning after the flip: c00/c0N left of cN0/cNN, near below far
    for corners in (uv[:4], muv[:4]):
        assert corners[0, 0] < corners[2, 0] and corners[1, 0] < corners[3, 0]
        assert corners[0, 1] > corners[1, 1] and corners[2, 1] > corners[3, 1]


def test_mirrored_scene_renders_as_the_flipped_image():
    """Simulate the mirrored configuration: its state and image are the mirrored state and the flipped image."""
    task = "ClothFold"
    a = ClothEnv(task=task, from_pixels=True, image_size=SIZE, horizon=5)
    obs_a, _ = a.reset(seed=4)
    cfg = a.config
    mcfg = dataclasses.replace(cfg, rotation=-cfg.rotation, offset_x=-cfg.offset_x)
    mpickers = [(-x, y, z) for x, y, z in a.picker_pos0][::-1]
    b = ClothEnv(task=task, from_pixels=True, image_size=SIZE, horizon=5)
    obs_b, _ = b.reset(seed=4, options={"config": mcfg, "picker_pos": mpickers})
    perm, sign = map(np.array, task_spec(task).state_mirror)
    np.testing.assert_allclose(obs_b["state"], obs_a["state"][perm] * sign, atol=2e-4)
    diff = np.abs(obs_b["pixels"].astype(int) - obs_a["pixels"][:, ::-1].astype(int))
    assert diff.mean() < 2.0 and np.percentile(diff, 99) < 60
