"""Episode rollouts and their summary, shared by the recipes (teacher/student evaluation, online
data collection, ``evaluate.py``).

:func:`run_episodes` rolls a policy out with a TorchRL collector (a ``Collector`` over a batched
environment, ``SerialEnv`` / ``ParallelEnv`` of ``N`` tasks or a single env, or a
``MultiSyncCollector`` of ``N`` processes) until ``num_episodes`` full episodes were played, and
returns per-episode results: the normalized performance at the episode's end (the paper's
metric), the return, the length, and optionally the rollout TensorDicts themselves (to insert
into a replay buffer or to render videos). :class:`EpisodeStream` hands the same episodes out one at a
time, so that a caller can pause a sequence and continue it later.
"""
from __future__ import annotations

import functools
import math
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal, Mapping, Sequence

import numpy as np
import pandas as pd
import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.batched_envs import BatchedEnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from trakdis.utils.checkpoint import atomic_write_bytes
from trakdis.utils.progress import progress
from trakdis.utils.video import side_by_side

__all__ = ["COLLECTORS", "CollectorName", "EpisodeResults", "EpisodeStream", "episode_frames", "episode_score", "markdown_table",
           "paired_difference", "pick_candidate", "race_survivors", "read_final_scores", "run_episodes",
           "split_episodes", "standard_error", "summarize", "worker_env_fns", "write_summary_table"]


@dataclass
class EpisodeResults:
    final_performance: np.ndarray
    """normalized performance at each episode's last step, shape [num_episodes]"""
    returns: np.ndarray
    lengths: np.ndarray
    unstable: np.ndarray
    """True where the physics blew up and the episode was truncated early"""
    episodes: list = field(default_factory=list)
    """one TensorDict of shape [length] per episode (only with keep_episodes=True)"""
    seconds: float = 0.0
    """wall-clock seconds the episodes took"""
    num_envs: int = 1
    """environments stepped together (worker processes with a ``ParallelEnv``)"""

    def summary(self) -> dict[str, float]:
        return summarize(self.final_performance)

    def rate(self) -> str:
        """``"40 episodes in 95.0 s, 2 envs: 0.21 episodes/s, 21 steps/s per env"``: the per-worker
        rate (with a ``ParallelEnv``, each env is one worker process)."""
        n, steps, s = len(self.final_performance), int(np.sum(self.lengths)), max(self.seconds, 1e-9)
        return (f"{n} episodes in {self.seconds:.1f} s, {self.num_envs} env{'s' if self.num_envs > 1 else ''}: "
                f"{n / s:.2f} episodes/s, {steps / s / self.num_envs:.1f} steps/s per env")


def summarize(values: Sequence[float] | np.ndarray) -> dict[str, float]:
    """``n``, ``mean``, ``std`` (population, as the paper's mean +- std), ``p25``, ``p50``, ``p75``, ``min``, ``max``."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 0:
        raise ValueError("summarize: no values")
    return {
        "n": int(v.size),
        "mean": float(v.mean()),
        "std": float(v.std()),
        "p25": float(np.percentile(v, 25)),
        "p50": float(np.percentile(v, 50)),
        "p75": float(np.percentile(v, 75)),
        "min": float(v.min()),
        "max": float(v.max()),
    }


def standard_error(values: Sequence[float] | np.ndarray) -> float:
    """Standard error of the mean, ``std / sqrt(n)`` with the sample std (``ddof=1``; 0 for one value)."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 0:
        raise ValueError("standard_error: no values")
    return float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else 0.0


def paired_difference(before: Sequence[float] | np.ndarray, after: Sequence[float] | np.ndarray) -> tuple[float, float]:
    """``(mean, standard error)`` of ``after - before`` over paired episodes (the same configurations
    played by two policies): the noise of the configurations cancels, so the difference is usually
    known better than either score."""
    a, b = np.asarray(before, dtype=np.float64).reshape(-1), np.asarray(after, dtype=np.float64).reshape(-1)
    if a.shape != b.shape:
        raise ValueError(f"paired_difference: {a.size} and {b.size} values are not paired")
    d = b - a
    return float(d.mean()), standard_error(d)


