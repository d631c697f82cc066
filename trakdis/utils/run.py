"""The skeleton every recipe shares: parse the config, find/create the run directory, save
``config.json``, seed, open the CSV log, checkpoint and resume, draw the curves at the end.

A recipe looks like::

    @dataclass
    class MyConfig(RunConfig):
        steps: int = 100
        \"\"\"number of updates\"\"\"

    run = Run.start("my_recipe", MyConfig, argv)
    state = run.resume_state()            # None for a fresh run
    ...
    run.log(step, {"train/loss": 0.1})
    run.save_checkpoint({...}, step=step)  # atomic, and the log is flushed with it
    run.finish()                           # curves.png

``--resume`` reloads ``config.json`` from the run directory and re-applies only the flags given
on the command line, so ``--resume --name X`` continues run X with its own configuration;
the CSV log is truncated to the checkpoint's step so that rows are neither lost nor duplicated.
``--stop-after N`` makes the recipe stop (checkpoint written) once its main counter reaches N,
which is how the tests simulate a killed run. ``--logger tensorboard`` / ``--logger wandb`` log
every ``run.log`` to TorchRL's TensorBoard or W&B logger as well (the wide CSV stays: the recipes
read it back for the curves); the backend's state is saved in the checkpoint, so ``--resume``
continues the same event directory or W&B run. One process at a time holds a run directory (an advisory
lock on its ``.lock`` file, taken before ``config.json`` is written, released by ``finish`` or at exit): a second
``--resume`` of a run that is still going is refused, naming the process, instead of both writing its files.
"""
from __future__ import annotations

import contextlib
import dataclasses
import errno
import os
import random
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Literal, Mapping, Optional, Sequence

import numpy as np
import torch
from torchrl.record.loggers import Logger

from .checkpoint import (FileFormatError, read_checkpoint, remove_stale_temporaries, rng_state, save_checkpoint,
                         set_rng_state)
from .config import load_config, parse_config, save_config
from .limits import MAX_SEED, check_option
from .logger import WideCSVLogger, check_logger_backend, make_run_dir, make_torchrl_logger
from .phases import PhaseTimer
from .plot import plot_csv

__all__ = ["RunConfig", "Run", "RunState", "seed_everything"]

try:
    import fcntl
except ImportError:  # not POSIX (Windows): run directories are not locked
    fcntl = None

_HELD: dict[Path, int] = {}  # run directory -> the descriptor of its locked .lock file, in this process


def _hold_run_dir(directory: Path) -> None:
    """Lock ``directory/.lock`` for this process (again in the same process: a no-op, as when a test resumes a
    run in the process that started it); another process holding it raises, naming its pid."""
    key = directory.resolve()
    if fcntl is None or key in _HELD:
        return
    fd = os.open(directory / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        if err.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
            raise
        raise RuntimeError(f"run directory {directory} is in use by another process (pid {holder}): wait for it "
                           f"to end, or stop it, before running or resuming this run") from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, str(os.getpid()).encode(), 0)
    _HELD[key] = fd


def _release_run_dir(directory: Path) -> None:
    fd = _HELD.pop(directory.resolve(), None)
    if fd is not None:
        os.close(fd)  # closing the only descriptor of the lock releases it


@dataclass
class RunConfig:
    """Options shared by every recipe."""

    name: Optional[str] = None
    """run name; the run directory is <root>/<recipe>/<name> (default: a UTC timestamp)"""
    root: str = "runs"
    """directory holding all runs"""
    resume: bool = False
    """continue the run --name (or the latest run of this recipe) from its checkpoint"""
    seed: int = 0
    """seed of Python, NumPy, torch and the environments"""
    device: str = "cpu"
    """torch device of the models (environments stay on the CPU)"""
    threads: int = 1
    """torch CPU threads (0: torch's default, all cores; 1 avoids oversubscribing a shared CPU)"""
    stop_after: Optional[int] = None
    """stop (checkpoint written) once the recipe's main counter reaches this value; for tests and
    time-sliced runs, continue with --resume"""
    progress: bool = True
    """show tqdm progress bars"""
    logger: Literal["csv", "tensorboard", "wandb"] = "csv"
    """where metrics go: csv (log.csv only), tensorboard or wandb (TorchRL's logger under the run
    directory, and log.csv too); tensorboard and wandb need the extra of that name, e.g.
    pip install 'trakdis[tensorboard]'"""

    def __post_init__(self):
        # checked while the command line is parsed (tyro), before the run directory exists; a recipe's
        # config calls super().__post_init__() from its own
        check_option("seed", self.seed, ge=0, lt=MAX_SEED, integer=True)
        check_option("threads", self.threads, ge=0, integer=True)
        if self.stop_after is not None:
            check_option("stop_after", self.stop_after, ge=0, integer=True)
        # a torch device at all; whether this machine has it is checked by Run.start, after a resumed run's
        # saved configuration met the typed flags (a run started on a GPU may go on with --device cpu)
        check_device(self.device, on_this_machine=False)
        parent = getattr(super(), "__post_init__", None)
        if parent is not None:
            parent()


