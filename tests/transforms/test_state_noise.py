import functools
import pickle

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs import SerialEnv, TransformedEnv, check_env_specs

from toy_pixel_env import make_toy_env
from trakdis.transforms import StateNoise


def test_statistics_and_seed():
    x = torch.zeros(20000, 3)
    a = StateNoise(1e-3, seed=3)._apply_transform(x)
    b = StateNoise(1e-3, seed=3)._apply_transform(x)
    c = StateNoise(1e-3, seed=4)._apply_transform(x)
    torch.testing.assert_close(a, b)
    assert not torch.equal(a, c)
    assert a.mean().abs() < 5e-5 and abs(a.std().item() - 1e-3) < 5e-5
    assert torch.equal(StateNoise(0.0)._apply_transform(x + 1), x + 1)


def test_pickle_keeps_generator_state():
    t = StateNoise(0.1, in_keys=["s"], seed=0)
    t._apply_transform(torch.zeros(5))  # advance the generator
    t2 = pickle.loads(pickle.dumps(t))
    torch.testing.assert_close(t._apply_transform(torch.zeros(5)), t2._apply_transform(torch.zeros(5)))


def test_as_buffer_transform_and_errors():
    td = TensorDict({"state_estimate": torch.ones(4, 2, 3)}, [4, 2])
    out = StateNoise(0.5, seed=0)(td.clone())
    assert out["state_estimate"].shape == (4, 2, 3) and not torch.equal(out["state_estimate"], td["state_estimate"])
    with pytest.raises(ValueError, match="sigma"):
        StateNoise(-1.0)
    with pytest.raises(TypeError, match="floating"):
        StateNoise(0.1)._apply_transform(torch.zeros(3, dtype=torch.long))


def test_env_specs_single_and_serial():
    env = TransformedEnv(make_toy_env(size=8), StateNoise(1e-2, in_keys=["state"], out_keys=["noisy"], seed=0))
    check_env_specs(env, seed=0)
    td = env.rollout(3)
    assert (td["noisy"] - td["state"]).abs().max() > 0
    assert (td["noisy"] - td["state"]).abs().max() < 0.1
    serial = TransformedEnv(SerialEnv(2, functools.partial(make_toy_env, size=8)), StateNoise(1e-2, in_keys=["state"]))
    check_env_specs(serial, seed=0)
    bounded = Bounded(-1.0, 1.0, shape=(3,))
    assert not isinstance(StateNoise(0.1, in_keys=["x"]).transform_observation_spec(bounded), Bounded)


def test_shared_dims_draw_one_offset_per_window():
    """shared_dims=(-2,) on windows [B, K, D]: each window gets one offset, the same at its K steps; windows and
    dims differ; its std is sigma; a dim the tensor lacks is refused, naming the key and shape."""
    td = TensorDict({"state": torch.zeros(4000, 5, 3)}, [4000, 5])
    out = StateNoise(0.02, in_keys=["state"], seed=1, shared_dims=(-2,))(td.clone())["state"]
    assert torch.equal(out, out[:, :1].expand_as(out))  # constant over each window's steps
    offsets = out[:, 0]
    assert not torch.equal(offsets[0], offsets[1]) and not torch.equal(offsets[:, 0], offsets[:, 1])
    assert abs(offsets.std().item() - 0.02) < 1e-3 and offsets.mean().abs() < 1e-3
    iid = StateNoise(0.02, in_keys=["state"], seed=1)(td.clone())["state"]
    assert not torch.equal(iid, iid[:, :1].expand_as(iid))  # the default: i.i.d. per entry
    again = StateNoise(0.02, in_keys=["state"], seed=1, shared_dims=(-2,))(td.clone())["state"]
    torch.testing.assert_close(out, again)
    assert "shared_dims=(-2,)" in repr(StateNoise(0.1, shared_dims=(-2,)))
    with pytest.raises(ValueError, match=r"shared dim -3 of \['state'\] of shape \(7, 3\)"):
        StateNoise(0.1, in_keys=["state"], shared_dims=(-3,))._apply_transform(torch.zeros(7, 3))
