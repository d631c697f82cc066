"""OutOfViewFill: pickers out of the camera's view replaced by a sentinel (--mask-unseen-pickers); a
TorchRL Transform (envs, replay buffers, stored TensorDicts)."""
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from trakdis.envs.model import CAMERA_POS
from trakdis.transforms import OutOfViewFill, fixed_camera_matrix
from trakdis.utils.checkpoint import read_checkpoint, save_checkpoint

IN_VIEW = [(0.0, 0.0, 0.0), (0.1, 0.05, 0.05), (0.0, 0.3, 0.0)]
# high above the frame, beyond its right / left edge, and behind the camera (on its axis: the
# projection alone would land in the middle of the image)
BEHIND = tuple(np.asarray(CAMERA_POS) - 0.2 * np.array([0.0, 1.0, -1.0]) / np.sqrt(2))
OUT_OF_VIEW = [(0.0, 0.0, 0.3), (0.4, 0.0, 0.0), (-0.4, 0.0, 0.0), BEHIND]


def _states(picker0, picker1, batch=(2, 3)):
    x = torch.randn(*batch, 18)
    x[..., 12:15] = torch.tensor(picker0, dtype=torch.float32)
    x[..., 15:18] = torch.tensor(picker1, dtype=torch.float32)
    return x


@pytest.mark.parametrize("out", OUT_OF_VIEW)
def test_out_of_view_picker_is_filled_in_view_one_kept(out):
    fill = OutOfViewFill.for_task("ClothFold")
    assert fill.starts == (12, 15) and fill.image_size == 32
    for inside in IN_VIEW:
        x = _states(inside, out)  # [B, T, D]
        before = x.clone()
        y = fill.mask(x)
        assert torch.equal(x, before)  # the input is not modified
        assert y.shape == x.shape and fill.visible(x)[..., 0].all() and not fill.visible(x)[..., 1].any()
        assert torch.equal(y[..., :15], x[..., :15])  # corners and the in-view picker unchanged
        assert torch.equal(y[..., 15:18], torch.tensor([0.0, 0.0, 0.4]).expand(2, 3, 3))
        assert torch.equal(fill.mask(y), y)  # idempotent: the sentinel itself is out of view


def test_diagonal_tasks_mask_their_one_picker_and_tensordicts():
    fill = OutOfViewFill.for_task("ClothFoldDiagonalPinned", fill=(0.0, 0.0, 0.5))
    assert fill.starts == (12,)
    x = torch.zeros(4, 15)
    x[1, 12:15] = torch.tensor([0.0, 0.0, 0.3])
    td = TensorDict({"state": x, "other": x.clone()}, [4])
    out = fill(td)
    assert out["state"][1, 12:].tolist() == [0.0, 0.0, 0.5] and torch.equal(out["state"][[0, 2, 3]], x[[0, 2, 3]])
    assert torch.equal(out["other"], x) and x[1, 14] == 0.3  # other keys and the input tensor untouched
    with pytest.raises(ValueError, match="dims"):
        fill.mask(torch.zeros(3, 12))


def test_dict_round_trip_through_the_safe_loader(tmp_path):
    fill = OutOfViewFill.for_task("ClothFold", image_size=64, in_keys=("state", "state_estimate"))
    save_checkpoint(tmp_path / "f.pt", {"fill": fill.to_dict()})
    saved = read_checkpoint(tmp_path / "f.pt")["fill"]
    assert set(saved) == {"camera_matrix", "image_size", "starts", "fill", "keys"}  # the format of earlier files
    again = OutOfViewFill.from_dict(saved)
    assert again.in_keys == again.out_keys == ["state", "state_estimate"] and again.starts == fill.starts
    assert torch.equal(again.camera_matrix, fill.camera_matrix) and torch.equal(again.fill, fill.fill)
    x = _states(IN_VIEW[1], OUT_OF_VIEW[0], batch=(5,))
    assert torch.equal(again.mask(x), fill.mask(x))
    earliest = {k: v for k, v in saved.items() if k != "keys"}
    assert OutOfViewFill.from_dict(earliest).in_keys == ["state"]
    other = OutOfViewFill(fill.camera_matrix, 64, fill.starts, in_keys=["state"], out_keys=["masked"])
    assert OutOfViewFill.from_dict(other.to_dict()).out_keys == ["masked"]


def test_in_an_env_and_a_replay_buffer():
    """A TorchRL transform: on env resets and steps (specs checked: a bounded state spec widened to
    hold the sentinel), as a replay buffer's sampling transform and into another key."""
    from points_env import PointsEnv
    from torchrl.data import LazyTensorStorage, ReplayBuffer
    from torchrl.envs import TransformedEnv, check_env_specs

    fill = OutOfViewFill(fixed_camera_matrix("ClothFold", 32), 32, [0, 3])
    env = TransformedEnv(PointsEnv(), fill)
    assert env.observation_spec["state"].space.high[5] == pytest.approx(0.4)  # 0.35 in the base env
    check_env_specs(env)
    torch.manual_seed(0)
    raw = PointsEnv().rollout(5)
    torch.manual_seed(0)
    out = env.rollout(5)
    for key in ("state", ("next", "state")):
        assert torch.equal(out[key], fill.mask(raw[key])) and (out[key][..., 3:] == torch.tensor([0.0, 0.0, 0.4])).all()
        assert env.observation_spec["state"].is_in(out[key])
    assert torch.equal(out["state_estimate"], raw["state_estimate"])
    buffer = ReplayBuffer(storage=LazyTensorStorage(5), batch_size=4, transform=fill.clone())  # one parent each
    buffer.extend(raw.select("state").set("step", torch.arange(5)))
    sample = buffer.sample()
    assert torch.equal(sample["state"], out["state"][sample["step"]])
    into = OutOfViewFill(fixed_camera_matrix("ClothFold", 32), 32, [0, 3], in_keys=["state"], out_keys=["masked"])
    td = into(raw.select("state"))
    assert torch.equal(td["masked"], out["state"]) and torch.equal(td["state"], raw["state"])


def test_camera_matrix_without_gl_is_the_rendering_envs():
    from trakdis.envs.cloth_env import ENV_CLASSES

    for task, size in (("ClothFold", 32), ("ClothFoldDiagonalPinned", 32), ("ClothFoldDiagonalUnpinned", 48)):
        env = ENV_CLASSES[task](from_pixels=True, image_size=size)
        try:
            env.reset(seed=0)
            np.testing.assert_allclose(fixed_camera_matrix(task, size), env.camera_matrix(), rtol=1e-12, atol=1e-9)
        finally:
            env.close()
    # each task has its own field of view: the unpinned fold's wider camera draws the scene smaller
    wide, narrow = fixed_camera_matrix("ClothFoldDiagonalUnpinned", 32), fixed_camera_matrix("ClothFold", 32)
    assert wide[0, 0] < 0.9 * narrow[0, 0]
