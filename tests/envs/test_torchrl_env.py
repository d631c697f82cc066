"""TorchRL factory: specs, batched envs, collectors, keys of docs/design.md."""

import functools

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.envs import ParallelEnv, SerialEnv
from torchrl.envs.utils import check_env_specs

from trakdis.envs import TASKS, ExpertPolicy, make_env, task_spec


@pytest.mark.parametrize("task", TASKS)
def test_check_env_specs_single(task):
    env = make_env(task, seed=0, horizon=5)
    check_env_specs(env)
    spec = task_spec(task)
    td = env.rollout(6, ExpertPolicy(task), break_when_any_done=True)
    assert td.shape == (5,)
    assert td["state"].shape == (5, spec.state_dim) and td["state"].dtype == torch.float32
    assert td["action"].shape == (5, spec.action_dim)
    assert td["next", "reward"].shape == (5, 1) and td["next", "reward"].dtype == torch.float32
    assert td["next", "normalized_performance"].dtype == torch.float32
    assert td["next", "sim_unstable"].dtype == torch.bool
    assert td["step_count"].dtype == torch.int64
    assert td["step_count"].squeeze(-1).tolist() == [0, 1, 2, 3, 4]
    assert td["next", "truncated"].squeeze(-1).tolist() == [False] * 4 + [True]
    assert not td["next", "terminated"].any()
    assert "pixels" not in td.keys()
    # reward is the performance; normalized performance is (perf - perf0) / -perf0
    assert (td["next", "reward"] <= 0).all()


def test_pixels_key():
    env = make_env("ClothFold", from_pixels=True, image_size=40, seed=0, horizon=3)
    check_env_specs(env)
    td = env.reset()
    assert td["pixels"].shape == (40, 40, 3) and td["pixels"].dtype == torch.uint8
    assert td["state"].shape == (18,)


def test_seeded_factory_is_deterministic():
    a = make_env("ClothFoldDiagonalUnpinned", seed=7, horizon=4).rollout(4, ExpertPolicy("ClothFoldDiagonalUnpinned"))
    b = make_env("ClothFoldDiagonalUnpinned", seed=7, horizon=4).rollout(4, ExpertPolicy("ClothFoldDiagonalUnpinned"))
    assert torch.equal(a["next", "state"], b["next", "state"])


def test_serial_env():
    env = SerialEnv(2, functools.partial(make_env, "ClothFoldDiagonalPinned", horizon=4))
    try:
        check_env_specs(env)
        env.set_seed(0)
        td = env.rollout(6, ExpertPolicy("ClothFoldDiagonalPinned"), break_when_any_done=False)
        assert td.shape == (2, 6)
        assert td["step_count"][0].squeeze(-1).tolist() == [0, 1, 2, 3, 0, 1]  # auto reset
    finally:
        env.close()


def test_parallel_env_and_collector():
    make = functools.partial(make_env, "ClothFold", from_pixels=True, horizon=4)
    env = ParallelEnv(2, make)
    try:
        check_env_specs(env)
        td = env.rollout(3, ExpertPolicy("ClothFold"), break_when_any_done=False)
        assert td["pixels"].shape == (2, 3, 32, 32, 3)
        assert td["normalized_performance"].shape == (2, 3, 1)
    finally:
        env.close()
    collector = Collector(make, ExpertPolicy("ClothFold", noise=0.2, seed=0), frames_per_batch=6,
                          total_frames=12, auto_register_policy_transforms=False)
    try:
        batches = list(collector)
    finally:
        collector.shutdown()
    assert len(batches) == 2 and batches[0].numel() == 6
    assert batches[0]["next", "sim_unstable"].dtype == torch.bool


def test_unknown_task():
    with pytest.raises(ValueError, match="expected one of"):
        make_env("ClothFlip")
