"""run_episodes on TorchRL collectors plays the episodes that env.rollout played: the same initial
configurations (seeded), the same resets of a stateful policy, the same first-done cut; a
MultiSyncCollector of one process per env plays them too, and leaves no process behind."""
import functools
import multiprocessing

import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import SerialEnv, StepCounter, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from trakdis.evaluation import run_episodes, split_episodes, worker_env_fns
from walk_env import Walk

Drift = functools.partial(Walk, random_start=True)  # a seeded random start at each reset





def make(h=5, unstable_at=None):
    return TransformedEnv(Drift(unstable_at), StepCounter(max_steps=h))


class Counting(TensorDictModuleBase):
    """A stateful policy: a per-env counter cleared where ``step_count == 0`` (as the DT acting
    wrapper clears its context) enters the action, so a missed or extra reset changes the episode."""

    in_keys = ["state", "step_count"]
    out_keys = ["action"]

    def __init__(self):
        super().__init__()
        self.count = None

    def forward(self, td):
        sc = td["step_count"]
        if self.count is None or self.count.shape != sc.shape:
            self.count = torch.zeros(sc.shape)
        self.count = torch.where(sc == 0, torch.zeros_like(self.count), self.count + 1)
        td["action"] = (-0.3 * td["state"] + 0.05 * self.count).clamp(-1, 1)
        return td


def rollout_reference(env, policy, num_episodes, max_steps, seed, deterministic=True):
    """run_episodes before the collectors: env.rollout rounds with a fresh reset, first-done cut."""
    mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    env.set_seed(seed)
    episodes = []
    with torch.no_grad(), set_exploration_type(mode):
        while len(episodes) < num_episodes:
            episodes += split_episodes(env.rollout(max_steps, policy, break_when_any_done=False, auto_reset=True))
    return episodes[:num_episodes]


def assert_same_episodes(reference, res, keys=("state", "action", ("next", "reward")), exact=True):
    assert len(res.episodes) == len(reference)
    assert res.lengths.tolist() == [ep.shape[0] for ep in reference]
    finals = [float(ep["next", "normalized_performance"][-1].reshape(-1)[0]) for ep in reference]
    returns = [float(ep["next", "reward"].sum()) for ep in reference]
    tol = {"rtol": 0, "atol": 0} if exact else {"rtol": 1e-4, "atol": 1e-5}
    np.testing.assert_allclose(res.final_performance, finals, **tol)
    np.testing.assert_allclose(res.returns, returns, **tol)
    for ref, ep in zip(reference, res.episodes):
        for key in keys:
            torch.testing.assert_close(ep[key], ref[key], **tol)


