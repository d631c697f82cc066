import functools
import pickle

import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import SerialEnv, TransformedEnv, check_env_specs
from torchrl.envs.utils import RandomPolicy
from torchrl.testing.mocking_classes import ContinuousActionConvMockEnvNumpy

from toy_pixel_env import TinyEncoder, make_toy_env
from trakdis.transforms import EncoderTransform


def test_single_env_spec_and_values():
    enc = TinyEncoder(out_dim=5)
    env = TransformedEnv(make_toy_env(size=16), EncoderTransform(enc))
    spec = env.observation_spec["state_estimate"]
    assert spec.shape == (5,) and spec.dtype == torch.float32
    check_env_specs(env, seed=0)
    td = env.rollout(4)
    assert td["state_estimate"].shape == (4, 5) and td["next", "state_estimate"].shape == (4, 5)
    torch.testing.assert_close(td["state_estimate"], enc(td["pixels"]))
    assert not td["state_estimate"].requires_grad
    assert all(not p.requires_grad for p in enc.parameters()) and not enc.training


def test_torchrl_mock_env_float_pixels():
    # a TorchRL env that is not ours at all: float channels-last 7x7x3 pixels
    base = ContinuousActionConvMockEnvNumpy()
    env = TransformedEnv(base, EncoderTransform(TinyEncoder(out_dim=3), out_keys=["latent"]))
    assert env.observation_spec["latent"].shape == (3,)
    check_env_specs(env, seed=0)
    assert env.rollout(3)["next", "latent"].shape == (3, 3)


def test_no_grad_chunking_and_train_mode():
    enc = TinyEncoder(out_dim=4)
    t = EncoderTransform(enc, freeze=False, max_batch=3)
    pix = torch.randint(0, 256, (2, 5, 16, 16, 3), dtype=torch.uint8)
    out = t._apply_transform(pix)
    assert out.shape == (2, 5, 4) and not out.requires_grad
    assert enc.calls == 4  # 10 images in chunks of 3
    t_big = EncoderTransform(enc, freeze=False)
    torch.testing.assert_close(t_big._apply_transform(pix), out)
    t.train()
    assert not enc.training


def test_env_device_moves_do_not_touch_the_encoder():
    enc = TinyEncoder(out_dim=4)
    t = EncoderTransform(enc)
    env = TransformedEnv(make_toy_env(size=16), t)
    env.to("cpu")
    t.to(torch.float64)
    assert all(p.dtype == torch.float32 for p in enc.parameters())
    assert t.encoder is enc and not any("conv" in k for k in t.state_dict())
    t2 = pickle.loads(pickle.dumps(t))
    pix = torch.randint(0, 256, (3, 16, 16, 3), dtype=torch.uint8)
    torch.testing.assert_close(t2._apply_transform(pix), t._apply_transform(pix))


def test_bad_encoder_output_is_reported():
    t = EncoderTransform(torch.nn.Flatten(0))
    with pytest.raises(RuntimeError, match="pixels"):
        t._apply_transform(torch.zeros(2, 4, 4, 3))
    env = TransformedEnv(make_toy_env(size=16), EncoderTransform(TinyEncoder(), in_keys=["rgb"]))
    with pytest.raises(KeyError, match="rgb"):
        env.observation_spec


def test_serial_env_and_collector():
    torch.manual_seed(0)
    t = EncoderTransform(TinyEncoder(out_dim=4))
    pickle.loads(pickle.dumps(t))
    serial = TransformedEnv(SerialEnv(2, functools.partial(make_toy_env, size=16)), t)
    check_env_specs(serial, seed=0)
    # collector over the batched env: episodes end at different times (partial resets)
    col = Collector(serial, RandomPolicy(serial.action_spec), frames_per_batch=20, total_frames=20)
    batch = next(iter(col))
    col.shutdown()
    assert batch["state_estimate"].shape == (2, 10, 4)
    torch.testing.assert_close(batch["next", "state_estimate"], t.encoder(batch["next", "pixels"].flatten(0, 1)).unflatten(0, (2, 10)))


def test_replay_buffer_windows():
    t = EncoderTransform(TinyEncoder(out_dim=4))
    rb = ReplayBuffer(storage=LazyTensorStorage(10), transform=t, batch_size=3)
    data = TensorDict({"pixels": torch.randint(0, 256, (10, 6, 16, 16, 3), dtype=torch.uint8)}, [10])
    rb.extend(data)
    sample = rb.sample()
    assert sample["state_estimate"].shape == (3, 6, 4)
    torch.testing.assert_close(sample["state_estimate"], t.encoder(sample["pixels"].flatten(0, 1)).unflatten(0, (3, 6)))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_encoder_on_other_device_cpu_env():
    enc = TinyEncoder(out_dim=4).cuda()
    env = TransformedEnv(make_toy_env(size=16), EncoderTransform(enc))
    check_env_specs(env, seed=0)
    td = env.rollout(3)
    assert td["state_estimate"].device.type == "cpu"
    torch.testing.assert_close(td["state_estimate"], enc(td["pixels"].cuda()).cpu())
