"""Expert datasets: collection with a TorchRL collector, on-disk format, loading.

Format (version 1, see docs/dataset.md): a directory ``<path>/`` with

* ``meta.json``: ``{"format": "trakdis-dataset", "version": 1, "task", "num_episodes", "horizon",
  "keys": {key: {"shape", "dtype"}}, "config": {...}, "stats": {...}}``;
* ``data/``: a memory-mapped TensorDict (``TensorDict.memmap``) of batch ``[num_episodes]`` with
  ``"steps"`` ``[num_episodes, horizon]`` (per-step keys) and ``"length"`` ``[num_episodes]`` int64.

Collection writes into ``<path>.partial/`` chunk by chunk (one episode per worker per chunk),
records progress in ``<path>.partial/progress.json`` after each chunk (atomic replace), and renames
the directory to ``<path>`` only when every episode is written. A killed collection is resumed by
calling :func:`collect_expert_dataset` again with the same arguments: finished chunks are kept and,
since each chunk's env and policy seeds derive from ``(seed, chunk index)`` only, the result equals
an uninterrupted collection.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase

__all__ = [
    "DATASET_FORMAT",
    "DATASET_VERSION",
    "DatasetError",
    "collect_expert_dataset",
    "load_dataset",
    "partial_path",
]

DATASET_FORMAT = "trakdis-dataset"
DATASET_VERSION = 1

#: per-step keys: (dataset key, key in the collector batch). Next-step values are what the step produced.
STEP_KEYS = (
    ("state", "state"),
    ("pixels", "pixels"),
    ("action", "action"),
    ("reward", ("next", "reward")),
    ("normalized_performance", ("next", "normalized_performance")),
    ("sim_unstable", ("next", "sim_unstable")),
    ("done", ("next", "done")),
    ("terminated", ("next", "terminated")),
    ("truncated", ("next", "truncated")),
    ("step_count", "step_count"),
)
REQUIRED_KEYS = ("state", "action", "reward", "done", "terminated", "truncated", "step_count")


class DatasetError(RuntimeError):
    """A dataset directory is missing, unfinished, of another format/version, or inconsistent."""


def partial_path(path: str | os.PathLike) -> Path:
    """Where an unfinished collection of ``path`` lives."""
    path = Path(path)
    return path.with_name(path.name + ".partial")


def _write_json_atomic(path: Path, obj: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _chunk_seeds(seed: int, chunk: int) -> tuple[int, int]:
    """Independent (env, policy) seeds for one chunk, a function of (seed, chunk) only."""
    env_seed, policy_seed = np.random.SeedSequence([int(seed), int(chunk)]).generate_state(2)
    return int(env_seed), int(policy_seed)


class _ReseedablePolicy(TensorDictModuleBase):
    """Holds a policy built by ``factory(seed)`` and rebuilds it per chunk, so that a resumed
    collection draws the same policy noise as an uninterrupted one (the collector keeps this
    wrapper; only the inner policy is swapped)."""

    def __init__(self, factory: Callable[[int | None], TensorDictModuleBase]):
        super().__init__()
        self.factory = factory
        self.inner = factory(None)
        self.in_keys = list(getattr(self.inner, "in_keys", []))
        self.out_keys = list(getattr(self.inner, "out_keys", ["action"]))

    def reseed(self, seed: int) -> None:
        self.inner = self.factory(seed)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.inner(tensordict)


def _default_env_fn(task, from_pixels, image_size, split, horizon):
    from trakdis.envs import make_env

    return make_env(task, from_pixels=from_pixels, image_size=image_size, split=split, horizon=horizon)


def _default_policy_fn(task, noise, seed):
    from trakdis.envs import ExpertPolicy

    return ExpertPolicy(task, noise=noise, seed=seed)


def _batch_to_episodes(batch: TensorDictBase, horizon: int, keys: list[str]) -> tuple[TensorDict, torch.Tensor]:
    """Collector batch ``[W, horizon]`` starting at a reset -> first episode per worker + lengths.

    Steps after the first episode end (an early termination/truncation) belong to the next
    episode and are zeroed."""
    W = batch.shape[0]
    done = batch.get(("next", "done")).reshape(W, horizon)
    any_done = done.any(-1)
    first = torch.where(any_done, done.float().argmax(-1), torch.full((W,), horizon - 1))
    lengths = first + 1
    valid = torch.arange(horizon).unsqueeze(0) < lengths.unsqueeze(1)
    out = {}
    for name, src in STEP_KEYS:
        if name not in keys:
            continue
        val = batch.get(src)
        v = valid.view(W, horizon, *([1] * (val.ndim - 2)))
        out[name] = torch.where(v, val, torch.zeros((), dtype=val.dtype))
    return TensorDict(out, [W, horizon]), lengths


def collect_expert_dataset(
    path: str | os.PathLike,
    task: str,
    num_episodes: int,
    num_workers: int = 1,
    image_size: int = 32,
    from_pixels: bool = True,
    noise: float = 0.0,
    seed: int = 0,
    split: str = "train",
    horizon: int = 100,
    progress: bool = True,
    overwrite: bool = False,
    callback: Callable[[int, int], None] | None = None,
    make_env_fn: Callable[[], Any] | None = None,
    make_policy_fn: Callable[[int | None], TensorDictModuleBase] | None = None,
    mp_start_method: str | None = None,
) -> Path:
    """Collects ``num_episodes`` expert episodes of ``task`` into a dataset directory at ``path``.

    Runs a TorchRL ``Collector`` over ``num_workers`` environments (a ``ParallelEnv`` of worker
    processes when ``num_workers > 1``, the env itself when 1) with the scripted
    ``trakdis.envs.ExpertPolicy``; each collector batch is one episode per worker, started from a
    reset. Data go to a memory-mapped TensorDict on disk chunk by chunk, so memory stays bounded
    by one chunk: 8000 x 100-step episodes per task (the paper) only need disk space
    (about 2.5 GB with 32x32 pixels).

    Args:
        path: dataset directory to create (must not exist unless ``overwrite``).
        task: a task of ``trakdis.envs.TASKS``.
        num_episodes: episodes to collect.
        num_workers: environments run in parallel (worker processes when > 1); also the chunk size.
        image_size: rendered pixel size (with ``from_pixels``).
        from_pixels: also store ``"pixels"`` ``[H, W, 3]`` uint8.
        noise: std of Gaussian noise on the expert's actions.
        seed: base seed; chunk ``c`` uses env/policy seeds derived from ``(seed, c)``.
        split: ``"train"`` or ``"eval"`` cloth configurations.
        horizon: episode length (100 in the paper).
        progress: show a tqdm progress bar.
        overwrite: replace an existing dataset at ``path`` (only once the new one is complete).
        callback: called as ``callback(episodes_done, num_episodes)`` after each chunk is saved.
        make_env_fn: builds one TorchRL env (default: ``trakdis.envs.make_env`` with the arguments
            above); must be picklable when ``num_workers > 1``.
        make_policy_fn: builds the policy from a seed (default: ``ExpertPolicy(task, noise, seed)``).
        mp_start_method: start method of the ``ParallelEnv`` workers (default: TorchRL's choice).

    Returns:
        The dataset path. Resume a killed collection by calling again with the same arguments.
    """
    from torchrl.collectors import Collector
    from torchrl.envs import ParallelEnv

    path = Path(path)
    if num_episodes < 1 or num_workers < 1 or horizon < 1:
        raise ValueError(
            f"collect_expert_dataset: num_episodes ({num_episodes}), num_workers ({num_workers}) and horizon "
            f"({horizon}) must be >= 1"
        )
    if path.exists() and not overwrite:
        raise FileExistsError(f"collect_expert_dataset: {path} already exists (pass overwrite=True to replace it)")
    from trakdis.envs import EXPERT_VERSION, RENDER_VERSION

    config = {
        "task": task,
        "num_episodes": int(num_episodes),
        "chunk_size": int(num_workers),
        "image_size": int(image_size),
        "from_pixels": bool(from_pixels),
        "noise": float(noise),
        "seed": int(seed),
        "split": split,
        "horizon": int(horizon),
        "custom_env": make_env_fn is not None,
        "custom_policy": make_policy_fn is not None,
        "expert_version": None if make_policy_fn is not None else EXPERT_VERSION,
        "render_version": RENDER_VERSION if from_pixels and make_env_fn is None else None,
    }
    tmp = partial_path(path)
    progress_file = tmp / "progress.json"
    chunks_done = 0
    if tmp.exists():
        try:
            state = json.loads(progress_file.read_text())
        except (OSError, ValueError) as err:
            raise DatasetError(
                f"collect_expert_dataset: cannot resume from {tmp}: unreadable {progress_file.name} ({err}); "
                f"delete {tmp} to start over"
            ) from err
        diff = {k: (state["config"].get(k), v) for k, v in config.items() if state["config"].get(k) != v}
        if diff:
            raise DatasetError(
                f"collect_expert_dataset: {tmp} holds an unfinished collection with other settings "
                f"(saved, requested): {diff}; use the same arguments to resume, or delete {tmp}"
            )
        chunks_done = int(state["chunks_done"])
    else:
        tmp.mkdir(parents=True)
        _write_json_atomic(progress_file, {"config": config, "chunks_done": 0, "episodes_done": 0})

    W = int(num_workers)
    num_chunks = -(-num_episodes // W)
    env_fn = make_env_fn or functools.partial(_default_env_fn, task, from_pixels, image_size, split, horizon)
    policy_fn = make_policy_fn or functools.partial(_default_policy_fn, task, noise)
    keys = [k for k, _ in STEP_KEYS if k != "pixels" or from_pixels]

    from tqdm.auto import tqdm

    bar = tqdm(
        total=num_episodes, initial=min(chunks_done * W, num_episodes), disable=not progress,
        unit="ep", desc=f"collect {task}",
    )
    t_start = time.perf_counter()
    data = None
    if chunks_done > 0:
        data = TensorDict.load_memmap(tmp / "data")
    # TorchRL 0.14 changes torch's intra-op thread count when it starts and shuts down a
    # ParallelEnv (it lowers it by the number of workers, then raises it again, up to the initial
    # default of all cores). Measured: a recipe that set 1 thread and collected its dataset first
    # trained with 2 OpenMP threads afterwards, ~5x slower per update on a loaded 2-core machine.
    threads = torch.get_num_threads()
    if chunks_done < num_chunks:
        env = ParallelEnv(W, env_fn, mp_start_method=mp_start_method) if W > 1 else env_fn()
        policy = _ReseedablePolicy(policy_fn)
        collector = Collector(
            env, policy, frames_per_batch=W * horizon, total_frames=-1, reset_at_each_iter=True,
            auto_register_policy_transforms=False,
        )
        try:
            it = iter(collector)
            for chunk in range(chunks_done, num_chunks):
                env_seed, policy_seed = _chunk_seeds(seed, chunk)
                collector.set_seed(env_seed)
                policy.reseed(policy_seed)
                batch = next(it)
                if W == 1:
                    batch = batch.unsqueeze(0)
                if batch.shape != (W, horizon):
                    raise RuntimeError(f"collect_expert_dataset: expected a batch [{W}, {horizon}], got {tuple(batch.shape)}")
                missing = [k for k, src in STEP_KEYS if k in keys and batch.get(src, None) is None]
                missing = [k for k in missing if k in REQUIRED_KEYS or k == "pixels"]
                if missing:
                    raise KeyError(f"collect_expert_dataset: the env's output lacks {missing}; got {list(batch.keys(True, True))}")
                keys = [k for k, src in STEP_KEYS if k in keys and batch.get(src, None) is not None]
                episodes, lengths = _batch_to_episodes(batch, horizon, keys)
                lo = chunk * W
                n = min(W, num_episodes - lo)
                if data is None:
                    template = TensorDict(
                        {"steps": episodes[:1].expand(num_episodes, horizon), "length": torch.zeros(num_episodes, dtype=torch.long)},
                        [num_episodes],
                    )
                    data = template.memmap_like(prefix=tmp / "data")
                data["steps"][lo : lo + n] = episodes[:n]
                data["length"][lo : lo + n] = lengths[:n]
                _write_json_atomic(progress_file, {"config": config, "chunks_done": chunk + 1, "episodes_done": lo + n})
                bar.update(n)
                if callback is not None:
                    callback(lo + n, num_episodes)
        finally:
            bar.close()
            collector.shutdown()
            torch.set_num_threads(threads)
    else:
        bar.close()

    # finalize: statistics, meta.json, atomic rename into place
    steps, lengths = data["steps"], data["length"].clone()
    last = (lengths - 1).clamp(min=0)
    idx = torch.arange(num_episodes)
    stats = {
        "mean_length": float(lengths.float().mean()),
        "mean_return": float(steps["reward"].squeeze(-1).double().sum(-1).mean()),
    }
    if "normalized_performance" in steps.keys():
        final = steps["normalized_performance"][idx, last].squeeze(-1)
        stats["final_normalized_performance_mean"] = float(final.mean())
        stats["final_normalized_performance_std"] = float(final.std()) if num_episodes > 1 else 0.0
    meta = {
        "format": DATASET_FORMAT,
        "version": DATASET_VERSION,
        "task": task,
        "num_episodes": int(num_episodes),
        "horizon": int(horizon),
        "keys": {
            k: {"shape": list(v.shape[2:]), "dtype": str(v.dtype).replace("torch.", "")}
            for k, v in steps.items()
        },
        "config": config,
        "stats": stats,
        "collect_seconds_last_run": time.perf_counter() - t_start,
    }
    _write_json_atomic(tmp / "meta.json", meta)
    # progress.json stays until the rename, so a kill at any point leaves a resumable .partial
    if path.exists():  # overwrite=True: move the old dataset away only now that the new one is complete
        trash = path.with_name(path.name + ".old")
        if trash.exists():
            shutil.rmtree(trash)
        os.rename(path, trash)
        os.rename(tmp, path)
        shutil.rmtree(trash)
    else:
        os.rename(tmp, path)
    (path / "progress.json").unlink()
    return path


def load_dataset(path: str | os.PathLike) -> tuple[TensorDict, dict]:
    """Opens a dataset written by :func:`collect_expert_dataset`.

    Returns:
        ``(steps, meta)``: ``steps`` is the memory-mapped TensorDict ``[num_episodes, horizon]``
        (read lazily from disk); ``meta`` is ``meta.json`` plus ``meta["lengths"]``, an int64 tensor
        ``[num_episodes]`` of episode lengths (steps at or beyond an episode's length are zero).

    Raises:
        DatasetError: the path is missing, holds an unfinished collection, is not a trakdis dataset,
            has another format version, or its data do not match ``meta.json``.
    """
    path = Path(path)
    if not path.exists():
        part = partial_path(path)
        if part.exists():
            done = "?"
            try:
                done = json.loads((part / "progress.json").read_text())["episodes_done"]
            except (OSError, ValueError, KeyError):
                pass
            raise DatasetError(
                f"load_dataset: {path} does not exist, but {part} holds an unfinished collection "
                f"({done} episodes written); rerun collect_expert_dataset with the same arguments to finish it"
            )
        raise DatasetError(f"load_dataset: no dataset at {path} (directory does not exist)")
    meta_file = path / "meta.json"
    if not meta_file.exists():
        raise DatasetError(f"load_dataset: {path} has no meta.json: not a trakdis dataset, or an unfinished one")
    try:
        meta = json.loads(meta_file.read_text())
    except ValueError as err:
        raise DatasetError(f"load_dataset: {meta_file} is not valid JSON ({err})") from err
    if meta.get("format") != DATASET_FORMAT:
        raise DatasetError(f"load_dataset: {meta_file} has format {meta.get('format')!r}, expected {DATASET_FORMAT!r}")
    if meta.get("version") != DATASET_VERSION:
        raise DatasetError(
            f"load_dataset: {path} is version {meta.get('version')!r} of the format; this trakdis reads version "
            f"{DATASET_VERSION}; recollect it with collect_expert_dataset"
        )
    try:
        data = TensorDict.load_memmap(path / "data")
    except Exception as err:  # noqa: BLE001 - any failure here means damaged data
        raise DatasetError(f"load_dataset: cannot read the memory-mapped data in {path / 'data'} ({err})") from err
    steps = data.get("steps", None)
    lengths = data.get("length", None)
    expected = (meta["num_episodes"], meta["horizon"])
    if steps is None or lengths is None or tuple(steps.batch_size) != expected:
        raise DatasetError(
            f"load_dataset: {path / 'data'} does not match meta.json (expected steps {list(expected)} and lengths)"
        )
    missing = [k for k in REQUIRED_KEYS if k not in steps.keys()]
    if missing:
        raise DatasetError(f"load_dataset: {path} lacks the per-step keys {missing}")
    meta = dict(meta)
    meta["lengths"] = lengths.clone()
    meta["path"] = str(path)
    return steps, meta