def read_final_scores(directory: str | Path) -> np.ndarray:
    """The per-episode final normalized performance of a ``recipes/evaluate.py`` run (its ``episodes.csv``),
    noise-free episodes only, in the order played."""
    episodes = pd.read_csv(Path(directory) / "episodes.csv")
    return episodes.loc[episodes["state_noise"] == 0, "final_normalized_performance"].to_numpy(float)


def pick_candidate(scores: Sequence[Sequence[float] | np.ndarray], *, margin: float = 1.0) -> int:
    """The index of the candidate to keep, from each candidate's per-episode scores of the same configurations
    (in the same order): the one with the highest mean if it beats candidate 0 (the default) by more than
    ``margin`` standard errors of the paired difference, else 0. Noise alone does not trade the default for
    another; a clearly better one replaces it (as :class:`~trakdis.training.SnapshotSelection` keeps snapshots)."""
    if not len(scores):
        raise ValueError("pick_candidate: no candidates")
    if margin < 0:
        raise ValueError(f"pick_candidate: margin must be >= 0, got {margin}")
    means = [float(np.mean(s)) for s in scores]
    best = max(range(len(scores)), key=lambda i: (means[i], -i))  # ties: the earlier candidate
    if best == 0:
        return 0
    gain, se = paired_difference(scores[0], scores[best])
    return best if gain > margin * se else 0


def race_survivors(scores: Mapping[Any, Sequence[float] | np.ndarray], *, margin: float = 2.0) -> list:
    """The keys of ``scores`` (policy -> per-episode scores of the same configurations, in the same order)
    still in a race after the episodes all of them have played: the leader (highest mean) and each one
    whose paired difference to the leader is within ``margin`` of its standard errors (all of them before
    two episodes). Racing (Maron and Moore 1994): a policy far behind after a few episodes plays no more,
    the close ones play on."""
    if margin < 0:
        raise ValueError(f"race_survivors: margin must be >= 0, got {margin}")
    if not scores:
        return []
    n = min(len(v) for v in scores.values())
    if n < 2:  # no standard error yet
        return list(scores)
    played = {k: np.asarray(v, dtype=np.float64)[:n] for k, v in scores.items()}
    leader = max(played, key=lambda k: played[k].mean())
    survivors = []
    for k, v in played.items():
        gap, se = paired_difference(v, played[leader])
        if k == leader or gap <= margin * se:
            survivors.append(k)
    return survivors


def _first_done(done: torch.Tensor) -> torch.Tensor:
    """Index of the first True along the last dim (or last index if none), for ``done`` [..., T]."""
    T = done.shape[-1]
    idx = torch.arange(T, device=done.device).expand_as(done)
    return torch.where(done, idx, torch.full_like(idx, T - 1)).min(-1).values


def split_episodes(rollout: TensorDictBase) -> list[TensorDictBase]:
    """Cut a ``[*B, T]`` rollout into the first complete episode of each batch entry.

    ``env.rollout(..., break_when_any_done=False)`` resets finished sub-environments and keeps
    stepping; everything after the first ``("next", "done")`` of an entry belongs to a later,
    incomplete episode and is dropped.
    """
    if rollout.batch_dims == 1:
        rollout = rollout.unsqueeze(0)
    flat = rollout.reshape(-1, rollout.shape[-1])
    done = flat.get(("next", "done")).reshape(flat.shape[0], flat.shape[-1])
    ends = _first_done(done)
    return [flat[i, : int(ends[i]) + 1] for i in range(flat.shape[0])]


CollectorName = Literal["sync", "multi_sync", "ray"]
"""How :func:`run_episodes` steps its environments (see its ``collector`` argument); the recipes' ``--collector``"""
COLLECTORS: tuple[str, ...] = CollectorName.__args__


def _build_worker_env(create_env_fn, create_env_kwargs, transform):
    env = create_env_fn(**create_env_kwargs)
    # auto_unwrap=False: the transforms stay on top of the sub-env's own, as on top of the batched env
    return env if transform is None else TransformedEnv(env, transform, auto_unwrap=False)


