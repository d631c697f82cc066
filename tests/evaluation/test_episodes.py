import numpy as np
import pandas as pd
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.data import Composite, Unbounded
from torchrl.envs import SerialEnv, StepCounter, TransformedEnv

from trakdis.evaluation import run_episodes, split_episodes, summarize, write_summary_table
from walk_env import Walk





def make(h=5, **kw):
    return TransformedEnv(Walk(**kw), StepCounter(max_steps=h))


policy = TensorDictModule(lambda s: torch.full_like(s, 0.5), in_keys=["state"], out_keys=["action"])


def test_run_episodes_batched_and_truncated_count():
    env = SerialEnv(2, make)
    res = run_episodes(env, policy, 3, max_steps=5, keep_episodes=True, desc=None)
    env.close()
    assert res.final_performance.tolist() == [2.5] * 3  # 5 steps of +0.5
    assert res.lengths.tolist() == [5] * 3 and not res.unstable.any()
    assert res.returns == pytest.approx([-(0.5 + 1 + 1.5 + 2 + 2.5)] * 3)
    assert len(res.episodes) == 3 and res.episodes[0].shape == (5,)


def test_early_end_uses_first_done():
    res = run_episodes(make(h=10, unstable_at=3), policy, 2, max_steps=10, desc=None)
    assert res.lengths.tolist() == [3, 3] and res.unstable.all()
    assert res.final_performance.tolist() == [1.5, 1.5]


def test_missing_key_is_named():
    env = TransformedEnv(Walk(), StepCounter(max_steps=3))
    env.base_env.observation_spec = Composite(state=Unbounded(shape=(1,)))

    def bad_reset(td):
        return TensorDict(state=torch.zeros(1), done=torch.zeros(1, dtype=torch.bool), terminated=torch.zeros(1, dtype=torch.bool))

    def bad_step(td):
        return TensorDict(state=td["state"], reward=torch.zeros(1), done=torch.zeros(1, dtype=torch.bool), terminated=torch.zeros(1, dtype=torch.bool))

    env.base_env._reset, env.base_env._step = bad_reset, bad_step
    with pytest.raises(KeyError, match="normalized_performance"):
        run_episodes(env, policy, 1, max_steps=3, desc=None)


def test_split_episodes_drops_tail():
    done = torch.tensor([[False, True, False, False], [False, False, False, True]])
    td = TensorDict({"x": torch.arange(8).reshape(2, 4), ("next", "done"): done.unsqueeze(-1)}, batch_size=[2, 4])
    eps = split_episodes(td)
    assert [e.shape[0] for e in eps] == [2, 4]


def test_summary_and_tables(tmp_path):
    s = summarize([0.0, 1.0, 2.0, 3.0])
    assert s["mean"] == 1.5 and s["p50"] == 1.5 and s["p25"] == 0.75 and s["std"] == pytest.approx(np.std([0, 1, 2, 3]))
    with pytest.raises(ValueError):
        summarize([])
    frame = write_summary_table([{"task": "ClothFold", "policy": "expert", **s}], tmp_path / "t.csv", tmp_path / "t.md")
    assert list(frame.columns[:3]) == ["task", "policy", "n"]
    md = (tmp_path / "t.md").read_text().splitlines()
    assert md[0].startswith("| task | policy | n | mean") and "| ClothFold | expert | 4 | 1.500 |" in md[2]
    assert pd.read_csv(tmp_path / "t.csv")["mean"].iloc[0] == 1.5


def test_close_env_keeps_thread_count():
    from trakdis.envs import close_env

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        env = SerialEnv(2, make)
        env.rollout(2, policy)
        close_env(env)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_close_env_never_masks_the_original_error():
    """close_env in a finally on an env that never started (the error came before its first reset)
    used to raise "trying to close a closed environment" over the real error."""
    from trakdis.envs import close_env

    env = SerialEnv(2, make)
    assert env.is_closed  # TorchRL starts it at the first reset
    with pytest.raises(ValueError, match="the real error"):
        try:
            raise ValueError("the real error")
        finally:
            close_env(env)
    with pytest.raises(KeyboardInterrupt):  # Ctrl-C stays Ctrl-C
        try:
            raise KeyboardInterrupt
        finally:
            close_env(env)
    close_env(env)  # never started, no error in flight: nothing to do
    env.rollout(2, policy)
    close_env(env)
    close_env(env)  # closing twice is harmless

    class Failing:
        is_closed = False

        def close(self):
            raise RuntimeError("close failed")

    with pytest.warns(RuntimeWarning, match="close failed.*ValueError"):
        with pytest.raises(ValueError, match="the real error"):
            try:
                raise ValueError("the real error")
            finally:
                close_env(Failing())
    with pytest.raises(RuntimeError, match="close failed"):  # alone, a failing close is an error
        close_env(Failing())


