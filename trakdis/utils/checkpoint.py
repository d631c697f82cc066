"""Atomic checkpoints and resume helpers.

A checkpoint is one ``torch.save`` file holding a dict. It is written to a temporary file in
the *same* directory, flushed and ``fsync``-ed, then ``os.replace``-d over the target (atomic on
POSIX and Windows), and the directory entry is ``fsync``-ed too: a run killed at any moment
leaves either the previous complete checkpoint or the new complete one, never a torn file.

:func:`capture_state` / :func:`restore_state` turn a dict of objects with ``state_dict`` /
``load_state_dict`` (modules, optimizers, replay buffers, ...) plus the Python, NumPy and torch
RNG states (TorchRL's ``torchrl.checkpoint.GlobalRNGState``) and plain counters into one checkpoint
dict and back.

Every file is read with ``torch.load(weights_only=True)``: PyTorch's restricted unpickler builds
tensors, containers and numbers only, so a crafted file cannot run code while it is loaded
(docs/security.md). Checkpoints therefore hold only such types: :func:`rng_state` stores the NumPy
RNG state with a tensor key. Resume checkpoints written before that (NumPy arrays inside) load with
``numpy_arrays=True``, which allow-lists NumPy's array types, nothing else.
Before ``torch.load`` runs, the file must be a regular file and a zip archive that unpacks to at
most :data:`~trakdis.utils.limits.MAX_EXPANSION` times its size (``max_bytes`` in all, when given).

A write follows the umask (``0o666 & ~umask``, as ``open`` creates files); a write killed before its
rename leaves a ``.<name>.<random>.tmp`` file, which :func:`remove_stale_temporaries` deletes when the
run (or collection) owning the directory starts again.

Why not ``torchrl.checkpoint.Checkpoint`` for the files (checked in TorchRL 0.14): it writes a directory,
or a zip of one, with a JSON manifest and one payload per component, not the one ``torch.save`` dict
that every policy, encoder and resume file written so far is; it publishes with ``os.replace`` but
fsyncs neither the file nor the directory, names its leftovers ``.<name>.stage-<hex>`` directories, and
loads an archive by extracting its members to a temporary directory without a bound on their size and
without checking that the path is a regular file. Its ``GlobalRNGState`` is used for the RNG streams.
"""
from __future__ import annotations

import io
import os
import pickle
import re
import tempfile
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import torch
from torchrl.checkpoint import GlobalRNGState

from .limits import check_zip_archive, open_regular_file

__all__ = [
    "atomic_write_bytes",
    "save_checkpoint",
    "read_checkpoint",
    "FileFormatError",
    "remove_stale_temporaries",
    "rng_state",
    "set_rng_state",
    "capture_state",
    "restore_state",
]

_FORMAT = "trakdis-checkpoint"


class FileFormatError(RuntimeError):
    """A file trakdis reads back (a resume checkpoint, a policy or encoder file: :func:`save_checkpoint`'s
    format) is missing, unreadable, refused (docs/security.md), or lacks or mistypes an expected entry.

    Not TorchRL's ``torchrl.checkpoint.CheckpointError`` (the failures of its ``Checkpoint`` directories)."""


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


def _umask() -> int:
    """This process's umask, read without changing it where Linux tells it (``/proc/self/status``)."""
    try:
        with open("/proc/self/status", "rb") as fh:
            for line in fh:
                if line.startswith(b"Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)  # elsewhere: read by setting it (not thread-safe, but rare)
    os.umask(mask)
    return mask


# the name of atomic_write_bytes' temporary files: "." + target name + "." + mkstemp's 8 characters + ".tmp"
_TEMPORARY = re.compile(r"\..+\.[a-z0-9_]{8}\.tmp")


def remove_stale_temporaries(directory: str | Path) -> list[Path]:
    """Delete the temporary files that :func:`atomic_write_bytes` left in ``directory`` when its process
    was killed before the rename (regular files named ``.<name>.<8 characters>.tmp``; symlinks and
    anything else are left alone). Call it only while no other process writes there (a run holds its
    directory's lock). Returns the files removed."""
    removed = []
    try:
        entries = list(os.scandir(directory))
    except OSError:
        return removed
    for entry in entries:
        if _TEMPORARY.fullmatch(entry.name) and entry.is_file(follow_symlinks=False):
            try:
                os.unlink(entry.path)
                removed.append(Path(entry.path))
            except FileNotFoundError:
                pass
    return removed


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temp file in the same dir, fsync, ``os.replace``), with the
    mode a plain ``open`` gives (``0o666 & ~umask``; ``mkstemp`` alone would leave ``0o600``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())
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


def _numpy_array_globals() -> list:
    """NumPy's array-reconstruction globals: what a pickled ``np.ndarray`` (the NumPy RNG state
    of checkpoints written before :func:`rng_state` stored plain types) needs, and nothing else."""
    core = getattr(np, "_core", None) or np.core
    return [core.multiarray._reconstruct, np.ndarray, np.dtype, type(np.dtype(np.uint32))]