def worker_env_fns(env) -> list[Callable[[], EnvBase]]:
    """One constructor per sub-environment of a batched ``env`` (``SerialEnv``/``ParallelEnv``,
    optionally inside a ``TransformedEnv``): each builds that sub-environment with a copy of
    ``env``'s transforms on top. A sequence of constructors is returned as a list. ``env`` itself is
    not started."""
    # own code: TorchRL 0.14 has no helper for this; a batched env keeps one create_env_fn and
    # create_env_kwargs per worker (torchrl/envs/batched_envs.py), which MultiSyncCollector takes as is
    if not isinstance(env, EnvBase) and isinstance(env, Sequence):
        return list(env)
    base, transform = env, None
    if isinstance(env, TransformedEnv):
        base, transform = env.base_env, env.transform
    if not isinstance(base, BatchedEnvBase):
        raise TypeError(f"worker_env_fns: expected a SerialEnv/ParallelEnv (optionally in a TransformedEnv) or a "
                        f"sequence of env constructors, got {type(base).__name__}")
    return [functools.partial(_build_worker_env, base.create_env_fn[i], base.create_env_kwargs[i],
                              None if transform is None else transform.clone()) for i in range(base.num_workers)]


def _shutdown(collector, **kwargs) -> None:
    """``collector.shutdown(**kwargs)``; a failure while another exception propagates is only warned about."""
    in_flight = sys.exc_info()[1]
    try:
        collector.shutdown(**kwargs)
    except Exception as err:
        if in_flight is None:
            raise
        warnings.warn(f"run_episodes: shutting the collector down failed ({type(err).__name__}: {err}) while "
                      f"{type(in_flight).__name__} was being raised; raising that one", RuntimeWarning, stacklevel=2)