def test_standard_error_and_paired_difference():
    from trakdis.evaluation import paired_difference, standard_error

    assert standard_error([1.0, 2.0, 3.0, 4.0]) == pytest.approx(np.std([1, 2, 3, 4], ddof=1) / 2)
    assert standard_error([0.5]) == 0.0
    with pytest.raises(ValueError):
        standard_error([])
    # the same configurations: a constant gain has no error, however spread the scores are
    before = np.array([0.0, 0.9, 0.2, 0.7])
    assert paired_difference(before, before + 0.1) == pytest.approx((0.1, 0.0))
    mean, se = paired_difference([0.0, 0.0, 0.0], [0.1, 0.2, 0.3])
    assert mean == pytest.approx(0.2) and se == pytest.approx(standard_error([0.1, 0.2, 0.3]))
    with pytest.raises(ValueError, match="not paired"):
        paired_difference([0.0, 1.0], [0.0])


def test_race_survivors_drops_only_the_clearly_worse():
    from trakdis.evaluation import race_survivors

    leader = [0.8, 0.6, 0.9, 0.7]
    scores = {"a": leader, "far": [s - 0.3 for s in leader], "close": [0.8, 0.7, 0.8, 0.6], "b": leader}
    assert race_survivors(scores) == ["a", "close", "b"]  # a constant gap has no error: "far" stops
    assert race_survivors(scores, margin=0.0) == ["a", "b"]  # ties with the leader stay
    # the episodes all have played: a longer list is cut to the shortest; one episode gives no error yet
    assert race_survivors({0: [1.0, 0.0, 0.0], 1: [0.0]}) == [0, 1]
    assert race_survivors({0: [1.0, 1.0, 0.0], 1: [0.0, 0.0]}) == [0]
    assert race_survivors({}) == []
    with pytest.raises(ValueError, match="margin"):
        race_survivors(scores, margin=-1)


def test_results_report_their_rate():
    env = SerialEnv(2, make)
    res = run_episodes(env, policy, 4, max_steps=5, desc=None)
    env.close()
    assert res.num_envs == 2 and res.seconds > 0
    assert res.rate().startswith("4 episodes in ") and "2 envs" in res.rate() and "steps/s per env" in res.rate()


def test_parallel_workers_play_the_same_episodes_as_serial_envs():
    """ParallelEnv (worker processes) and SerialEnv of the same size, same seed: the same episodes,
    value for value; another seed plays other configurations."""
    from trakdis.envs import close_env
    from trakdis.policies import load_policy

    expert = load_policy("expert", task="ClothFold", horizon=4)
    results = {}
    for parallel, runs in ((False, (("serial", 3),)), (True, (("parallel", 3), ("parallel_other_seed", 4)))):
        env = expert.make_env(num_envs=2, split="eval", parallel=parallel)  # one env per mode: workers start once
        try:
            for name, seed in runs:
                results[name] = run_episodes(env, expert.make_policy(seed=0), 3, max_steps=4, keep_episodes=True,
                                             desc=None, seed=seed)
        finally:
            close_env(env)
    a, b, c = results["serial"], results["parallel"], results["parallel_other_seed"]
    assert b.num_envs == 2 and len(b.episodes) == 3
    np.testing.assert_array_equal(a.final_performance, b.final_performance)
    np.testing.assert_array_equal(a.returns, b.returns)
    for ea, eb in zip(a.episodes, b.episodes):
        torch.testing.assert_close(ea["state"], eb["state"], rtol=0, atol=0)
        torch.testing.assert_close(ea["action"], eb["action"], rtol=0, atol=0)
    assert not torch.equal(a.episodes[0]["state"][0], c.episodes[0]["state"][0])


def test_pick_candidate_keeps_the_first_unless_another_is_measurably_better():
    from trakdis.evaluation import pick_candidate

    first = [0.8, 0.7, 0.9, 0.75, 0.85]
    collapsed = [0.1, 0.2, 0.0, 0.3, 0.15]
    assert pick_candidate([first]) == 0
    assert pick_candidate([collapsed, first, collapsed]) == 1  # clearly better: replaces the default
    assert pick_candidate([collapsed, first, [x + 0.01 for x in first]]) == 2  # the best of the others
    assert pick_candidate([first, collapsed]) == 0
    noisy = [0.85, 0.65, 0.95, 0.7, 0.9]  # a higher mean (+0.01) within one standard error: the default stays
    assert np.mean(noisy) > np.mean(first) and pick_candidate([first, noisy]) == 0
    assert pick_candidate([first, noisy], margin=0.0) == 1
    assert pick_candidate([first, list(first)]) == 0  # ties: the earlier one
    with pytest.raises(ValueError, match="no candidates"):
        pick_candidate([])
    with pytest.raises(ValueError, match="margin"):
        pick_candidate([first], margin=-1)
    with pytest.raises(ValueError, match="not paired"):
        pick_candidate([first, first[:3] + [1.0]])


def test_read_final_scores_keeps_the_noise_free_episodes_in_order(tmp_path):
    from trakdis.evaluation import read_final_scores

    pd.DataFrame({"episode": [0, 1, 0, 1], "state_noise": [0.0, 0.0, 1e-3, 1e-3],
                  "final_normalized_performance": [0.5, 0.7, 0.1, 0.2]}).to_csv(tmp_path / "episodes.csv", index=False)
    np.testing.assert_array_equal(read_final_scores(tmp_path), [0.5, 0.7])