CASES = {  # name: (env factory, episodes, max_steps)
    "horizon_steps": (lambda: SerialEnv(2, functools.partial(make, 5)), 5, 5),  # 3 batches, the last one half used
    "shorter_than_horizon": (lambda: SerialEnv(2, functools.partial(make, 10)), 4, 4),  # no env done: all reset
    "mixed_ends": (lambda: SerialEnv(2, [functools.partial(make, 4), functools.partial(make, 10)]), 6, 4),
    "early_end": (lambda: SerialEnv(2, functools.partial(make, 10, unstable_at=3)), 4, 10),
    "single_env": (lambda: make(5), 3, 5),
    "single_env_shorter": (lambda: make(10), 3, 4),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_collector_plays_the_episodes_of_env_rollout(case):
    factory, n, steps = CASES[case]
    reference = rollout_reference(factory(), Counting(), n, steps, seed=7)
    env = factory()
    res = run_episodes(env, Counting(), n, max_steps=steps, keep_episodes=True, desc=None, seed=7)
    assert_same_episodes(reference, res)
    assert "collector" not in res.episodes[0].keys()
    # the same seed again on the same env: the same configurations; another seed: others
    again = run_episodes(env, Counting(), n, max_steps=steps, desc=None, seed=7)
    np.testing.assert_array_equal(again.final_performance, res.final_performance)
    other = run_episodes(env, Counting(), n, max_steps=steps, desc=None, seed=8)
    assert not np.array_equal(other.final_performance, res.final_performance)


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_paused_episode_stream_continues_the_same_episodes(case):
    """EpisodeStream: taken in pieces of 1, 2, ... episodes, with another stream on its own env played
    between them, the episodes of one run_episodes call (early ends and half-used batches included)."""
    from trakdis.evaluation import EpisodeStream, episode_score

    factory, n, steps = CASES[case]
    reference = run_episodes(factory(), Counting(), n + 2, max_steps=steps, keep_episodes=True, desc=None, seed=7)
    env, other_env = factory(), factory()
    taken, piece = [], 1
    with EpisodeStream(env, Counting(), max_steps=steps, seed=7) as stream, \
            EpisodeStream(other_env, Counting(), max_steps=steps, seed=8) as other:
        while len(taken) < n + 2:
            taken += [next(stream) for _ in range(min(piece, n + 2 - len(taken)))]
            next(other)
            piece += 1
        assert stream.num_envs == (1 if case.startswith("single") else 2)
    assert [episode_score(ep) for ep in taken] == reference.final_performance.tolist()
    for ref, ep in zip(reference.episodes, taken):
        for key in ("state", "action", ("next", "reward")):
            torch.testing.assert_close(ep[key], ref[key], rtol=0, atol=0)
    assert case.startswith("single") or not env.is_closed  # the caller's env, as with run_episodes
    with pytest.raises(RuntimeError, match="after close"):
        next(stream)
    stream.close()  # idempotent
    env.close()
    other_env.close()


def test_collector_leaves_the_env_open_and_the_thread_count():
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        env = SerialEnv(2, functools.partial(make, 5))
        run_episodes(env, Counting(), 2, max_steps=5, desc=None, seed=0)
        assert not env.is_closed and torch.get_num_threads() == 1
        env.rollout(2, Counting())  # still usable
        env.close()
    finally:
        torch.set_num_threads(before)


def test_unknown_collector_is_refused():
    with pytest.raises(ValueError, match="collector must be one of"):
        run_episodes(make(3), Counting(), 1, max_steps=3, desc=None, collector="gpu_cluster")


def test_worker_env_fns_rebuild_the_sub_envs_with_the_transforms():
    from trakdis.transforms import ReturnToGo

    batched = TransformedEnv(SerialEnv(2, [functools.partial(make, 4), functools.partial(make, 6)]), ReturnToGo(-2.0))
    fns = worker_env_fns(batched)
    assert len(fns) == 2 and batched.is_closed  # never started
    env = fns[1]()
    assert env.batch_size == () and "return_to_go" in env.observation_spec.keys()
    assert env.rollout(10, Counting(), break_when_any_done=True).shape == (6,)
    assert worker_env_fns([make, make]) == [make, make]
    with pytest.raises(TypeError, match="SerialEnv/ParallelEnv"):
        worker_env_fns(make(3))


def _tiny_teacher(horizon):
    from trakdis.envs import task_spec
    from trakdis.modules import make_dt_actor
    from trakdis.modules import DTModelConfig
    from trakdis.policies import PolicyHandle
    from torchrl.envs import ObservationNorm

    torch.manual_seed(0)
    spec = task_spec("ClothFold", horizon=horizon)
    dt_cfg = DTModelConfig(embed_dim=16, n_layer=1, n_head=1, context_len=3).for_task(spec.state_dim, spec.action_dim, horizon)
    actor = make_dt_actor(dt_cfg, observation_key="state")
    normalizer = ObservationNorm(torch.zeros(spec.state_dim), torch.full((spec.state_dim,), 0.1), in_keys=["state"],
                                 standard_normal=True)
    return PolicyHandle("teacher", "ClothFold", horizon, actor=actor.eval(), observation_key="state", target_return=-1.0,
                        normalizer=normalizer)


@pytest.mark.parametrize("kind", ["expert", "teacher"])
def test_collector_plays_the_episodes_of_env_rollout_on_clothfold(kind):
    """A real task: the scripted expert and a (random) DT teacher with its acting wrapper, 2 envs,
    2 batches (the second started by the collector's own resets)."""
    from trakdis.envs import close_env
    from trakdis.policies import load_policy

    handle = load_policy("expert", task="ClothFold", horizon=4) if kind == "expert" else _tiny_teacher(4)
    envs = [handle.make_env(num_envs=2, split="eval") for _ in range(2)]
    try:
        reference = rollout_reference(envs[0], handle.make_policy(seed=0), 3, 4, seed=11)
        res = run_episodes(envs[1], handle.make_policy(seed=0), 3, max_steps=4, keep_episodes=True, desc=None, seed=11)
    finally:
        for env in envs:
            close_env(env)
    assert_same_episodes(reference, res)


def test_multi_sync_collector_plays_the_same_episodes_and_shuts_down():
    """2 processes, each with its own ClothFold env and copy of the policy: the episodes of the
    single-process collector (the same seeded configurations), with every env reset by run_episodes
    between batches. No process is left and the thread count is kept. (A DT teacher's weights
    reaching the processes: tests/recipes/test_online_collectors.py.)"""
    from trakdis.envs import close_env
    from trakdis.policies import load_policy

    expert = load_policy("expert", task="ClothFold", horizon=5)
    threads = torch.get_num_threads()
    for handle, steps, exact in ((expert, 3, True),):
        env = handle.make_env(num_envs=2, split="eval")
        try:
            single = run_episodes(env, handle.make_policy(seed=0), 4, max_steps=steps, keep_episodes=True, desc=None,
                                  seed=5)
        finally:
            close_env(env)
        env = handle.make_env(num_envs=2, split="eval", parallel=True)
        multi = run_episodes(env, handle.make_policy(seed=0), 4, max_steps=steps, keep_episodes=True, desc=None,
                             seed=5, collector="multi_sync")
        assert env.is_closed  # only described the processes' envs
        assert multi.num_envs == 2 and len(multi.episodes) == 4
        # batched vs one-row forward passes of the DT may differ in the last bits
        assert_same_episodes(single.episodes, multi, exact=exact)
        assert not multiprocessing.active_children()
        assert torch.get_num_threads() == threads


def test_ray_collector_plays_the_same_episodes():
    """--collector ray: a RayCollector of 2 Ray actors (a local 2-CPU Ray), each a Collector with its own ClothFold
    env and copy of the policy: the single-process collector's episodes, value for value, with the envs reset
    between batches (3 episodes on 2 envs: two batches)."""
    ray = pytest.importorskip("ray")
    from trakdis.envs import close_env
    from trakdis.policies import load_policy

    expert = load_policy("expert", task="ClothFold", horizon=3)
    env = expert.make_env(num_envs=2, split="eval")
    try:
        single = run_episodes(env, expert.make_policy(seed=0), 3, max_steps=3, keep_episodes=True, desc=None, seed=5)
    finally:
        close_env(env)
    ray.init(num_cpus=2, include_dashboard=False, object_store_memory=100 * 2**20)
    try:
        env = expert.make_env(num_envs=2, split="eval")
        res = run_episodes(env, expert.make_policy(seed=0), 3, max_steps=3, keep_episodes=True, desc=None, seed=5,
                           collector="ray")
    finally:
        ray.shutdown()
    assert res.num_envs == 2 and len(res.episodes) == 3
    assert_same_episodes(single.episodes, res, exact=True)
