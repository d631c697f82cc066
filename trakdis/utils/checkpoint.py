"""Atomic checkpoints and resume helpers.

A checkpoint is one ``torch.save`` file holding a dict. It is written to a temporary file in
the *same* directory, flushed and ``fsync``-ed, then ``os.replace``-d over the target (atomic on
POSIX and Windows), and the directory entry is ``fsync``-ed too: a run killed at any moment
leaves either the previous complete checkpoint or the new complete one, never a torn file.

:func:`capture_state` / :func:`restore_state` turn a dict of objects with ``state_dict`` /
``load_state_dict`` (modules, optimizers, replay buffers, ...) plus the Python, NumPy and torch
RNG states and plain counters into one checkpoint dict and back.
"""
from __future__ import annotations

import io
import os
import random
import tempfile
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import torch

__all__ = [
    "atomic_write_bytes",
    "save_checkpoint",
    "load_checkpoint",
    "CheckpointError",
    "rng_state",
    "set_rng_state",
    "capture_state",
    "restore_state",
]

_FORMAT = "trakdis-checkpoint"


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable or lacks an expected entry."""


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # e.g. Windows: directories cannot be opened; os.replace is enough there
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temp file in the same dir, fsync, ``os.replace``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    _fsync_dir(path.parent)
    return path


def save_checkpoint(path: str | Path, state: Mapping[str, Any]) -> Path:
    """Atomically ``torch.save`` the dict ``state`` to ``path``."""
    if not isinstance(state, Mapping):
        raise TypeError(f"checkpoint state must be a mapping, got {type(state).__name__}")
    buffer = io.BytesIO()
    torch.save({"format": _FORMAT, **state}, buffer)
    return atomic_write_bytes(path, buffer.getvalue())


def load_checkpoint(
    path: str | Path,
    *,
    required: Iterable[str] = (),
    map_location: str | torch.device | None = "cpu",
) -> dict[str, Any]:
    """Load a checkpoint written by :func:`save_checkpoint`.

    Raises :class:`CheckpointError` naming the file when it is missing, unreadable, not a
    trakdis checkpoint, or lacks one of the ``required`` keys.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        # weights_only=False: checkpoints hold optimizer/buffer states and RNG states (numpy
        # arrays, tuples) that the restricted unpickler rejects. Only load files you wrote.
        state = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as err:
        raise CheckpointError(f"checkpoint {path} could not be read ({type(err).__name__}: {err})") from err
    if not isinstance(state, dict) or state.get("format") != _FORMAT:
        raise CheckpointError(f"{path} is not a trakdis checkpoint (no 'format': {_FORMAT!r} entry)")
    missing = [k for k in required if k not in state]
    if missing:
        raise CheckpointError(f"checkpoint {path} lacks {missing}; it has {sorted(k for k in state if k != 'format')}")
    return state


# --------------------------------------------------------------------------- RNG
def rng_state() -> dict[str, Any]:
    """Python, NumPy and torch (CPU and, if initialised, CUDA) RNG states."""
    state = {
        "python": random.getstate(),
        "numpy": np.random.get_state(),
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: Mapping[str, Any]) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


# --------------------------------------------------------------------------- resume
def capture_state(objects: Mapping[str, Any], **extra: Any) -> dict[str, Any]:
    """``{name: obj.state_dict()}`` for every object, plus RNG states and ``extra`` values.

    Objects without ``state_dict`` (ints, dicts, tensors) are stored as they are.
    """
    state: dict[str, Any] = {}
    for name, obj in objects.items():
        state[name] = obj.state_dict() if hasattr(obj, "state_dict") else obj
    state["rng"] = rng_state()
    state.update(extra)
    return state


def restore_state(state: Mapping[str, Any], objects: Mapping[str, Any], *, restore_rng: bool = True) -> None:
    """Load ``state[name]`` into ``objects[name]`` via ``load_state_dict``; restore RNG states."""
    for name, obj in objects.items():
        if name not in state:
            raise CheckpointError(f"checkpoint has no entry {name!r}; it has {sorted(state)}")
        if not hasattr(obj, "load_state_dict"):
            raise TypeError(f"cannot restore {name!r}: {type(obj).__name__} has no load_state_dict")
        try:
            obj.load_state_dict(state[name])
        except Exception as err:
            raise CheckpointError(f"restoring {name!r} from the checkpoint failed: {err}") from err
    if restore_rng and "rng" in state:
        set_rng_state(state["rng"])
