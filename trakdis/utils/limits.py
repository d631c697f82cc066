"""The limits on what a file from someone else, or a number on the command line, may ask for.

Every policy, encoder and dataset file is untrusted input (docs/security.md): before anything
it describes is allocated, its sizes are checked against the limits below, so that a crafted or
damaged file ends with an error naming it, never with the machine out of memory or a run that
never ends. Each limit is a named constant here; the ones a legitimate file may outgrow can be
raised by the caller (``load_policy(max_params=...)``, the recipes' ``--max-params``).

* Files: :func:`open_regular_file` / :func:`check_regular_file` accept regular files only (a FIFO
  would block, ``/dev/zero`` never ends) and, with ``within``, only paths that stay inside a
  directory once symlinks are resolved; :func:`read_json` reads at most :data:`MAX_JSON_BYTES`;
  :func:`check_zip_archive` bounds what a ``torch.save`` archive unpacks to (:data:`MAX_EXPANSION`
  times its size on disk, and ``max_bytes`` in all) before ``torch.load`` reads it.
* Models: :data:`MAX_PARAMS` parameters and :data:`MAX_ACTIVATION_BYTES` of activations per
  acting window, estimated from a file's config before the model is built;
  :data:`MAX_LAYERS`, :data:`MAX_MEMBERS` bound the module counts.
* Environments: :func:`check_env_kwargs`, the env options a policy file may carry and their
  ranges (:data:`ENV_KWARG_RANGES`); :data:`MAX_HORIZON` steps per episode.
* Options: :func:`check_option`, one range check of a parsed number that names the flag;
  :func:`cap_workers`, environments and worker processes bounded by the work and the cores.
"""
from __future__ import annotations

import json
import math
import os
import stat
import warnings
import zipfile
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

__all__ = [
    "MAX_PARAMS", "MAX_ACTIVATION_BYTES", "MAX_LAYERS", "MAX_MEMBERS", "MAX_HORIZON", "MAX_JSON_BYTES",
    "MAX_EXPANSION", "MAX_SEED", "ENV_KWARG_RANGES", "MAX_SIM_SUBSTEPS", "MIN_CORE_CAP",
    "check_regular_file", "open_regular_file", "read_json", "check_zip_archive", "check_env_kwargs",
    "check_option", "check_options", "cap_workers", "available_cores", "is_int",
]

MAX_PARAMS = 25_000_000
"""parameters of one model built from a file (the paper's teacher: about 8 M); ``--max-params`` raises it"""
MAX_ACTIVATION_BYTES = 2**30
"""float32 activations of one model's forward pass on one acting window, estimated from its config"""
MAX_LAYERS = 256
"""transformer blocks (``n_layer``) or MLP layers of a model from a file"""
MAX_MEMBERS = 64
"""encoders of an ensemble in an encoder file"""
MAX_HORIZON = 10_000
"""steps of an episode (the paper: 100), from a file or from ``--horizon``"""
MAX_JSON_BYTES = 16 * 2**20
"""size of a JSON file read from a dataset or run directory (``meta.json`` of 8000 episodes: a few kB)"""
MAX_EXPANSION = 2.0
"""bytes a ``torch.save`` archive may unpack to per byte of the file (``torch.save`` stores its
entries uncompressed, so its own files unpack to less than their size)"""
MAX_SEED = 2**63
"""seeds are ints in ``[0, MAX_SEED)`` (``torch.manual_seed`` takes up to ``2**64 - 1``; the recipes add offsets)"""
MAX_SIM_SUBSTEPS = 64
MIN_CORE_CAP = 8
"""environments or worker processes a machine with fewer cores still starts when asked (see :func:`cap_workers`)"""
"""physics steps per env step (``action_repeat * substeps``; the default env: 8) of a policy file's env options"""

# env options a policy file may carry: name -> (type, low, high); None: unbounded on that side
ENV_KWARG_RANGES: dict[str, tuple[type, Any, Any]] = {
    "resolution": (int, 4, 30),
    "timestep": (float, 1e-5, 0.02),
    "substeps": (int, 1, 16),
    "iterations": (int, 1, 200),
    "solver": (str, ("CG", "Newton", "PGS"), None),
    "tolerance": (float, 0.0, 1.0),
    "selfcollide": (str, ("none", "narrow", "bvh", "sap", "auto"), None),
    "action_repeat": (int, 1, 64),
    "move_per_substep": (float, 1e-4, 0.1),
    "grasp_radius": (float, 1e-3, 0.2),
    "render_supersample": (int, 1, 8),
}
"""The env options (:class:`~trakdis.envs.ClothEnv` arguments) a policy file's ``env_kwargs`` may
set, each with its type and range (a ``str`` option: its allowed values); ``action_repeat *
substeps`` at most :data:`MAX_SIM_SUBSTEPS`. The episode length is the file's ``horizon`` (or
``--horizon``), never an env option."""


