"""An evaluation (``recipes/evaluate.py``) cut into parts that run side by side, and the parts joined into the
``episodes.csv``, ``summary.csv`` and ``summary.md`` that the whole evaluation writes, value for value.

Which configuration episode ``k`` plays: ``evaluate.py`` seeds its ``N`` envs (``--num-envs``) with ``--seed``
(TorchRL's seed chain: env ``i`` gets the chain's ``i``-th seed), and each env draws a configuration (its pool
index and the pickers' start) from its own generator at every reset; one batch plays one episode per env, so
episode ``k`` is the ``k // N``-th episode of env ``k % N``. A part from episode ``K`` on (``--first-episode K``,
a multiple of ``N``) has each env draw the ``K / N`` configurations of the skipped batches first, without playing
them (:func:`~trakdis.evaluation.run_episodes`'s ``skip_batches``), and then plays the episodes ``K ...`` of the
whole evaluation, in batches of the same ``N`` envs (a policy acts on a batch of the same size: the same
rounding). Every method of a seed still plays the same configuration as episode ``k``, so paired differences
stay exact. One case breaks this: a skipped episode that would have ended early (the physics became unstable)
resets its env once more; :func:`merge_evaluations` then finds an episode shorter than the horizon before a
later part's first and returns False, and the evaluation runs whole. Noise levels are separate evaluations
(each its own envs and noise generator, the same seed), so a ladder of levels is cut by level.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import pandas as pd

from trakdis.utils.checkpoint import atomic_write_bytes
from trakdis.utils.stages import Parts

from .episodes import summarize, write_summary_table

__all__ = ["SUMMARY_COLUMNS", "evaluation_parts", "merge_evaluations", "summary_rows"]

SUMMARY_COLUMNS = ("task", "policy", "state_noise", "n", "mean", "std", "p25", "p50", "p75")
"""The first columns of ``evaluate.py``'s ``summary.csv``"""


def evaluation_parts(trials: int, chunk: int, *, num_envs: int = 2,
                     noise_levels: Sequence[float] = (0.0,)) -> Parts | None:
    """The parts of an ``evaluate.py`` stage of ``trials`` episodes per level of ``noise_levels`` on ``num_envs``
    envs (its ``--num-envs``): one per level for a ladder; noise-free, parts of ``chunk`` episodes (rounded up to
    a multiple of ``num_envs``), the last one shorter. None when it stays whole (``chunk`` 0, or not below
    ``trials``)."""
    if len(noise_levels) > 1:
        return Parts(tuple(("--noise-levels", repr(float(level))) for level in noise_levels), merge_evaluations)
    if not chunk or any(float(level) for level in noise_levels):
        return None
    chunk = -(-chunk // num_envs) * num_envs
    if chunk >= trials:
        return None
    return Parts(tuple(("--first-episode", str(k), "--trials", str(min(chunk, trials - k)),
                        *(("--videos", "0") if k else ())) for k in range(0, trials, chunk)), merge_evaluations)


def summary_rows(episodes: pd.DataFrame, task: str, policy: str) -> list[dict]:
    """``evaluate.py``'s summary rows from its episodes (one per noise level, in the order played)."""
    rows = []
    for sigma in pd.unique(episodes["state_noise"]):
        at = episodes[episodes["state_noise"] == sigma]
        rows.append({"task": task, "policy": policy, "state_noise": float(sigma),
                     **summarize(at["final_normalized_performance"].to_numpy(float)),
                     "unstable": int(at["sim_unstable"].astype(bool).sum())})
    return rows


def merge_evaluations(parts: Sequence[Path], directory: Path) -> bool:
    """Join the ``evaluate.py`` runs ``parts`` (of :func:`evaluation_parts`, in order) into ``directory``: its
    ``episodes.csv``, ``summary.csv`` and ``summary.md`` as the whole evaluation writes them, and ``parts.json``
    (where they came from). False, writing nothing, when a part's episodes are not the whole evaluation's (an
    episode before a later part's first ended early: see the module's text)."""
    frames = [pd.read_csv(Path(p) / "episodes.csv") for p in parts]
    summary = pd.read_csv(Path(parts[0]) / "summary.csv")
    episodes = pd.concat(frames, ignore_index=True)
    horizon = int(episodes["length"].max())
    for i, frame in enumerate(frames[1:], start=1):
        levels = set(frame["state_noise"])
        if levels & set(pd.concat(frames[:i])["state_noise"]):  # the same level, later episodes: cut by episode
            before = pd.concat(frames[:i])
            if (before["length"] < horizon).any():
                return False
    for sigma in pd.unique(episodes["state_noise"]):
        numbers = episodes.loc[episodes["state_noise"] == sigma, "episode"].tolist()
        if numbers != list(range(len(numbers))):
            raise ValueError(f"merge_evaluations: {[str(p) for p in parts]} hold episodes {numbers} at noise "
                             f"{sigma:g}, not 0 .. n-1 in order")
    directory.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(directory / "episodes.csv", episodes.to_csv(index=False).encode())
    atomic_write_bytes(directory / "parts.json", json.dumps([str(p) for p in parts], indent=1).encode())
    write_summary_table(summary_rows(episodes, summary["task"].iloc[0], summary["policy"].iloc[0]),
                        directory / "summary.csv", directory / "summary.md", columns=SUMMARY_COLUMNS)
    return True