def check_device(device: str, name: str = "--device", *, on_this_machine: bool = True) -> None:
    """A ``ValueError`` naming ``name`` unless ``device`` is a torch device (that this machine has, with
    ``on_this_machine``)."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError) as err:
        raise ValueError(f"{name} {device!r} is not a torch device (cpu, cuda, cuda:1, mps, ...): {err}") from None
    if not on_this_machine:
        return
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"{name} {device}: this machine has no CUDA device")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ValueError(f"{name} {device}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    if dev.type == "mps" and not (hasattr(torch.backends, "mps") and torch.backends.mps.is_available()):
        raise ValueError(f"{name} {device}: MPS is not available on this machine")


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


class Run:
    """A recipe run: resolved config, run directory, CSV log and checkpoint."""

    def __init__(self, recipe: str, cfg: Any, directory: Path):
        self.recipe = recipe
        self.cfg = cfg
        self.dir = Path(directory)
        self.checkpoint_path = self.dir / "checkpoint.pt"
        self.log_path = self.dir / "log.csv"
        self._logger: WideCSVLogger | None = None
        self._backend: Logger | None = None
        self._resume_state: dict[str, Any] | None = None
        self.t0 = time.time()

    # ------------------------------------------------------------------ start
    @classmethod
    def start(
        cls,
        recipe: str,
        cfg_cls: type,
        argv: Sequence[str] | None = None,
        *,
        presets: Mapping[str, Mapping[str, Any]] | None = None,
        description: str | None = None,
    ) -> "Run":
        cfg = parse_config(cfg_cls, argv, presets=presets, description=description)
        check_logger_backend(cfg.logger)  # before anything is written
        if not cfg.resume:
            check_device(cfg.device)
        resuming = cfg.resume
        directory = make_run_dir(recipe, name=cfg.name, root=cfg.root, resume=resuming)
        saved = directory / "config.json"
        if resuming:
            if not saved.is_file():  # resuming on the defaults would silently run another configuration
                raise FileNotFoundError(
                    f"--resume: {saved} is missing, so the configuration of run {directory} is unknown; restore "
                    f"the file, or start a new run without --resume")
            # The run's own configuration is the default that the typed flags override; --stop-after
            # belongs to one invocation, so a resumed run never inherits it.
            own = dataclasses.replace(load_config(cfg_cls, saved), stop_after=None)
            cfg = parse_config(cfg_cls, argv, presets=presets, description=description, default=own)
            check_logger_backend(cfg.logger)
            check_device(cfg.device)
        _hold_run_dir(directory)  # before anything of the run is written
        for stale in remove_stale_temporaries(directory):  # of an earlier process of this run, killed mid-write
            print(f"removed {stale}, a temporary file of an interrupted write", file=sys.stderr)
        cfg = dataclasses.replace(cfg, name=directory.name, resume=False)
        save_config(cfg, saved)
        run = cls(recipe, cfg, directory)
        run.resuming = resuming
        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        if not cfg.progress:
            os.environ["TRAKDIS_NO_PROGRESS"] = "1"
        seed_everything(cfg.seed)
        if run.resuming:
            if run.checkpoint_path.exists():
                # One's own file, yet read like any other (weights_only); NumPy arrays are allowed
                # for checkpoints written before the RNG state was stored as plain types.
                run._resume_state = read_checkpoint(run.checkpoint_path, map_location="cpu", numpy_arrays=True)
                saved_by = run._resume_state.get("recipe")
                if saved_by is not None and saved_by != recipe:
                    raise FileFormatError(f"--resume: {run.checkpoint_path} is a checkpoint of {saved_by}, not of "
                                          f"{recipe}: it cannot continue this run")
                run.print(f"resuming {directory} from step {run._resume_state.get('step', 0)}")
            else:
                run.print(f"--resume: {run.checkpoint_path} does not exist yet; starting {directory} afresh")
        else:
            run.print(f"run directory: {directory}")
        return run

    # ------------------------------------------------------------------ state
    def resume_state(self) -> dict[str, Any] | None:
        """The checkpoint dict being resumed from (``None`` for a fresh run)."""
        return self._resume_state

    @property
    def logger(self) -> WideCSVLogger:
        if self._logger is None:
            # Rows logged after the checkpoint (or all rows, without a checkpoint) are dropped: the
            # resumed run logs them again.
            step = -1 if self._resume_state is None else int(self._resume_state.get("step", 0))
            self._logger = WideCSVLogger(self.log_path, resume=self.log_path.exists(), truncate_after=step)
        return self._logger

    @property
    def backend(self) -> Logger | None:
        """TorchRL's logger chosen with ``--logger`` (``None`` for ``csv``), opened on first use."""
        if self._backend is None and self.cfg.logger != "csv":
            saved = (self._resume_state or {}).get("logger") or {}
            state = saved.get("state") if saved.get("kind") == self.cfg.logger else None
            self._backend = make_torchrl_logger(self.cfg.logger, self.dir, f"{self.recipe}/{self.dir.name}",
                                                state_dict=state)
            self._backend.log_hparams(_flat_hparams(dataclasses.asdict(self.cfg)))
        return self._backend

    def log(self, step: int, metrics: Mapping[str, Any]) -> None:
        self.logger.log(step, metrics)
        if self.cfg.logger != "csv":
            numbers = {k: v for k, v in metrics.items() if k != "step" and not isinstance(v, str)}
            if numbers:
                self.backend.log_metrics(numbers, step=int(step))

    def save_checkpoint(self, state: Mapping[str, Any], *, step: int) -> Path:
        self.logger.flush()
        extra = {}
        if self._backend is not None:
            extra["logger"] = {"kind": self.cfg.logger, "state": self._backend.state_dict()}
        elif self._resume_state is not None and "logger" in self._resume_state:
            extra["logger"] = self._resume_state["logger"]  # not opened since the resume: keep its state
        return save_checkpoint(self.checkpoint_path, {**state, **extra, "step": int(step), "recipe": self.recipe,
                                                     "config": dataclasses.asdict(self.cfg)})

    def should_stop(self, counter: int) -> bool:
        """True once ``counter`` reached ``--stop-after``."""
        return self.cfg.stop_after is not None and counter >= self.cfg.stop_after

    def print(self, *args: Any) -> None:
        print(f"[{self.recipe} {time.time() - self.t0:7.1f}s]", *args, flush=True)

    def finish(self, *, columns: Sequence[str] | None = None) -> Path | None:
        """Flush the log and write ``curves.png`` (returns its path, or None without a log): the
        curves of ``columns`` that the log has (default: every numeric column); the run directory is released."""
        try:
            return self._finish(columns)
        finally:
            _release_run_dir(self.dir)

    def _finish(self, columns: Sequence[str] | None) -> Path | None:
        if self._backend is not None:
            self._backend.close()
            self._backend = None
        if self._logger is None and not self.log_path.exists():
            return None
        if columns is not None:
            columns = [c for c in columns if c in self.logger.frame().columns]
        self.logger.close()
        try:
            return plot_csv(self.log_path, self.dir / "curves.png", columns=columns)
        except Exception as err:  # a figure must never lose a finished run
            print(f"warning: could not draw curves: {err}", file=sys.stderr)
            return None


