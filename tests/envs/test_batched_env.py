"""Batched envs: a ParallelEnv of the tasks plays the same steps as a SerialEnv."""
import torch

from trakdis.envs import close_env, make_batched_env


def test_parallel_batched_env_matches_serial():
    rollouts = []
    for parallel in (False, True):
        env = make_batched_env("ClothFoldDiagonalUnpinned", num_envs=2, parallel=parallel, seed=3, env_kwargs={"horizon": 4})
        try:
            torch.manual_seed(0)
            rollouts.append(env.rollout(4, break_when_any_done=False))
        finally:
            close_env(env)
    serial, parallel = rollouts
    assert parallel.batch_size == serial.batch_size == torch.Size([2, 4])
    torch.testing.assert_close(parallel["state"], serial["state"])
    torch.testing.assert_close(parallel["next", "reward"], serial["next", "reward"])