def run_episodes(
    env,
    policy: Callable[[TensorDictBase], TensorDictBase],
    num_episodes: int,
    *,
    max_steps: int,
    deterministic: bool = True,
    keep_episodes: bool = False,
    desc: str | None = "episodes",
    on_episode: Callable[[TensorDictBase], Any] | None = None,
    seed: int | None = None,
    collector: str = "sync",
    skip_batches: int = 0,
) -> EpisodeResults:
    """Play ``num_episodes`` episodes of ``policy`` (a TensorDict module) on ``N`` environments with
    a TorchRL collector, ``max_steps`` steps per episode.

    ``collector``:

    * ``"sync"``: a ``torchrl.collectors.Collector`` over ``env`` in this process (``N`` =
      ``env.batch_size``: a ``SerialEnv``/``ParallelEnv`` or a single env); the policy acts for the
      whole batch here. ``env`` stays open.
    * ``"multi_sync"``: a ``torchrl.collectors.MultiSyncCollector`` of ``N`` processes, each with
      its own environment and its own copy of the policy. ``env`` is a batched env whose
      sub-environments (and transforms) the processes build (:func:`worker_env_fns`; ``env``
      itself is never started), or a sequence of env constructors. The processes are started for
      this call and shut down before it returns.
    * ``"ray"``: a ``torchrl.collectors.distributed.RayCollector`` of ``N`` Ray actors (one CPU each), each a
      ``Collector`` with one of those envs and a copy of the policy, on the Ray cluster this process is connected
      to (``ray.init`` first, or ``RAY_ADDRESS``; else TorchRL starts a local Ray). The actors are started for this
      call and stopped before it returns; Ray stays up. Needs ``pip install -e ".[ray]"``.

    Each collector batch holds ``N * max_steps`` frames: one episode per environment, from its
    start (a reset) to its first ``("next", "done")`` (:func:`split_episodes`; the steps after an
    early end are dropped). An environment that did not end by the batch's last step is reset before
    the next batch; one that ended there was already reset by the collector. A stateful policy (the
    DT acting wrapper) therefore sees ``step_count == 0`` at every episode start.

    ``deterministic``: ``ExplorationType.DETERMINISTIC`` (the distribution's mean), otherwise
    ``RANDOM`` (sampled actions). ``on_episode`` is called with each finished episode.
    ``seed`` seeds the environments first (``env.set_seed`` / ``collector.set_seed``: env ``i``
    gets the ``i``-th seed of TorchRL's chain in both cases), so that calls with the same seed play
    the same initial configurations, with either collector (common random numbers for comparing
    policies; exact resumption). Sampled actions and a policy's own noise are drawn per process
    with ``"multi_sync"`` and ``"ray"``, so only deterministic policies give the same episodes there.

    ``skip_batches`` (``"sync"`` only): start at the episodes of the batch ``skip_batches`` of a call with the same
    ``seed`` and envs, episode ``skip_batches * N`` on: each env draws that many initial configurations first
    (resets, nothing stepped). The episodes are then that call's, value for value, as long as none of the skipped
    ones would have ended early (an early end resets its env once more) and nothing else in ``env`` draws random
    numbers per step (a ``StateNoise``): :mod:`trakdis.evaluation.chunks` checks this when it joins the parts of an
    evaluation.
    """
    if num_episodes < 1:
        raise ValueError(f"num_episodes must be >= 1, got {num_episodes}")
    finals, returns, lengths, unstable, kept = [], [], [], [], []
    t0 = time.perf_counter()
    stream = EpisodeStream(env, policy, max_steps=max_steps, deterministic=deterministic, seed=seed,
                           collector=collector, skip_batches=skip_batches)
    bar = progress(total=num_episodes, desc=desc)
    try:
        with torch.no_grad(), set_exploration_type(stream.exploration_type):
            while len(finals) < num_episodes:
                ep = next(stream)
                nxt = ep.get("next")
                finals.append(episode_score(ep))
                returns.append(float(nxt.get("reward").sum()))
                lengths.append(ep.shape[0])
                unstable.append(bool(nxt.get("sim_unstable").any()) if "sim_unstable" in nxt.keys() else False)
                if keep_episodes:
                    kept.append(ep)
                if on_episode is not None:
                    on_episode(ep)
                bar.update(1)
    finally:
        bar.close()
        stream.close()
    return EpisodeResults(
        final_performance=np.asarray(finals),
        returns=np.asarray(returns),
        lengths=np.asarray(lengths),
        unstable=np.asarray(unstable),
        episodes=kept,
        seconds=time.perf_counter() - t0,
        num_envs=stream.num_envs,
    )


def episode_score(episode: TensorDictBase) -> float:
    """The normalized performance at the last step of ``episode`` (one episode, ``[T]``): the paper's metric."""
    nxt = episode.get("next")
    if "normalized_performance" not in nxt.keys():
        raise KeyError(
            "run_episodes: the environment writes no ('next', 'normalized_performance'); "
            f"next keys are {sorted(map(str, nxt.keys()))}"
        )
    return float(nxt.get("normalized_performance")[-1].reshape(-1)[0])