def _flat_hparams(cfg: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``cfg`` with nested dicts flattened to ``a.b`` keys and values other than numbers, strings
    and booleans written as strings (what TensorBoard's hparams accept)."""
    out: dict[str, Any] = {}
    for key, value in cfg.items():
        if isinstance(value, Mapping):
            out.update(_flat_hparams(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value if isinstance(value, (bool, int, float, str)) else str(value)
    return out


class RunState(dict):
    """A run's counters (this dict) and the objects whose ``state_dict`` its checkpoint holds.

    ``save()`` writes ``{<name>: obj.state_dict() for each object, "counters": dict(self), "rng":
    <RNG state>}`` at step ``self[step_key]``; on ``--resume`` the counters come back at once, the
    objects with :meth:`load` and the RNG streams with :meth:`restore_rng` (each when the recipe has
    built what must come before it)::

        state = RunState(run, {"updates": 0}, step_key="updates", updater=updater, buffer=buffer)
        state.load()           # no-op on a fresh run
        ...
        state["updates"] += 1
        state.save()
        if state.save_and_should_stop(total, key="rounds", unit="round"):   # end of a round
            return                                                            # --stop-after

    ``on_save`` (if set) is called first, to put derived values into the counters. With
    ``phases_key``, ``self.phases`` is a :class:`~trakdis.utils.phases.PhaseTimer` that continues the
    counter ``phases_key`` (a resumed run's time per phase) and is saved into it.
    ``counters_key=None`` keeps the counters at the checkpoint's top level instead (a counter
    missing from a checkpoint keeps its initial value).
    """

    def __init__(self, run: Run, counters: Mapping[str, Any], *, step_key: str, counters_key: str | None = "counters",
                 phases_key: str | None = None, **objects: Any):
        super().__init__(counters)
        self.run, self.step_key, self.counters_key, self.objects = run, step_key, counters_key, objects
        self.on_save = None
        self.checkpoint = run.resume_state()
        if self.checkpoint is not None:
            if counters_key is None:
                self.update({k: self.checkpoint[k] for k in counters if k in self.checkpoint})
            elif not isinstance(self.checkpoint.get(counters_key), Mapping):
                raise FileFormatError(f"--resume: {run.checkpoint_path} has no {counters_key!r} entry of "
                                      f"{run.recipe}'s counters: not a checkpoint of this recipe")
            else:
                self.update(self.checkpoint[counters_key])
        self.phases_key, self.phases = phases_key, None
        if phases_key is not None:
            self.phases = PhaseTimer(self.setdefault(phases_key, {}))

    @property
    def resuming(self) -> bool:
        """Whether a checkpoint is being resumed from."""
        return self.checkpoint is not None

    def load(self, *names: str) -> None:
        """Load the named objects' (default: all) state from the checkpoint being resumed, if any."""
        if self.checkpoint is not None:
            for name in names or tuple(self.objects):
                if name not in self.checkpoint:
                    raise FileFormatError(f"--resume: {self.run.checkpoint_path} has no {name!r} entry; it has "
                                          f"{sorted(self.checkpoint)}")
                self.objects[name].load_state_dict(self.checkpoint[name])

    def restore_rng(self) -> None:
        """Set the RNG streams to the checkpoint's, if resuming."""
        if self.checkpoint is not None:
            set_rng_state(self.checkpoint["rng"])

    def save(self) -> Path:
        if self.phases is not None:
            self[self.phases_key] = self.phases.state_dict()
        if self.on_save is not None:
            self.on_save()
        counters = dict(self) if self.counters_key is None else {self.counters_key: dict(self)}
        return self.run.save_checkpoint({**{k: obj.state_dict() for k, obj in self.objects.items()}, **counters,
                                         "rng": rng_state()}, step=self[self.step_key])

    def once(self, key: str, fn: Callable[[], Any]) -> None:
        """``fn()`` unless the counter ``key`` says it ran (in this run, or the run resumed): then
        the counter is set and the state saved (e.g. a file written from the model as it is now)."""
        if not self.get(key):
            fn()
            self[key] = True
            self.save()

    def finish(self, *, columns: Sequence[str] | None = None, extra: Mapping[str, Any] | None = None) -> None:
        """The end of a run: :meth:`save`, then :meth:`Run.finish` (``curves.png`` of ``columns``), as
        the phase ``"files and curves"``; with phases, their table printed and written to
        ``phases.json`` (with ``extra``)."""
        with self.phases.phase("files and curves") if self.phases is not None else contextlib.nullcontext():
            self.save()
            self.run.finish(columns=columns)
        if self.phases is not None:
            self.phases.report(self.run.print, self.run.dir / "phases.json", total_wall=time.time() - self.run.t0,
                               resumed=self.run.resuming, extra=extra)

    def save_and_should_stop(self, total: int, *, key: str | None = None, unit: str | None = None) -> bool:
        """:meth:`save`, then whether the run stops here: ``--stop-after`` reached by ``self[key]``
        (default: the step key) before ``total``; a stop is announced as ``"stopping after <unit>
        <n> (--stop-after); continue with --resume"`` (``unit`` defaults to ``key``)."""
        self.save()
        key = self.step_key if key is None else key
        if self.run.should_stop(self[key]) and self[key] < total:
            self.run.print(f"stopping after {unit or key} {self[key]} (--stop-after); continue with --resume")
            return True
        return False
