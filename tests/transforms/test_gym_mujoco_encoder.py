"""EncoderTransform(in_keys=..., out_keys=...) on a gymnasium MuJoCo env that is not ours.

TorchRL's ``GymEnv("InvertedPendulum-v5", from_pixels=True, pixels_only=False)``, rendered
offscreen (EGL), resized to two pixel keys of different sizes, each encoded by one lazy encoder
(``LazyConv2d``/``LazyLinear``, shapes fixed by the spec's dry run): single env and ``ParallelEnv``.
"""

import functools

import pytest
import torch
from torchrl.envs import ParallelEnv, TransformedEnv, check_env_specs

from toy_pixel_env import LazyEncoder, make_gym_mujoco_env
from trakdis.transforms import EncoderTransform

pytest.importorskip("imageio", reason="gymnasium's MuJoCo envs need imageio (pip install -e '.[test]')")


def test_single_gym_mujoco_env_two_cameras_lazy_encoder():
    torch.manual_seed(0)
    env = make_gym_mujoco_env(functools.partial(LazyEncoder, out_dim=3))
    t = env.transform[-1]
    assert isinstance(t, EncoderTransform) and t.in_keys == ["pixels32", "pixels24"]
    assert any(isinstance(p, torch.nn.parameter.UninitializedParameter) for p in t.encoder.parameters())
    spec = env.observation_spec
    assert not any(isinstance(p, torch.nn.parameter.UninitializedParameter) for p in t.encoder.parameters())
    assert spec["pixels32"].shape == (32, 32, 3) and spec["pixels24"].shape == (24, 24, 3)
    for key in ("estimate32", "estimate24"):
        assert spec[key].shape == (3,) and spec[key].dtype == torch.float32
    assert all(not p.requires_grad for p in t.encoder.parameters())
    check_env_specs(env, seed=0)
    td = env.rollout(4)
    for size in (32, 24):
        est = td["next", f"estimate{size}"]
        assert est.shape == (td.shape[0], 3)
        torch.testing.assert_close(est, t.encoder(td["next", f"pixels{size}"]))
    assert not torch.equal(td["next", "estimate32"], td["next", "estimate24"])  # one estimate per camera
    env.close()


def test_parallel_gym_mujoco_env():
    # inside the workers: the pickled, still uninitialised lazy encoder on both keys; outside, on the
    # batched env: a second lazy encoder on one key, as a user would add it on top of a ParallelEnv
    par = ParallelEnv(2, functools.partial(make_gym_mujoco_env, functools.partial(LazyEncoder, out_dim=3)),
                      mp_start_method="spawn")
    outside = EncoderTransform(LazyEncoder(out_dim=5), in_keys=["pixels32"], out_keys=["outside"])
    env = TransformedEnv(par, outside)
    try:
        spec = env.observation_spec
        assert spec["estimate32"].shape == (2, 3) and spec["estimate24"].shape == (2, 3)
        assert spec["outside"].shape == (2, 5)
        check_env_specs(env, seed=0)
        td = env.rollout(3)
        assert td["next", "outside"].shape == (2, 3, 5) and td["next", "estimate24"].shape == (2, 3, 3)
        torch.testing.assert_close(td["next", "outside"], outside.encoder(td["next", "pixels32"].flatten(0, 1)).unflatten(0, (2, 3)))
        assert torch.isfinite(td["next", "estimate32"]).all()
    finally:
        if not par.is_closed:
            par.close()


def test_key_arguments_are_checked():
    enc = LazyEncoder()
    assert EncoderTransform(enc, in_keys="rgb", out_keys=("agent", "estimate")).out_keys == [("agent", "estimate")]  # as TorchRL
    with pytest.raises(ValueError, match="in_keys is empty"):
        EncoderTransform(enc, in_keys=[])
    with pytest.raises(ValueError, match="several in_keys"):
        EncoderTransform(enc, in_keys=["a", "b"])
    with pytest.raises(ValueError, match="differ in length"):
        EncoderTransform(enc, in_keys=["a", "b"], out_keys=["x"])
    with pytest.raises(ValueError, match="repeat"):
        EncoderTransform(enc, in_keys=["a", "b"], out_keys=["x", "x"])
    t = EncoderTransform(torch.nn.Sequential(torch.nn.Flatten(1), torch.nn.LazyLinear(4)), out_dim=3)
    with pytest.raises(RuntimeError, match=r"4 features for 'pixels', expected out_dim=3"):
        t.encode(torch.zeros(2, 8, 8, 3))
