"""GL backend selection and the error raised when no backend works."""

import os
import subprocess
import sys

import numpy as np
import torch
import pytest

from trakdis.envs import ClothEnv
from trakdis.envs import rendering


def test_egl_is_the_default_backend():
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    code = "import os, trakdis.envs; print(os.environ['MUJOCO_GL'], os.environ['PYOPENGL_PLATFORM'])"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["egl", "egl"]


def test_user_choice_is_kept(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    assert rendering.configure_gl() == "osmesa"
    assert os.environ["PYOPENGL_PLATFORM"] == "osmesa"


def test_missing_gl_gives_instructions_and_state_envs_still_work(monkeypatch):
    import mujoco

    def broken(*args, **kwargs):
        raise mujoco.FatalError("gladLoadGL error")

    monkeypatch.setattr(mujoco, "Renderer", broken)
    with pytest.raises(RuntimeError, match="MUJOCO_GL=egl") as err:
        ClothEnv(task="ClothFold", from_pixels=True, horizon=2).reset(seed=0)
    assert "from_pixels=False" in str(err.value) and "gladLoadGL" in str(err.value)
    env = ClothEnv(task="ClothFold", horizon=2)  # state-only: no GL needed
    obs, _ = env.reset(seed=0)
    assert np.isfinite(obs["state"]).all()


def test_renderer_argument_errors():
    with pytest.raises(ValueError, match="image_size"):
        rendering.FrameRenderer(4)
    with pytest.raises(ValueError, match="render_supersample"):
        rendering.FrameRenderer(32, supersample=8)


@pytest.mark.parametrize("first", ["mujoco", "torchrl.envs"])
def test_importing_mujoco_first_still_renders_offscreen(first):
    # torchrl.envs imports mujoco, so a TorchRL user's natural import order loads mujoco before
    # trakdis could set MUJOCO_GL: the renderer must still use the offscreen backend.
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    code = (f"import {first}, trakdis.envs\n"
            "from trakdis.envs import rendering\n"
            "obs, _ = trakdis.envs.ClothEnv(task='ClothFold', from_pixels=True).reset(seed=0)\n"
            "print('rendered', obs['pixels'].shape, obs['pixels'].std() > 0, rendering.mujoco_gl_backend())\n")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "rendered (32, 32, 3) True egl" in out.stdout, out.stdout


def test_explicit_backend_chosen_before_mujoco_is_kept():
    env = {k: v for k, v in os.environ.items() if k not in ("PYOPENGL_PLATFORM",)}
    env["MUJOCO_GL"] = "glfw"
    code = ("import mujoco, os\n"
            "os.environ['MUJOCO_GL'] = 'egl'\n"
            "from trakdis.envs import rendering\n"
            "rendering.adopt_configured_backend()\n"
            "print(rendering.mujoco_gl_backend())\n")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "glfw", out.stdout


@pytest.mark.parametrize("task", ["ClothFold", "ClothFoldDiagonalUnpinned"])
def test_picker_markers_are_visible_at_32px_and_change_no_physics(task, monkeypatch):
    """Each picker is drawn as a marker several pixels wide where the camera sees it, in the marker's
    colour; the marker is rendering only: the same episode has the same states with a 12 mm marker."""
    from trakdis.envs import ExpertPolicy, PICKER_MARKER_RADIUS, make_env
    from trakdis.envs import model

    assert PICKER_MARKER_RADIUS >= 0.03
    env = ClothEnv(task=task, from_pixels=True, image_size=32, horizon=5)
    obs, _ = env.reset(seed=2)
    P = env.camera_matrix()
    img = obs["pixels"].astype(int)
    white = (img.min(-1) > 200)  # the marker's colour; cloth is blue, the table brown
    for p in obs["state"][12:].reshape(-1, 3):
        u, v, w = P @ np.append(p, 1.0)
        col, row = int(u / w), int(v / w)
        assert white[max(row - 1, 0): row + 2, max(col - 1, 0): col + 2].any(), f"no marker at ({col}, {row})"
    assert white.sum() >= 6 * env.num_pickers  # several pixels per picker, not one

    def states(radius):
        monkeypatch.setattr(model, "PICKER_MARKER_RADIUS", radius)
        td = make_env(task, from_pixels=True, image_size=32, seed=0, horizon=12).rollout(12, ExpertPolicy(task))
        return td["next", "state"], td["pixels"]

    big, small = states(PICKER_MARKER_RADIUS), states(0.012)
    assert torch.equal(big[0], small[0]) and not torch.equal(big[1], small[1])
