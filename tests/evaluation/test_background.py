"""BackgroundEvaluation: the same episodes and numbers as an in-process evaluation; errors come back."""
import numpy as np
import pytest

from trakdis.envs import close_env
from trakdis.evaluation import BackgroundEvaluation, run_episodes
from trakdis.policies import load_policy


def test_background_expert_matches_in_process_parallel_evaluation():
    job = BackgroundEvaluation("expert", task="ClothFold", horizon=3, num_episodes=3, num_envs=2, env_seed=5,
                               policy_seed=0, nice=0)
    handle = load_policy("expert", task="ClothFold", horizon=3)
    env = handle.make_env(num_envs=2, split="eval")  # SerialEnv: the episodes of online_dt.py's ParallelEnv
    # (test_episodes.py::test_parallel_workers_play_the_same_episodes_as_serial_envs)
    try:
        here = run_episodes(env, handle.make_policy(seed=0), 3, max_steps=3, desc=None, seed=5)
    finally:
        close_env(env)
    there = job.result()
    assert job.done() and job.cpu_seconds > 0 and job.wall_seconds > 0
    np.testing.assert_array_equal(there.final_performance, here.final_performance)
    np.testing.assert_array_equal(there.returns, here.returns)
    assert there.final_performance.shape == (3,)


def test_background_error_names_the_file(tmp_path):
    missing = tmp_path / "no_such_policy.pt"
    with pytest.raises(FileNotFoundError, match="no_such_policy.pt"):
        BackgroundEvaluation(missing, task="ClothFold", horizon=3, num_episodes=1)


def test_background_rejects_bad_counts():
    with pytest.raises(ValueError, match="num_episodes"):
        BackgroundEvaluation("expert", task="ClothFold", horizon=3, num_episodes=0)
