import functools

import cv2
import numpy as np
import pytest
import torch
from torchrl.data import Bounded
from torchrl.envs import SerialEnv, TransformedEnv, check_env_specs

from toy_pixel_env import make_toy_env
from trakdis.transforms import ImageResize, resize_images


def test_area_mode_matches_opencv_inter_area():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (64, 48, 3), dtype=np.uint8)
    ref = cv2.resize(img, (12, 16), interpolation=cv2.INTER_AREA)  # cv2 takes (width, height)
    out = resize_images(torch.from_numpy(img), (16, 12), mode="area")
    assert out.dtype == torch.uint8 and out.shape == (16, 12, 3)
    assert (out.int() - torch.from_numpy(ref).int()).abs().max() <= 1


def test_antialiasing_averages_high_frequencies():
    # 1-pixel stripes: an aliasing resize picks whole stripes (0 or 255), an anti-aliased one averages.
    img = torch.zeros(60, 60, 3, dtype=torch.uint8)
    img[:, ::2] = 255
    out = resize_images(img, (20, 20))  # factor 3: non-antialiased bilinear would sample single stripes
    assert (out.float() - 127.5).abs().max() < 45, out[..., 0]
    naive = torch.nn.functional.interpolate(img.permute(2, 0, 1)[None].float(), size=(20, 20), mode="bilinear")
    assert (naive - 127.5).abs().max() > 100  # the test image does alias without anti-aliasing


@pytest.mark.parametrize("dtype", [torch.uint8, torch.float32])
def test_layouts_and_batch_shapes(dtype):
    hwc = torch.randint(0, 256, (2, 3, 40, 30, 3)).to(dtype)
    out = ImageResize(size=(10, 15))._apply_transform(hwc)
    assert out.shape == (2, 3, 10, 15, 3) and out.dtype == dtype
    chw = hwc.movedim(-1, -3).contiguous()
    out_chw = ImageResize(size=(10, 15))._apply_transform(chw)
    assert out_chw.shape == (2, 3, 3, 10, 15)
    torch.testing.assert_close(out_chw.movedim(-3, -1), out)
    # a constant image stays constant
    const = torch.full((40, 30, 3), 77, dtype=dtype)
    assert (ImageResize(size=8)._apply_transform(const) == 77).all()


def test_as_replay_buffer_transform_on_windows():
    from tensordict import TensorDict

    td = TensorDict({"pixels": torch.randint(0, 256, (4, 3, 32, 32, 3), dtype=torch.uint8)}, [4, 3])
    out = ImageResize(size=16)(td.clone())
    assert out["pixels"].shape == (4, 3, 16, 16, 3)
    torch.testing.assert_close(out["pixels"], resize_images(td["pixels"], (16, 16)))


def test_bounded_spec_keeps_bounds():
    spec = Bounded(low=0, high=255, shape=(2, 20, 20, 3), dtype=torch.uint8)
    out = ImageResize(size=5).transform_observation_spec(spec)
    assert isinstance(out, Bounded) and out.shape == (2, 5, 5, 3) and out.dtype == torch.uint8
    assert out.space.low.max() == 0 and out.space.high.min() == 255


def test_errors_name_the_problem():
    with pytest.raises(ValueError, match="channel axis"):
        resize_images(torch.zeros(2, 10, 10, 10), (5, 5))
    with pytest.raises(ValueError, match="mode"):
        ImageResize(size=4, mode="nearest")


def test_spec_single_env_and_out_key():
    env = TransformedEnv(make_toy_env(size=16), ImageResize(in_keys=["pixels"], out_keys=["small"], size=8))
    spec = env.observation_spec
    assert spec["small"].shape == (8, 8, 3) and spec["small"].dtype == torch.uint8
    assert type(spec["small"]) is type(spec["pixels"]) and spec["pixels"].shape == (16, 16, 3)
    check_env_specs(env, seed=0)
    td = env.rollout(4)
    assert td["small"].shape == (4, 8, 8, 3) and td["next", "small"].shape == (4, 8, 8, 3)


def test_float_chw_env():
    env = TransformedEnv(make_toy_env(size=16, float_pixels=True), ImageResize(size=8))
    assert env.observation_spec["pixels"].shape == (3, 8, 8)
    check_env_specs(env, seed=0)


def test_serial_env():
    serial = TransformedEnv(SerialEnv(2, functools.partial(make_toy_env, size=16)), ImageResize(size=8))
    check_env_specs(serial, seed=0)
    assert serial.rollout(3)["pixels"].shape == (2, 3, 8, 8, 3)
    serial.close()
