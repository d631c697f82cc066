"""The scripted expert's evaluation, measured once and cached as JSON next to the datasets.

The expert is deterministic, so its score on a given set of evaluation episodes never changes:
``online_dt.py`` measures it once per configuration and reuses it, instead of simulating the same
episodes on every run. A cache file

    <data.root>/expert_scores/<task>_<split>_h<horizon>_<episodes>ep_<hash>.json

holds ``{"format": "trakdis-expert-scores", "version": 1, "key": {...}, "scores": [...],
"returns": [...], "seconds": ...}``: the per-episode normalized performance at the episode's end and
return, and the *key*, every
setting that decides those episodes (task, split, horizon, episode count, seed, number of
environments, expert noise and version, MuJoCo version). ``<hash>`` is a digest of the key, so a
changed setting (another seed, a new expert version, ...) looks for another file: stale scores are
never used, and never overwritten either.

Files are written atomically (temporary file, fsync, rename) and read as untrusted JSON: nothing
in them is executed, and a file that is not valid JSON, has another format, holds a key other than
the one its name stands for, or scores that are not ``episodes`` finite numbers, is an
:class:`ExpertScoreError` naming the file (delete it to measure again).
"""
from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import mujoco
import numpy as np

from trakdis.data import DatasetError
from trakdis.envs import expert_version
from trakdis.utils.checkpoint import atomic_write_bytes

__all__ = ["ExpertScoreError", "expert_score_key", "expert_score_path", "read_expert_scores", "write_expert_scores"]

CACHE_FORMAT = "trakdis-expert-scores"
CACHE_VERSION = 1


class ExpertScoreError(DatasetError):
    """A cached expert score file is unreadable or inconsistent."""


def expert_score_key(*, task: str, split: str, horizon: int, episodes: int, seed: int, num_envs: int,
                     expert_noise: float = 0.0) -> dict[str, Any]:
    """Every setting that decides the expert's evaluation episodes and their scores.

    ``num_envs`` is part of it: ``run_episodes`` draws episode ``i``'s configuration from the
    random stream of environment ``i % num_envs``, so another count plays other configurations."""
    return {"task": str(task), "split": str(split), "horizon": int(horizon), "episodes": int(episodes),
            "seed": int(seed), "num_envs": int(num_envs), "expert_noise": float(expert_noise),
            "expert_version": int(expert_version(task)), "mujoco": str(mujoco.__version__)}


def expert_score_path(root: str | Path, key: Mapping[str, Any]) -> Path:
    digest = hashlib.sha256(json.dumps(dict(key), sort_keys=True).encode()).hexdigest()[:12]
    name = f"{key['task']}_{key['split']}_h{key['horizon']}_{key['episodes']}ep_{digest}.json"
    return Path(root) / "expert_scores" / name


def _error(path: Path, problem: str) -> ExpertScoreError:
    return ExpertScoreError(f"expert score cache {path}: {problem}; delete the file to measure the expert again")


def read_expert_scores(path: str | Path, key: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray] | None:
    """The cached per-episode ``(scores, returns)`` for ``key``, or ``None`` when ``path`` does not exist."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise _error(path, f"not valid JSON ({err})") from err
    if not isinstance(data, dict) or data.get("format") != CACHE_FORMAT:
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise _error(path, f"format {found!r}, expected {CACHE_FORMAT!r}")
    if data.get("version") != CACHE_VERSION:
        raise _error(path, f"version {data.get('version')!r}, this trakdis reads version {CACHE_VERSION}")
    if data.get("key") != dict(key):
        raise _error(path, f"'key' is {data.get('key')!r}, but the file's name stands for {dict(key)!r}")
    out = []
    for name in ("scores", "returns"):
        values = data.get(name)
        if not (isinstance(values, list) and len(values) == key["episodes"]
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values)):
            raise _error(path, f"{name!r} must be a list of {key['episodes']} finite numbers, got {str(values)[:200]}")
        out.append(np.asarray(values, dtype=np.float64))
    return out[0], out[1]


def write_expert_scores(path: str | Path, key: Mapping[str, Any], scores: Sequence[float], *,
                        returns: Sequence[float], seconds: float | None = None) -> Path:
    """Write the cache file atomically (a concurrent reader sees the old file or the new one, whole)."""
    scores, returns = [float(s) for s in scores], [float(r) for r in returns]
    if not len(scores) == len(returns) == key["episodes"]:
        raise ValueError(f"write_expert_scores: {len(scores)} scores and {len(returns)} returns for a key of "
                         f"{key['episodes']} episodes")
    data = {"format": CACHE_FORMAT, "version": CACHE_VERSION, "key": dict(key), "scores": scores, "returns": returns,
            "seconds": None if seconds is None else float(seconds)}
    return atomic_write_bytes(path, (json.dumps(data, indent=1) + "\n").encode())
