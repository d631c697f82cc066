"""Episode rollouts and their summary, shared by the recipes (teacher/student evaluation, online
data collection, ``evaluate.py``).

:func:`run_episodes` rolls a policy out in a batched TorchRL environment (``SerialEnv`` /
``ParallelEnv`` of ``N`` tasks, or a single env) with ``env.rollout`` until ``num_episodes``
full episodes were played, and returns per-episode results: the normalized performance at the
episode's end (the paper's metric), the return, the length, and optionally the rollout
TensorDicts themselves (to insert into a replay buffer or to render videos).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import pandas as pd
import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from trakdis.utils.checkpoint import atomic_write_bytes
from trakdis.utils.progress import progress

__all__ = ["EpisodeResults", "episode_frames", "markdown_table", "paired_difference", "run_episodes", "split_episodes",
           "standard_error", "summarize", "write_summary_table"]


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
) -> EpisodeResults:
    """Play ``num_episodes`` episodes of ``policy`` in ``env`` (batched over ``env.batch_size``).

    Each round is one ``env.rollout`` of ``max_steps`` steps (the horizon) with a fresh reset, so
    a stateful policy (the DT acting wrapper) sees ``step_count == 0`` at every episode start.
    ``deterministic`` evaluates the distribution's mean (``ExplorationType.DETERMINISTIC``);
    otherwise actions are sampled. ``on_episode`` is called with each finished episode.
    ``seed`` reseeds the env first, so that calls with the same seed play the same initial
    configurations (common random numbers for comparing policies; exact resumption).
    """
    if num_episodes < 1:
        raise ValueError(f"num_episodes must be >= 1, got {num_episodes}")
    n_env = int(np.prod(tuple(env.batch_size))) if len(env.batch_size) else 1
    rounds = math.ceil(num_episodes / n_env)
    finals, returns, lengths, unstable, kept = [], [], [], [], []
    t0 = time.perf_counter()
    mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    if seed is not None:
        env.set_seed(seed)
    bar = progress(total=num_episodes, desc=desc)
    with torch.no_grad(), set_exploration_type(mode):
        for _ in range(rounds):
            rollout = env.rollout(max_steps, policy, break_when_any_done=False, auto_reset=True)
            for ep in split_episodes(rollout):
                if len(finals) >= num_episodes:
                    break
                nxt = ep.get("next")
                if "normalized_performance" not in nxt.keys():
                    raise KeyError(
                        "run_episodes: the environment writes no ('next', 'normalized_performance'); "
                        f"next keys are {sorted(map(str, nxt.keys()))}"
                    )
                finals.append(float(nxt.get("normalized_performance")[-1].reshape(-1)[0]))
                returns.append(float(nxt.get("reward").sum()))
                lengths.append(ep.shape[0])
                unstable.append(bool(nxt.get("sim_unstable").any()) if "sim_unstable" in nxt.keys() else False)
                if keep_episodes:
                    kept.append(ep)
                if on_episode is not None:
                    on_episode(ep)
                bar.update(1)
    bar.close()
    return EpisodeResults(
        final_performance=np.asarray(finals),
        returns=np.asarray(returns),
        lengths=np.asarray(lengths),
        unstable=np.asarray(unstable),
        episodes=kept,
        seconds=time.perf_counter() - t0,
        num_envs=n_env,
    )


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
    from trakdis.utils.video import side_by_side

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