class EpisodeStream:
    """The episodes of :func:`run_episodes`, one per ``next()``, for as long as the caller asks.

    Each collector batch plays one episode on each of the ``N`` environments; ``next()`` hands them out
    in turn and starts the next batch only when they are used up. A caller can therefore stop after
    any episode, do something else (play another stream), and continue: the episodes after the first
    ``k`` are those that one :func:`run_episodes` call for more episodes would have played (the same
    resets, in the same order). Used to race several policies on the same configurations, each in its
    own stream, dropping the clearly worse ones early (:func:`trakdis.student.weight_copy_race`).

    ``env``, ``policy``, ``max_steps``, ``deterministic``, ``seed``, ``collector`` and ``skip_batches``: as in
    :func:`run_episodes`. :meth:`close` (or leaving a ``with`` block) shuts the collector down; with
    ``"sync"``, ``env`` stays open (the caller's).
    """

    def __init__(self, env, policy: Callable[[TensorDictBase], TensorDictBase], *, max_steps: int,
                 deterministic: bool = True, seed: int | None = None, collector: str = "sync", skip_batches: int = 0):
        if collector not in COLLECTORS:
            raise ValueError(f"collector must be one of {COLLECTORS}, got {collector!r}")
        if skip_batches and (collector != "sync" or seed is None):
            raise ValueError(f"skip_batches={skip_batches} needs collector='sync' and a seed")
        self.exploration_type = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
        self.collector, self._env = collector, env
        self._threads = torch.get_num_threads()
        self._pending: list[TensorDictBase] = []
        self._batch = self._it = None
        if collector == "sync":
            self.num_envs = int(np.prod(tuple(env.batch_size))) if len(env.batch_size) else 1
            if seed is not None:
                # before the Collector: its constructor resets env, and that reset starts the first episodes
                env.set_seed(seed)
                for _ in range(skip_batches):  # the configurations of the skipped batches, drawn and not played
                    env.reset()
            # use_buffers=False: the batch is stacked from the steps as env.rollout does (keys the policy
            # writes beyond the env's specs, e.g. a TanhNormal's loc/scale, kept)
            self._coll = Collector(env, policy, frames_per_batch=self.num_envs * max_steps, total_frames=-1,
                                   exploration_type=self.exploration_type, use_buffers=False,
                                   auto_register_policy_transforms=False)
        elif collector == "ray":
            from torchrl.collectors.distributed import RayCollector  # imports ray: the optional extra

            env_fns = worker_env_fns(env)
            self.num_envs = len(env_fns)
            # sync=True: a batch is one max_steps rollout of every actor, stacked [N, max_steps] as with "sync"
            # total_frames: RayCollector stops at once on -1 (its loop runs while collected < total_frames)
            self._coll = RayCollector(env_fns, policy, frames_per_batch=self.num_envs * max_steps, total_frames=2**62,
                                      num_collectors=self.num_envs, sync=True, remote_configs={"num_cpus": 1},
                                      exploration_type=self.exploration_type,  # it overrides collector_kwargs'
                                      collector_kwargs={"use_buffers": False, "auto_register_policy_transforms": False})
            if seed is not None:
                try:
                    self._coll.set_seed(seed)  # each actor's env in turn: TorchRL's seed chain, as SerialEnv's
                    _reset_actors(self._coll, [True] * self.num_envs)  # the seeded first episodes
                except BaseException:
                    self.close()
                    raise
        else:
            env_fns = worker_env_fns(env)
            self.num_envs = len(env_fns)
            # num_threads: TorchRL would otherwise lower this process's thread count by the number of workers
            self._coll = MultiSyncCollector(env_fns, policy, frames_per_batch=self.num_envs * max_steps,
                                            total_frames=-1, exploration_type=self.exploration_type,
                                            use_buffers=False, cat_results="stack", num_threads=self._threads,
                                            auto_register_policy_transforms=False)
            if seed is not None:
                try:
                    self._coll.set_seed(seed)  # each process's env in turn (TorchRL's seed chain), then resets
                except BaseException:
                    self.close()
                    raise

    def __iter__(self) -> EpisodeStream:
        return self

    def __next__(self) -> TensorDictBase:
        if self._coll is None:
            raise RuntimeError("EpisodeStream: next() after close()")
        if not self._pending:
            with torch.no_grad(), set_exploration_type(self.exploration_type):
                if self._batch is not None:  # every env starts a new episode before the next batch
                    _start_next_episodes(self._coll, self._batch, self.num_envs, self.collector, self._env)
                if self._it is None:
                    self._it = iter(self._coll)
                batch = next(self._it)
            batch.names = None
            self._batch = batch
            # split_episodes, not split_trajs/trajs_per_batch: those also yield the episodes begun after an
            # early end, and trajs_per_batch continues unfinished ones into the next batch (_single.py)
            self._pending = split_episodes(batch.exclude("collector"))
        return self._pending.pop(0)

    def close(self) -> None:
        """Shut the collector down (its processes and, with ``"multi_sync"``, their envs); idempotent."""
        coll, self._coll, self._pending = self._coll, None, []
        if coll is None:
            return
        try:
            if self.collector == "sync":
                _shutdown(coll, close_env=False)  # env belongs to the caller (close_env)
            else:
                _shutdown(coll)  # its processes and their envs
        finally:
            torch.set_num_threads(self._threads)  # TorchRL's shutdown raises the thread count (see close_env)

    def __enter__(self) -> EpisodeStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _start_next_episodes(coll, batch: TensorDictBase, n_env: int, collector: str, env) -> None:
    """Reset the environments whose episode did not end at ``batch``'s last step (the collector
    already reset those that ended there), so that every environment starts a new episode."""
    # own code, not reset_at_each_iter=True: that resets every env again, also those the collector's
    # step_and_maybe_reset has just reset (torchrl/collectors/_single.py), drawing one more initial
    # configuration per env and batch than env.rollout(auto_reset=True), whose last step does not reset
    done = batch.get(("next", "done"))[..., -1, :].reshape(n_env)
    if bool(done.all()):
        return
    if collector == "multi_sync":  # one env per process
        coll.reset(reset_idx=(~done).tolist())
    elif collector == "ray":  # one env per actor
        _reset_actors(coll, (~done).tolist())
    elif len(env.batch_size):
        coll.reset(index=(~done).reshape(env.batch_size))
    else:
        coll.reset()