def read_checkpoint(
    path: str | Path,
    *,
    required: Iterable[str] = (),
    map_location: str | torch.device | None = "cpu",
    numpy_arrays: bool = False,
    max_bytes: int | None = None,
    limit_hint: str = "",
) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint` (not TorchRL's ``torchrl.render.load_checkpoint``:
    this one checks the file before unpickling it and refuses files trakdis did not write).

    The file is read with ``torch.load(weights_only=True)`` (tensors, containers, numbers and
    strings only): a file holding anything else, e.g. an object whose unpickling would run code,
    is refused before any of it runs. ``numpy_arrays=True`` also allows NumPy arrays (resume
    checkpoints written by earlier versions hold the NumPy RNG state as one).

    Before anything is unpickled, the file must be a regular file (not a FIFO or a device), a zip
    archive (``torch.save``'s format) and unpack to at most
    :data:`~trakdis.utils.limits.MAX_EXPANSION` times its size, and to at most ``max_bytes`` when
    given (``limit_hint``: how the caller raises that limit, for the error).

    Raises :class:`FileFormatError` naming the file when it is missing, not a regular file, not a
    checkpoint, too large, unreadable, holds types the safe loader refuses, is not a trakdis
    checkpoint, or lacks one of the ``required`` keys.
    """
    path = Path(path)
    with open_regular_file(path, error=FileFormatError, what="checkpoint") as fh:
        check_zip_archive(path, max_bytes=max_bytes, error=FileFormatError, hint=limit_hint)
        state = _torch_load(path, fh, map_location=map_location, numpy_arrays=numpy_arrays)
    if not isinstance(state, dict) or state.get("format") != _FORMAT:
        raise FileFormatError(f"{path} is not a trakdis checkpoint (no 'format': {_FORMAT!r} entry)")
    missing = [k for k in required if k not in state]
    if missing:
        raise FileFormatError(f"checkpoint {path} lacks {missing}; it has {sorted(k for k in state if k != 'format')}")
    return state


def _torch_load(path: Path, fh, *, map_location, numpy_arrays: bool) -> Any:
    try:
        with torch.serialization.safe_globals(_numpy_array_globals() if numpy_arrays else []):
            return torch.load(fh, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as err:
        lines = str(err).strip().splitlines() or [""]
        if not any("GLOBAL" in line or "global" in line for line in lines):  # damaged, not a refused type
            detail = next((line for line in lines if "Unsupported" in line), lines[-1]).strip()
            raise FileFormatError(f"{path} is not a valid checkpoint: its contents are damaged ({detail})") from err
        detail = next((line for line in lines if "GLOBAL" in line), lines[-1]).split(" Please use")[0].strip()
        raise FileFormatError(
            f"checkpoint {path} was refused: it holds objects other than tensors, containers and numbers, "
            f"which trakdis never loads from a file (torch.load(weights_only=True); docs/security.md). {detail}"
        ) from err
    except Exception as err:
        raise FileFormatError(f"checkpoint {path} could not be read ({type(err).__name__}: {err})") from err


# --------------------------------------------------------------------------- RNG
def rng_state() -> dict[str, Any]:
    """Python, NumPy and torch (CPU and initialised accelerators) RNG states: TorchRL's
    ``GlobalRNGState().state_dict()`` (keys ``"python"``, ``"numpy"``, ``"torch_cpu"``, ``"torch_cuda"``, ...),
    types that ``torch.load(weights_only=True)`` reads (the NumPy key: a tensor)."""
    return GlobalRNGState().state_dict()


def set_rng_state(state: Mapping[str, Any]) -> None:
    """Restore :func:`rng_state`'s streams (``GlobalRNGState().load_state_dict``). Checkpoints written
    before hold keys ``"torch"`` / ``"cuda"`` and NumPy's state as ``get_state(legacy=False)``'s dict
    (a tensor key) or its legacy tuple (an ndarray key): they are converted first."""
    state = dict(state)
    if "torch_cpu" not in state:  # the earlier layout
        np_state = state["numpy"]
        if isinstance(np_state, Mapping):
            np_state = (np_state["bit_generator"], torch.as_tensor(np_state["state"]["key"]), np_state["state"]["pos"],
                        np_state["has_gauss"], np_state["gauss"])
        state = {"python": state["python"], "numpy": np_state, "torch_cpu": state["torch"],
                 **({"torch_cuda": state["cuda"]} if "cuda" in state else {})}
    # GlobalRNGState.load_state_dict raises when the state holds CUDA's and CUDA is unavailable; a run
    # started on a GPU resumes on a CPU-only machine (as it did before), its CUDA streams unused there.
    if not torch.cuda.is_available():
        state.pop("torch_cuda", None)
    GlobalRNGState().load_state_dict(state)


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
            raise FileFormatError(f"checkpoint has no entry {name!r}; it has {sorted(state)}")
        if not hasattr(obj, "load_state_dict"):
            raise TypeError(f"cannot restore {name!r}: {type(obj).__name__} has no load_state_dict")
        try:
            obj.load_state_dict(state[name])
        except Exception as err:
            raise FileFormatError(f"restoring {name!r} from the checkpoint failed: {err}") from err
    if restore_rng and "rng" in state:
        set_rng_state(state["rng"])
