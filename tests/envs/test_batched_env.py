"""Batched envs: a ParallelEnv of the tasks plays the same steps as a SerialEnv; its wait for the
workers sleeps, and reports a dead worker or a timeout."""
import time

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from trakdis.envs import close_env, make_batched_env
from trakdis.envs.batched import SleepWaitParallelEnv


def test_parallel_batched_env_matches_serial():
    rollouts = []
    for parallel in (False, True):
        env = make_batched_env("ClothFoldDiagonalUnpinned", num_envs=2, parallel=parallel, seed=3, env_kwargs={"horizon": 4})
        assert isinstance(env, SleepWaitParallelEnv) == parallel
        try:
            torch.manual_seed(0)
            rollouts.append(env.rollout(4, break_when_any_done=False))
            if parallel:
                check_env_specs(env)  # the shared buffers hold what the specs say
        finally:
            close_env(env)
    serial, parallel = rollouts
    assert parallel.batch_size == serial.batch_size == torch.Size([2, 4])
    torch.testing.assert_close(parallel["state"], serial["state"])
    torch.testing.assert_close(parallel["next", "reward"], serial["next", "reward"])


class _Worker:
    def __init__(self, alive=True):
        self.alive = alive

    def is_alive(self):
        return self.alive


def _waiting_env(flags, alive=(True, True), timeout=5.0):
    """A SleepWaitParallelEnv with only what ``_wait_for_workers`` reads (no worker processes)."""
    env = object.__new__(SleepWaitParallelEnv)
    env.__dict__.update(_use_buffers=True, _shm_done_flags=flags, _worker_indices=[0, 1], poll_interval=1e-4,
                        _workers=[_Worker(a) for a in alive], BATCHED_PIPE_TIMEOUT=timeout, _shutdown_workers=lambda: None)
    return env


def test_sleep_wait_returns_when_the_workers_are_done_and_clears_their_flags():
    import threading

    flags = [0, 0]
    env = _waiting_env(flags)
    threading.Timer(0.02, lambda: flags.__setitem__(0, 1)).start()
    threading.Timer(0.04, lambda: flags.__setitem__(1, 1)).start()
    t0 = time.process_time()
    start = time.monotonic()
    env._wait_for_workers(range(2))
    assert time.monotonic() - start >= 0.035  # it waited for the second worker
    assert flags == [0, 0]
    assert time.process_time() - t0 < 0.03  # slept, did not spin for those 40 ms


def test_sleep_wait_names_a_dead_worker_and_times_out():
    with pytest.raises(RuntimeError, match="worker 1 dead"):
        _waiting_env([1, 0], alive=(True, False))._wait_for_workers(range(2))
    with pytest.raises(RuntimeError, match="time limit"):
        _waiting_env([0, 0], timeout=0.05)._wait_for_workers(range(2))
