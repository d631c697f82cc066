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
an uninterrupted collection. One collection at a time writes into ``<path>.partial/`` (an exclusive
``fcntl.flock`` on the directory); a second one is refused.

:func:`load_expert_dataset` reads any dataset as untrusted input: ``meta.json`` (a regular file of at
most :data:`~trakdis.utils.limits.MAX_JSON_BYTES`) is validated, every file must be a regular file
inside the dataset directory (symlinks resolved), every data file's size must equal what its
``meta.json`` shape and dtype give, the episode lengths must lie in ``[1, horizon]``, and the files are
mapped read-only (copy-on-write: the file is opened read-only, in-memory writes never reach the disk,
and no pickle is ever read). Only collection (writing its own ``.partial`` directory) opens them for
writing; it checks the disk's free space before it maps a file that it will fill.
"""

from __future__ import annotations

import fcntl
import functools
import json
import math
import os
import re
import shutil
import time
from pathlib import Path
from typing import Any, Callable

import mujoco
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector
from tqdm.auto import tqdm

from trakdis.envs import ExpertPolicy, expert_version, make_env, render_version
from trakdis.envs.batched import SleepWaitParallelEnv
from trakdis.envs.specs import TASKS, task_spec
from trakdis.utils import limits
from trakdis.utils.checkpoint import atomic_write_bytes, remove_stale_temporaries

from .layout import REQUIRED_KEYS, STEP_KEYS, valid_mask

__all__ = [
    "DATASET_FORMAT",
    "DATASET_VERSION",
    "DatasetError",
    "collect_expert_dataset",
    "load_expert_dataset",
    "partial_path",
    "read_meta",
    "collected_close_radius",
    "collected_expert_version",
]

DATASET_FORMAT = "trakdis-dataset"
DATASET_VERSION = 1


class DatasetError(RuntimeError):
    """A dataset directory is missing, unfinished, of another format/version, or inconsistent."""


def _progress_enabled(progress: bool) -> bool:
    """``TRAKDIS_NO_PROGRESS=1`` silences the bar even when ``progress=True`` was passed."""
    return bool(progress) and os.environ.get("TRAKDIS_NO_PROGRESS", "0") in ("", "0")


class _CollectionLock:
    """An exclusive, non-blocking ``flock`` on the ``.partial`` directory of one collection: a second
    collection into the same path (another process, or another call in this one) is refused instead
    of colliding on its files. The OS releases it when the process dies (a SIGKILL leaves no stale lock)."""

    def __init__(self, directory: Path, target: Path):
        try:
            self.fd = os.open(directory, os.O_RDONLY)
        except FileNotFoundError:  # another collection just finished and renamed it
            raise DatasetError(f"collect_expert_dataset: another collection was writing {target} ({directory} "
                               f"vanished); use its dataset") from None
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self.fd)
            raise DatasetError(
                f"collect_expert_dataset: another collection is writing {target} right now (it holds the lock "
                f"on {directory}); wait for it to finish and use its dataset, or choose another path"
            ) from None

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)  # closing the descriptor releases the flock
            self.fd = None


def partial_path(path: str | os.PathLike) -> Path:
    """Where an unfinished collection of ``path`` lives."""
    path = Path(path)
    return path.with_name(path.name + ".partial")


def _write_json_atomic(path: Path, obj: dict) -> None:
    """``obj`` as indented JSON, written atomically (:func:`~trakdis.utils.atomic_write_bytes`)."""
    atomic_write_bytes(path, json.dumps(obj, indent=1).encode())


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
    return make_env(task, from_pixels=from_pixels, image_size=image_size, split=split, horizon=horizon)


def _default_policy_fn(task, noise, aim_error, close_radius, seed):
    return ExpertPolicy(task, noise=noise, seed=seed, aim_error=aim_error, close_radius=close_radius)  # None: the task's


def _batch_to_episodes(batch: TensorDictBase, horizon: int, keys: list[str]) -> tuple[TensorDict, torch.Tensor]:
    """Collector batch ``[W, horizon]`` starting at a reset -> first episode per worker + lengths.

    Steps after the first episode end (an early termination/truncation) belong to the next
    episode and are zeroed."""
    W = batch.shape[0]
    done = batch.get(("next", "done")).reshape(W, horizon)
    any_done = done.any(-1)
    first = torch.where(any_done, done.float().argmax(-1), torch.full((W,), horizon - 1))
    lengths = first + 1
    valid = valid_mask(lengths, horizon)
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
    aim_error: float = 0.0,
    close_radius: float | None = None,
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
        aim_error: the expert aims at source corners misplaced by this std (metres; ``ExpertPolicy``'s
            ``aim_error``: missed grasps); recorded in the config when > 0.
        close_radius: the expert closes a picker on a corner still on the table within this distance (metres;
            ``expert_action``'s; default None: the task's); recorded in the config when set.

    Returns:
        The dataset path. Resume a killed collection by calling again with the same arguments.
    """
    path = Path(path)
    if num_episodes < 1 or num_workers < 1 or horizon < 1:
        raise ValueError(
            f"collect_expert_dataset: num_episodes ({num_episodes}), num_workers ({num_workers}) and horizon "
            f"({horizon}) must be >= 1"
        )
    if (aim_error or close_radius is not None) and make_policy_fn is not None:
        raise ValueError("collect_expert_dataset: aim_error and close_radius apply to the scripted expert, not to "
                         "make_policy_fn")
    policy_fn = make_policy_fn or functools.partial(_default_policy_fn, task, noise, aim_error, close_radius)
    if make_policy_fn is None:
        policy_fn(None)  # the expert's own checks (noise, aim_error, close_radius) reject bad values before any disk write
    if path.exists() and not overwrite:
        raise FileExistsError(f"collect_expert_dataset: {path} already exists (pass overwrite=True to replace it)")
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
        "expert_version": None if make_policy_fn is not None else expert_version(task),
        "render_version": render_version(task) if from_pixels and make_env_fn is None else None,
    }
    if aim_error:  # only then: the config of every other dataset (and of a collection to resume) stays as it was
        config["aim_error"] = float(aim_error)
    if close_radius is not None:  # the same
        config["close_radius"] = float(close_radius)
    tmp = partial_path(path)
    tmp.mkdir(parents=True, exist_ok=True)
    lock = _CollectionLock(tmp, path)
    try:
        if path.exists() and not overwrite:  # another collection finished it while this one started
            raise FileExistsError(f"collect_expert_dataset: {path} already exists (pass overwrite=True to replace it)")
        return _collect_into(
            path, tmp, config, task=task, num_episodes=num_episodes, num_workers=num_workers, image_size=image_size,
            from_pixels=from_pixels, seed=seed, split=split, horizon=horizon, progress=progress,
            callback=callback, make_env_fn=make_env_fn, policy_fn=policy_fn, mp_start_method=mp_start_method)
    finally:
        lock.release()