def is_int(value: Any) -> bool:
    """An int that is not a bool (``True`` is an ``int`` to Python, never a count here)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def is_number(value: Any) -> bool:
    """A finite real number that is not a bool."""
    return (isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
            and math.isfinite(value))


# --------------------------------------------------------------------------- files
def _inside(path: Path, within: str | os.PathLike) -> None:
    root = Path(within).resolve()
    resolved = Path(path).resolve()
    if resolved != root and root not in resolved.parents:
        raise PermissionError(f"{path} leads outside {within} (to {resolved}): files of a dataset or run are read "
                              f"from inside its directory only")


def check_regular_file(path: str | os.PathLike, *, within: str | os.PathLike | None = None,
                       error: type[Exception] = ValueError, what: str = "file") -> Path:
    """``path``, if it is a regular file (symlinks followed) and, with ``within``, resolves to a path
    inside that directory; else ``error`` naming it (missing, a FIFO, a device, a directory, or a
    symlink leading out). Reads nothing from it."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise error(f"{what} {path} does not exist") from None
    except OSError as err:
        raise error(f"{what} {path} cannot be read ({err.strerror})") from None
    if not stat.S_ISREG(mode):
        kind = ("a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else
                "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "a socket" if stat.S_ISSOCK(mode) else
                "a special file")
        raise error(f"{what} {path} is not a regular file ({kind}): trakdis reads regular files only")
    if within is not None:
        try:
            _inside(path, within)
        except PermissionError as err:
            raise error(str(err)) from None
    return path


def open_regular_file(path: str | os.PathLike, *, within: str | os.PathLike | None = None,
                      error: type[Exception] = ValueError, what: str = "file"):
    """``path`` opened for binary reading, once :func:`check_regular_file` accepts it; opened without
    blocking and checked again on the descriptor, so that a file swapped for a FIFO in between is
    refused rather than waited on."""
    path = check_regular_file(path, within=within, error=error, what=what)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as err:
        raise error(f"{what} {path} cannot be read ({err.strerror})") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise error(f"{what} {path} is not a regular file: trakdis reads regular files only")
    return os.fdopen(fd, "rb")


def read_json(path: str | os.PathLike, *, within: str | os.PathLike | None = None, max_bytes: int | None = None,
              error: type[Exception] = ValueError, what: str = "file") -> Any:
    """The JSON value of a regular file of at most ``max_bytes`` bytes (default :data:`MAX_JSON_BYTES`;
    :func:`open_regular_file`); anything else, or invalid JSON, is ``error`` naming the file."""
    max_bytes = MAX_JSON_BYTES if max_bytes is None else int(max_bytes)
    with open_regular_file(path, within=within, error=error, what=what) as fh:
        raw = fh.read(max_bytes + 1)
    if len(raw) > max_bytes:
        raise error(f"{what} {path} is larger than {max_bytes} bytes (trakdis.utils.limits.MAX_JSON_BYTES): "
                    f"not a file trakdis wrote")
    try:
        return json.loads(raw)
    except ValueError as err:
        raise error(f"{what} {path} is not valid JSON ({err})") from err


def check_zip_archive(path: str | os.PathLike, *, max_bytes: int | None = None, max_expansion: float = MAX_EXPANSION,
                      error: type[Exception] = ValueError, hint: str = "") -> int:
    """The bytes the ``torch.save`` archive at ``path`` unpacks to, read from its zip directory (nothing
    is unpacked): ``error`` naming the file if it is no zip archive (not a checkpoint at all), if it
    unpacks to more than ``max_expansion`` times its size (a compressed "zip bomb") or, with
    ``max_bytes``, to more than ``max_bytes`` (``hint``: how to raise that limit)."""
    size = os.path.getsize(path)
    try:
        with zipfile.ZipFile(path) as archive:
            infos = archive.infolist()
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as err:
        raise error(f"{path} is not a valid checkpoint: not the zip archive torch.save writes ({err})") from None
    unpacked = sum(info.file_size for info in infos)
    if unpacked > max_expansion * max(size, 1):
        raise error(f"{path} unpacks to {unpacked} bytes from a {size}-byte file ({unpacked / max(size, 1):.0f}x; "
                    f"torch.save's own files unpack to their size, at most {max_expansion:g}x: "
                    f"trakdis.utils.limits.MAX_EXPANSION): refused as a compressed archive bomb")
    if max_bytes is not None and unpacked > max_bytes:
        raise error(f"{path} holds {unpacked} bytes of data, more than the {max_bytes} a model within the parameter "
                    f"limit needs{hint}")
    return unpacked