def _reset_actors(coll, which: Sequence[bool]) -> None:
    """Reset the envs of a ``RayCollector``'s actors where ``which`` is True (one env per actor)."""
    import ray

    ray.get([actor.reset.remote() for actor, reset in zip(coll.remote_collectors, which) if reset])


def write_summary_table(
    rows: Sequence[dict[str, Any]], csv_path: str | Path, md_path: str | Path | None = None, *,
    columns: Sequence[str] = ("task", "policy", "n", "mean", "std", "p25", "p50", "p75"),
) -> pd.DataFrame:
    """Write summary rows as CSV and (optionally) as a Markdown table; returns the frame."""
    frame = pd.DataFrame(list(rows))
    cols = [c for c in columns if c in frame.columns] + [c for c in frame.columns if c not in columns]
    frame = frame[cols]
    atomic_write_bytes(csv_path, frame.to_csv(index=False).encode())
    if md_path is not None:
        atomic_write_bytes(md_path, (markdown_table(frame) + "\n").encode())
    return frame


def markdown_table(frame: pd.DataFrame) -> str:
    """A GitHub Markdown table (no ``tabulate`` dependency, unlike ``DataFrame.to_markdown``)."""

    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.3f}"
        return str(v)

    lines = ["| " + " | ".join(map(str, frame.columns)) + " |", "|" + "---|" * len(frame.columns)]
    for rec in frame.itertuples(index=False):
        lines.append("| " + " | ".join(fmt(v) for v in rec) + " |")
    return "\n".join(lines)


def episode_frames(episode: TensorDictBase, *, large_key: str = "pixels", small_key: str = "pixels_agent",
                   label: str = "") -> list[np.ndarray]:
    """Side-by-side frames (large render | agent view upscaled) of one episode ``[T]`` TensorDict,
    captioned with the step and the normalized performance after it, plus the final frame."""
    for key in (large_key, small_key):
        if key not in episode.keys():
            raise KeyError(f"episode_frames: the episode has no {key!r} entry; keys are {sorted(map(str, episode.keys()))}")
    perf = episode.get(("next", "normalized_performance")).reshape(-1)
    frames = []
    for t in range(episode.shape[0]):
        frames.append(side_by_side(episode.get(large_key)[t], episode.get(small_key)[t],
                                   text=f"{label} t={t} perf={float(perf[t]):.3f}".strip()))
    nxt = episode.get("next")
    if large_key in nxt.keys() and small_key in nxt.keys():
        frames.append(side_by_side(nxt.get(large_key)[-1], nxt.get(small_key)[-1],
                                   text=f"{label} end perf={float(perf[-1]):.3f}".strip()))
    return frames