def _collect_into(path: Path, tmp: Path, config: dict, *, task, num_episodes, num_workers, image_size, from_pixels,
                  seed, split, horizon, progress, callback, make_env_fn, policy_fn, mp_start_method) -> Path:
    """The body of :func:`collect_expert_dataset`, run while it holds the lock on ``tmp``."""
    progress_file = tmp / "progress.json"
    chunks_done = 0
    remove_stale_temporaries(tmp)  # of a collection killed while it replaced progress.json or meta.json
    if progress_file.exists():
        try:
            state = limits.read_json(progress_file, within=tmp, error=DatasetError, what="progress file")
            if not isinstance(state, dict) or not isinstance(state.get("config"), dict):
                raise DatasetError(f"{progress_file} is not a progress record")
        except DatasetError as err:
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
        _write_json_atomic(progress_file, {"config": config, "chunks_done": 0, "episodes_done": 0})

    W = int(num_workers)
    num_chunks = -(-num_episodes // W)
    env_fn = make_env_fn or functools.partial(_default_env_fn, task, from_pixels, image_size, split, horizon)
    keys = [k for k, _ in STEP_KEYS if k != "pixels" or from_pixels]

    bar = tqdm(
        total=num_episodes, initial=min(chunks_done * W, num_episodes), disable=not _progress_enabled(progress),
        unit="ep", desc=f"collect {task}",
    )
    t_start = time.perf_counter()
    data = None
    if chunks_done > 0:
        data = TensorDict.load_memmap(tmp / "data", allow_pickle=False)  # the writer's own files, read-write
        _check_free_space(tmp / "data", _unallocated_bytes(tmp / "data"))
    # TorchRL 0.14 changes torch's intra-op thread count when it starts and shuts down a
    # ParallelEnv (it lowers it by the number of workers, then raises it again, up to the initial
    # default of all cores). Measured: a recipe that set 1 thread and collected its dataset first
    # trained with 2 OpenMP threads afterwards, ~5x slower per update on a loaded 2-core machine.
    threads = torch.get_num_threads()
    if chunks_done < num_chunks:
        # a ParallelEnv that does not busy-wait for its workers (trakdis.envs.batched; the data are the same)
        env = SleepWaitParallelEnv(W, env_fn, mp_start_method=mp_start_method) if W > 1 else env_fn()
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
                    _check_free_space(tmp, _template_bytes(template))
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
        "mujoco_version": str(mujoco.__version__),  # recorded, not checked (other releases play other episodes)
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


def _template_bytes(template: TensorDictBase) -> int:
    return sum(v.numel() * v.element_size() for v in template.values(True, True))


def _unallocated_bytes(directory: Path) -> int:
    """Bytes the memory-mapped files under ``directory`` still need on disk (sparse files: their size
    minus the blocks already allocated)."""
    total = 0
    for file in directory.rglob("*.memmap"):
        st = file.stat()
        total += max(0, st.st_size - 512 * getattr(st, "st_blocks", st.st_size // 512))
    return total


def _check_free_space(directory: Path, needed: int) -> None:
    """A :class:`DatasetError` naming the disk when less than ``needed`` bytes (plus 1%) are free there:
    a memory-mapped write to a full disk kills the process with SIGBUS, without a message."""
    free = shutil.disk_usage(directory).free
    if needed * 1.01 > free:
        raise DatasetError(
            f"collect_expert_dataset: the dataset needs {needed / 2**20:,.1f} MiB more on the disk of {directory}, "
            f"which has {free / 2**20:,.1f} MiB free; free some space (the collection resumes where it stopped) "
            f"or collect to another disk")


_DTYPES = {name: getattr(torch, name) for name in (
    "float16", "bfloat16", "float32", "float64", "uint8", "int8", "int16", "int32", "int64", "bool")}
_KEY_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def _meta_error(meta_file: Path, key: str, problem: str) -> DatasetError:
    return DatasetError(f"load_expert_dataset: {meta_file}: {key!r} {problem}")


# the layout of the per-step keys whose form does not depend on the task: dtype names and shape (None: any)
_FIXED_LAYOUT = {
    "reward": (("float32", "float64"), [1]), "normalized_performance": (("float32", "float64"), [1]),
    "done": (("bool",), [1]), "terminated": (("bool",), [1]), "truncated": (("bool",), [1]),
    "sim_unstable": (("bool",), [1]), "step_count": (("int64",), [1]),
    "state": (("float32", "float64"), None), "action": (("float32", "float64"), None), "pixels": (("uint8",), None),
}


def _task_names() -> tuple[str, ...]:
    return tuple(TASKS)


def _check_layout(meta: dict, meta_file: Path) -> None:
    """Each known per-step key of the dtype and shape a collection writes (a ``meta.json`` whose shapes
    lie consistently with its files' sizes is refused here); for a task of ``trakdis.envs.TASKS``, the
    state and action widths of that task, and images of the collection's ``image_size`` (unless the
    collection used an env of its own)."""
    keys = meta["keys"]
    for name, (dtypes, shape) in _FIXED_LAYOUT.items():
        if name not in keys:
            continue
        spec = keys[name]
        if spec["dtype"] not in dtypes:
            raise _meta_error(meta_file, f"keys.{name}.dtype", f"must be {' or '.join(dtypes)}, got {spec['dtype']!r}")
        if shape is not None and spec["shape"] != shape:
            raise _meta_error(meta_file, f"keys.{name}.shape", f"must be {shape}, got {spec['shape']!r}")
    for name in ("state", "action"):
        if name in keys and len(keys[name]["shape"]) != 1:
            raise _meta_error(meta_file, f"keys.{name}.shape", f"must be [width], got {keys[name]['shape']!r}")
    config = meta.get("config", {})
    ours = meta["task"] in _task_names() and not config.get("custom_env")  # a trakdis task's env: its widths known
    size = config.get("image_size") if ours else None
    if "pixels" in keys:
        shape = keys["pixels"]["shape"]
        if len(shape) != 3 or shape[2] != 3 or shape[0] != shape[1] or (limits.is_int(size) and shape[0] != size):
            raise _meta_error(meta_file, "keys.pixels.shape", f"must be [size, size, 3] images"
                              f"{f' of the image_size {size} it records' if limits.is_int(size) else ''}, got {shape!r}")
    if ours:
        spec = task_spec(meta["task"])
        for name, width in (("state", spec.state_dim), ("action", spec.action_dim)):
            if name in keys and keys[name]["shape"] != [width]:
                raise _meta_error(meta_file, f"keys.{name}.shape", f"must be [{width}] for task {meta['task']}, "
                                  f"got {keys[name]['shape']!r}")


def collected_expert_version(meta: dict) -> int | None:
    """The version of the scripted expert that collected the dataset of ``meta`` (its ``meta.json``):
    1 for datasets older than the field, None for a dataset of a custom policy."""
    return meta.get("config", {}).get("expert_version", 1)


def collected_close_radius(meta: dict) -> float | None:
    """The grasp radius (metres) the scripted expert that collected the dataset of ``meta`` closed its pickers
    within, when it was not the task's (``collect_expert_dataset(close_radius=)``); None: the task's."""
    return meta.get("config", {}).get("close_radius")


def read_meta(path: str | os.PathLike) -> dict:
    """``<path>/meta.json``, checked: a JSON object of this format and version whose ``task``,
    ``num_episodes``, ``horizon`` and ``keys`` (``{key: {"shape": [ints], "dtype": name}}``) are
    well-formed. Raises :class:`DatasetError` naming the file and the offending key."""
    path = Path(path)
    meta_file = path / "meta.json"
    if not os.path.lexists(meta_file):
        raise DatasetError(f"load_expert_dataset: {path} has no meta.json: not a trakdis dataset, or an unfinished one")
    meta = limits.read_json(meta_file, within=path, error=DatasetError, what="load_expert_dataset: dataset file")
    if not isinstance(meta, dict):
        raise DatasetError(f"load_expert_dataset: {meta_file} holds a JSON {type(meta).__name__}, expected an object "
                           f"with 'format', 'version', 'task', 'num_episodes', 'horizon' and 'keys'")
    if meta.get("format") != DATASET_FORMAT:
        raise DatasetError(f"load_expert_dataset: {meta_file} has format {meta.get('format')!r}, expected {DATASET_FORMAT!r}")
    if meta.get("version") != DATASET_VERSION:
        raise DatasetError(
            f"load_expert_dataset: {path} is version {meta.get('version')!r} of the format; this trakdis reads version "
            f"{DATASET_VERSION}; recollect it with collect_expert_dataset"
        )
    for key in ("task", "num_episodes", "horizon", "keys"):
        if key not in meta:
            raise _meta_error(meta_file, key, "is missing")
    if not isinstance(meta["task"], str):
        raise _meta_error(meta_file, "task", f"must be a task name, got {meta['task']!r}")
    for key in ("num_episodes", "horizon"):
        value = meta[key]
        if not (limits.is_int(value) and value >= 1):
            raise _meta_error(meta_file, key, f"must be an int >= 1, got {value!r}")
    if meta["horizon"] > limits.MAX_HORIZON:
        raise _meta_error(meta_file, "horizon", f"must be at most {limits.MAX_HORIZON} "
                          f"(trakdis.utils.limits.MAX_HORIZON), got {meta['horizon']!r}")
    keys = meta["keys"]
    if not isinstance(keys, dict):
        raise _meta_error(meta_file, "keys", f"must map each per-step key to its shape and dtype, got {keys!r}")
    for name, spec in keys.items():
        where = f"keys.{name}"
        if not _KEY_RE.fullmatch(name):
            raise _meta_error(meta_file, where, "is not a plain key name")
        if not isinstance(spec, dict) or "shape" not in spec or "dtype" not in spec:
            raise _meta_error(meta_file, where, f"must be {{'shape': [...], 'dtype': ...}}, got {spec!r}")
        shape = spec["shape"]
        if not (isinstance(shape, list) and all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape)):
            raise _meta_error(meta_file, where + ".shape", f"must be a list of ints >= 0, got {shape!r}")
        if spec["dtype"] not in _DTYPES:
            raise _meta_error(meta_file, where + ".dtype", f"must be one of {sorted(_DTYPES)}, got {spec['dtype']!r}")
    if "config" in meta and not isinstance(meta["config"], dict):
        raise _meta_error(meta_file, "config", f"must be an object, got {meta['config']!r}")
    _check_layout(meta, meta_file)
    return meta


def _open_readonly(file: Path, dtype: torch.dtype, shape: tuple[int, ...], what: str, root: Path) -> torch.Tensor:
    """Map ``file`` as a ``dtype`` tensor of ``shape``, read-only on disk (opened ``O_RDONLY``, mapped
    private: writes to the tensor stay in memory), after checking that it is a regular file inside
    ``root`` (symlinks resolved) whose size is exactly what ``shape`` and ``dtype`` need."""
    numel = math.prod(shape)
    expected = numel * torch.empty((), dtype=dtype).element_size()
    if not os.path.lexists(file):
        raise DatasetError(f"load_expert_dataset: {file} ({what}) is missing")
    limits.check_regular_file(file, within=root, error=DatasetError, what=f"load_expert_dataset: {what}:")
    size = file.stat().st_size
    if size != expected:
        raise DatasetError(
            f"load_expert_dataset: {file} does not match meta.json: it holds {size} bytes, but {what} is "
            f"{str(dtype).replace('torch.', '')} {list(shape)} = {expected} bytes "
            f"(the file is {'truncated' if size < expected else 'too long'})"
        )
    if numel == 0:
        return torch.empty(shape, dtype=dtype)
    return torch.from_file(str(file), shared=False, size=numel, dtype=dtype).view(shape)


def load_expert_dataset(path: str | os.PathLike) -> tuple[TensorDict, dict]:
    """Opens a dataset written by :func:`collect_expert_dataset`, read-only.

    Returns:
        ``(steps, meta)``: ``steps`` is a TensorDict ``[num_episodes, horizon]`` of tensors mapped
        from the files (read lazily from disk; opened read-only and mapped copy-on-write, so writing
        to them never changes the dataset); ``meta`` is ``meta.json`` plus ``meta["lengths"]``, an int64 tensor
        ``[num_episodes]`` of episode lengths (steps at or beyond an episode's length are zero).

    Raises:
        DatasetError: the path is missing, holds an unfinished collection, is not a trakdis dataset,
            has another format version, a malformed ``meta.json``, or a data file whose size does not
            match its shape and dtype in ``meta.json`` (each error names the file and the key).
    """
    path = Path(path)
    if not path.exists():
        part = partial_path(path)
        if part.exists():
            done = "?"
            try:
                done = int(limits.read_json(part / "progress.json", within=part, error=DatasetError)["episodes_done"])
            except (DatasetError, KeyError, TypeError, ValueError):
                pass
            raise DatasetError(
                f"load_expert_dataset: {path} does not exist, but {part} holds an unfinished collection "
                f"({done} episodes written); rerun collect_expert_dataset with the same arguments to finish it"
            )
        raise DatasetError(f"load_expert_dataset: no dataset at {path} (directory does not exist)")
    meta = read_meta(path)
    missing = [k for k in REQUIRED_KEYS if k not in meta["keys"]]
    if missing:
        raise DatasetError(f"load_expert_dataset: {path} lacks the per-step keys {missing}")
    n, horizon = meta["num_episodes"], meta["horizon"]
    data = path / "data"
    # Files are read by the layout collect_expert_dataset writes (TensorDict.memmap: one raw file per
    # tensor), sized from meta.json; TensorDict.load_memmap is not used here because it maps directory
    # datasets read-write and extends a short file with zeros on disk.
    steps = TensorDict(
        {key: _open_readonly(data / "steps" / f"{key}.memmap", _DTYPES[spec["dtype"]], (n, horizon, *spec["shape"]),
                             f"steps[{key!r}]", path)
         for key, spec in meta["keys"].items()},
        batch_size=[n, horizon],
    )
    lengths_file = data / "length.memmap"
    lengths = _open_readonly(lengths_file, torch.int64, (n,), "the episode lengths", path)
    bad = ((lengths < 1) | (lengths > horizon)).nonzero()
    if len(bad):
        i = int(bad[0])
        raise DatasetError(f"load_expert_dataset: {lengths_file}: episode {i} has length {int(lengths[i])}; every "
                           f"episode length must lie in [1, {horizon}] (the horizon of meta.json)")
    meta = dict(meta)
    meta["lengths"] = lengths.clone()
    meta["path"] = str(path)
    return steps, meta