# --------------------------------------------------------------------------- env options from a file
def check_env_kwargs(kwargs: Any, source: str, *, error: type[Exception] = ValueError) -> dict[str, Any]:
    """A policy file's ``env_kwargs``, checked against :data:`ENV_KWARG_RANGES` (an option not
    listed, such as ``horizon``, a value of the wrong type or out of range, or ``action_repeat *
    substeps`` above :data:`MAX_SIM_SUBSTEPS`: ``error`` naming ``source`` and the key)."""
    if kwargs is None:
        return {}
    if not isinstance(kwargs, Mapping):
        raise error(f"{source}: 'env_kwargs' must map env options to values, got {type(kwargs).__name__}")
    out = {}
    for key, value in kwargs.items():
        if key not in ENV_KWARG_RANGES:
            raise error(f"{source}: env_kwargs.{key} is not an env option a policy file may set (allowed: "
                        f"{', '.join(ENV_KWARG_RANGES)}; the episode length is the file's 'horizon')")
        kind, low, high = ENV_KWARG_RANGES[key]
        if kind is str:
            ok = isinstance(value, str) and value in low
            allowed = f"one of {list(low)}"
        else:
            ok = (is_int(value) if kind is int else is_number(value)) and low <= value <= high
            allowed = f"{'an int' if kind is int else 'a number'} in [{low:g}, {high:g}]"
        if not ok:
            raise error(f"{source}: env_kwargs.{key} must be {allowed}, got {value!r}")
        out[key] = value
    sub = out.get("action_repeat", 8) * out.get("substeps", 1)
    if sub > MAX_SIM_SUBSTEPS:
        raise error(f"{source}: env_kwargs ask for {sub} physics steps per env step (action_repeat x substeps), "
                    f"more than {MAX_SIM_SUBSTEPS} (trakdis.utils.limits.MAX_SIM_SUBSTEPS; the default env: 8)")
    return out


# --------------------------------------------------------------------------- options
def flag(name: str) -> str:
    """The command-line flag of a config field: ``grad_clip`` -> ``--grad-clip``."""
    return "--" + name.replace("_", "-")


def check_option(name: str, value: Any, *, ge: float | None = None, gt: float | None = None,
                 le: float | None = None, lt: float | None = None, integer: bool = False) -> None:
    """A ``ValueError`` naming the flag of ``name`` unless ``value`` is a finite number (an int, with
    ``integer``) within the bounds given: ``"--grad-clip must be >= 0, got -1.0"``. Raised from a config's
    ``__post_init__``, tyro reports it while parsing, before a run directory exists."""
    bounds = [f"{op} {b:g}" for op, b in ((">=", ge), (">", gt), ("<=", le), ("<", lt)) if b is not None]
    need = " and ".join(bounds) if bounds else "a finite number"
    good = is_int(value) if integer else is_number(value)
    if good:
        good = ((ge is None or value >= ge) and (gt is None or value > gt) and (le is None or value <= le)
                and (lt is None or value < lt))
    if not good:
        kind = "an int" if integer else "a finite number"
        raise ValueError(f"{flag(name) if not name.startswith('-') else name} must be {kind} {need}, got {value!r}")


def check_options(cfg: Any, *, sizes: tuple[str, ...] = (), counts: tuple[str, ...] = (),
                  positive: tuple[str, ...] = (), nonnegative: tuple[str, ...] = (), prefix: str = "") -> None:
    """:func:`check_option` of several fields of a config dataclass: ``sizes`` ints >= 1, ``counts`` ints
    >= 0, ``positive`` numbers > 0, ``nonnegative`` numbers >= 0 (a field set to None is skipped: its
    default applies). ``prefix``: the section of a nested config (``"data."``)."""
    for names, bounds in ((sizes, dict(ge=1, integer=True)), (counts, dict(ge=0, integer=True)),
                          (positive, dict(gt=0)), (nonnegative, dict(ge=0))):
        for name in names:
            value = getattr(cfg, name)
            if value is not None:
                check_option(prefix + name, value, **bounds)


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask; ``os.cpu_count()`` elsewhere)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def cap_workers(requested: int, work: int, *, what: str = "--num-envs", unit: str = "episodes",
                warn: Callable[[str], None] | None = None) -> int:
    """``min(requested, work, max(cores, MIN_CORE_CAP))``: environments (worker processes) to start for
    ``work`` episodes. More would only hold memory (a MuJoCo env each) and processes with nothing to do; a
    lowered count is said (``warn``, default: a ``UserWarning``). The number of envs decides which
    configurations an evaluation plays, so a count up to :data:`MIN_CORE_CAP` (the defaults: 2) is never
    lowered for the machine: the same command plays the same episodes on any machine."""
    requested, work = int(requested), int(work)
    if requested < 1:
        raise ValueError(f"{what} must be >= 1, got {requested}")
    cores = max(available_cores(), MIN_CORE_CAP)
    n = max(1, min(requested, max(work, 1), cores))
    if n < requested:
        why = f"{work} {unit}" if n == max(work, 1) else f"{cores} CPU cores"
        message = f"{what} {requested}: starting {n} (there are {why})"
        if warn is None:
            warnings.warn(message, stacklevel=2)
        else:
            warn(message)
    return n
