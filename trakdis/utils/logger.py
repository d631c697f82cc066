"""Run directories and a one-table CSV logger.

``runs/<recipe>/<name>/`` holds ``config.json``, ``log.csv``, ``curves.png`` and
``checkpoint.pt``. TorchRL's ``torchrl.record.loggers.CSVLogger`` writes one file per scalar
(``scalars/<name>.csv``); its ``state_dict`` restores its scalar history and step counters on resume,
but its files keep (and then repeat) the rows a killed run wrote after its last checkpoint. This
module keeps one wide table instead: one row per logged step, one stable column per metric
(``train/loss_nll``, ``eval/normalized_performance``), rewritten atomically with pandas and, on
resume, cut back to the checkpoint's step (``truncate_after``).
:class:`WideCSVLogger` is a ``torchrl.record.loggers.Logger``, so TorchRL-style code
(``log_scalar``, ``log_metrics``) writes into the same table; :func:`make_torchrl_logger` opens
TorchRL's TensorBoard or W&B logger in a run directory, for runs that log to one of them as well.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import importlib.util
import json
import math
import numbers
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import pandas as pd
from tensordict import TensorDictBase
from torchrl.record.loggers import Logger, get_logger

from .checkpoint import atomic_write_bytes
from .limits import check_regular_file

__all__ = ["check_run_name", "make_run_dir", "latest_run_dir", "latest_run_file", "WideCSVLogger",
           "LOGGER_PACKAGES", "check_logger_backend", "make_torchrl_logger"]


def latest_run_dir(root: str | Path, recipe: str) -> Path | None:
    """The most recently modified run directory of ``recipe`` under ``root`` (or ``None``)."""
    base = Path(root) / recipe
    if not base.is_dir():
        return None
    runs = [p for p in base.iterdir() if p.is_dir() and (p / "config.json").exists()]
    return max(runs, key=lambda p: p.stat().st_mtime) if runs else None


def latest_run_file(spec: str, root: str | Path, recipe: str, filename: str, *, flag: str) -> Path:
    """``spec`` as a path; for ``"latest"``, ``filename`` in the newest run of ``recipe`` under
    ``root`` (a ``FileNotFoundError`` naming the recipe to run and the option ``flag`` if none has it)."""
    if spec != "latest":
        return Path(spec)
    run = latest_run_dir(root, recipe)
    if run is None or not (run / filename).exists():
        raise FileNotFoundError(f"no {filename} under {Path(root) / recipe}: run recipes/{recipe}.py first "
                                f"or pass {flag} PATH")
    return run / filename


def check_run_name(name: str) -> str:
    """``name`` if it is a plain directory name; a ``ValueError`` naming ``--name`` otherwise (a path
    separator, ``.``, ``..``, an absolute path or an empty name would put the run outside
    ``<root>/<recipe>/`` or on top of it)."""
    seps = [s for s in (os.sep, os.altsep, "/") if s]
    if (not isinstance(name, str) or name in ("", ".", "..") or any(s in name for s in seps) or "\0" in name
            or Path(name).is_absolute()):
        raise ValueError(
            f"--name {name!r} is not a plain run name: the run directory is <root>/<recipe>/<name>, so a name "
            f"must not be empty, '.' or '..', an absolute path, or contain a path separator "
            f"(choose the parent directory with --root)"
        )
    return name


def make_run_dir(
    recipe: str,
    *,
    name: str | None = None,
    root: str | Path = "runs",
    resume: bool = False,
) -> Path:
    """Create (or, with ``resume``, find) ``<root>/<recipe>/<name>``.

    ``name`` defaults to a UTC timestamp; with ``resume`` and no name, the latest run of the
    recipe is resumed. A fresh run refuses to reuse a directory that already holds a
    checkpoint or a log, so nothing is overwritten by accident. ``name`` must be a plain
    directory name (see :func:`check_run_name`): a run never leaves ``<root>/<recipe>/``.
    """
    if name is not None:
        check_run_name(name)
    root = Path(root)
    if resume:
        if name is None:
            run = latest_run_dir(root, recipe)
            if run is None:
                raise FileNotFoundError(f"--resume: no earlier run of {recipe!r} under {root / recipe}")
            return run
        run = root / recipe / name
        if not run.is_dir():
            raise FileNotFoundError(f"--resume: run directory {run} does not exist")
        return run
    if name is None:
        name = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%d-%H%M%S")
        run = root / recipe / name
        i = 1
        while run.exists():
            run = root / recipe / f"{name}-{i}"
            i += 1
    else:
        run = root / recipe / name
        if any((run / f).exists() for f in ("checkpoint.pt", "log.csv")):
            raise FileExistsError(
                f"run directory {run} already holds a run; pass --resume to continue it or "
                "choose another --name"
            )
    run.mkdir(parents=True, exist_ok=True)
    return run


def _scalar(value: Any, key: str) -> float | int | str:
    if hasattr(value, "item") and callable(value.item):
        try:
            value = value.item()
        except (ValueError, RuntimeError) as err:
            raise ValueError(f"metric {key!r} is not a scalar (shape {tuple(getattr(value, 'shape', ()))})") from err
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, numbers.Number) or isinstance(value, str):
        return value
    raise TypeError(f"metric {key!r} has unsupported type {type(value).__name__}")


class WideCSVLogger(Logger):
    """One-table CSV log: ``log(step, {"train/loss_nll": 0.3, ...})`` adds/merges one row.

    Rows with the same ``step`` are merged (train and eval metrics of one step share a row).
    The file is rewritten atomically on :meth:`flush` (every ``flush_every`` rows and at
    :meth:`close`). With ``resume=True`` the existing file is read back; pass
    ``truncate_after=step`` to drop rows logged after the checkpoint being resumed from, so a
    killed run neither loses nor duplicates rows.

    As a ``torchrl.record.loggers.Logger``: ``log_scalar(name, value, step)`` and
    ``log_metrics(metrics, step)`` merge into the row of ``step`` (without a step, the n-th value
    of a name goes to step n, as in TorchRL's ``CSVLogger``); ``log_hparams(cfg)`` writes
    ``hparams.json`` beside the table; videos and histograms are not scalars and raise
    ``NotImplementedError``. ``exp_name`` (default: the name of the file's directory, the run
    name) and ``log_dir`` (the file's directory) are the ``Logger`` attributes; there is no
    separate ``experiment`` object (``None``): the table is the logger.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        resume: bool = False,
        truncate_after: int | None = None,
        flush_every: int = 1,
        exp_name: str | None = None,
    ) -> None:
        self.path = Path(path)
        super().__init__(exp_name=self.path.parent.name if exp_name is None else exp_name,
                         log_dir=str(self.path.parent))
        self.flush_every = max(1, int(flush_every))
        self._rows: dict[int, dict[str, Any]] = {}
        self._columns: list[str] = ["step"]
        self._pending = 0
        if resume and self.path.exists():
            check_regular_file(self.path, what="log")
            try:
                frame = pd.read_csv(self.path)
            except pd.errors.EmptyDataError:
                frame = pd.DataFrame(columns=["step"])
            except (pd.errors.ParserError, UnicodeDecodeError, ValueError) as err:
                raise ValueError(f"{self.path} is not a readable CSV log ({type(err).__name__}: {err}); restore it, "
                                 f"or move it away to resume with a new log") from None
            if "step" not in frame.columns:
                raise ValueError(f"{self.path} has no 'step' column; columns are {list(frame.columns)}")
            steps = pd.to_numeric(frame["step"], errors="coerce")
            if steps.isna().any() or not (steps == steps.round()).all():
                raise ValueError(f"{self.path}: its 'step' column holds values that are not step numbers; restore "
                                 f"the log, or move it away to resume with a new log")
            for col in frame.columns:
                if col not in self._columns:
                    self._columns.append(col)
            for record in frame.to_dict("records"):
                step = int(record["step"])
                if truncate_after is not None and step > truncate_after:
                    continue
                self._rows[step] = {k: v for k, v in record.items() if not _isnan(v)}
            self.flush()
        elif not resume and self.path.exists():
            raise FileExistsError(f"{self.path} exists; pass resume=True to append to it")

    def log(self, step: int, metrics: Mapping[str, Any] | None = None, **kw: Any) -> None:
        """Merge ``metrics`` (and keyword metrics) into the row of ``step``."""
        metrics = {**(metrics or {}), **kw}
        step = int(step)
        row = self._rows.setdefault(step, {"step": step})
        for key, value in metrics.items():
            if key == "step":
                continue
            row[key] = _scalar(value, key)
            if key not in self._columns:
                self._columns.append(key)
        self._pending += 1
        if self._pending >= self.flush_every:
            self.flush()

    def frame(self) -> pd.DataFrame:
        """The table: one row per step (ascending), columns in first-logged order."""
        rows = [self._rows[s] for s in sorted(self._rows)]
        return pd.DataFrame(rows, columns=self._columns)

    def last(self, key: str) -> Any:
        """The most recent logged value of ``key`` (``None`` if never logged)."""
        for step in sorted(self._rows, reverse=True):
            if key in self._rows[step]:
                return self._rows[step][key]
        return None

    def flush(self, timeout: float | None = None) -> None:
        """Write the table atomically (``timeout``: ``Logger``'s signature, unused)."""
        atomic_write_bytes(self.path, self.frame().to_csv(index=False).encode())
        self._pending = 0

    def close(self, timeout: float | None = None) -> None:
        """Flush; the table stays open for more rows."""
        self.flush()

    def __enter__(self) -> "WideCSVLogger":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ------------------------------------------------- torchrl.record.loggers.Logger
    def _create_experiment(self) -> None:
        return None

    def log_scalar(self, name: str, value: float, step: int | None = None) -> None:
        """Merge ``{name: value}`` into the row of ``step`` (default: the number of rows that
        already hold ``name``)."""
        if step is None:
            step = sum(name in row for row in self._rows.values())
        self.log(step, {name: value})

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None, *,
                    keys_sep: str = "/") -> dict[str, Any]:
        """Merge several scalars (a dict or a TensorDict, nested keys joined by ``keys_sep``)
        into the row of ``step`` in one write; returns them as Python values."""
        if isinstance(metrics, TensorDictBase):
            metrics = metrics.flatten_keys(keys_sep).to_dict()
        values = {key: _scalar(value, key) for key, value in metrics.items()}
        if step is None:
            for name, value in values.items():
                self.log_scalar(name, value)
        else:
            self.log(step, values)
        return values

    def log_hparams(self, cfg: Any) -> None:
        """Write ``cfg`` (a dict, a dataclass, or an OmegaConf config) to ``hparams.json`` beside
        the table."""
        if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
            cfg = dataclasses.asdict(cfg)
        elif not isinstance(cfg, Mapping):
            from omegaconf import OmegaConf  # a hydra DictConfig, as TorchRL's loggers accept

            cfg = OmegaConf.to_container(cfg, resolve=True)
        text = json.dumps(cfg, indent=2, sort_keys=True, default=str) + "\n"
        atomic_write_bytes(self.path.with_name("hparams.json"), text.encode())

    def log_video(self, name: str, video: Any, step: int | None = None, **kwargs: Any) -> None:
        raise NotImplementedError(
            f"WideCSVLogger holds scalars only; write video {name!r} with trakdis.utils.write_video, "
            "or log it to a TensorBoard/W&B logger (--logger tensorboard|wandb)")

    def log_histogram(self, name: str, data: Sequence, **kwargs: Any) -> None:
        raise NotImplementedError(
            f"WideCSVLogger holds scalars only; log histogram {name!r} to a TensorBoard/W&B logger "
            "(--logger tensorboard|wandb)")

    def __repr__(self) -> str:
        return f"WideCSVLogger(path={str(self.path)!r}, exp_name={self.exp_name!r})"


def _isnan(value: Any) -> bool:
    return isinstance(value, float) and math.isnan(value)


#: the package each TorchRL logger backend needs, and the trakdis extra that installs it
LOGGER_PACKAGES: dict[str, tuple[str, str]] = {"tensorboard": ("tensorboard", "tensorboard"),
                                               "wandb": ("wandb", "wandb")}


def _has_package(name: str) -> bool:
    return importlib.util.find_spec(name) is not None


def check_logger_backend(kind: str) -> None:
    """Raise ``ModuleNotFoundError`` naming the package and the extra to install if the TorchRL
    logger ``kind`` (``"csv"``: none needed) cannot be used here."""
    if kind == "csv":
        return
    if kind not in LOGGER_PACKAGES:
        raise ValueError(f"unknown logger {kind!r}; choose one of {['csv', *LOGGER_PACKAGES]}")
    package, extra = LOGGER_PACKAGES[kind]
    if not _has_package(package):
        raise ModuleNotFoundError(
            f"--logger {kind} needs the {package!r} package, which is not installed: "
            f"pip install 'trakdis[{extra}]' (or pip install {package})", name=package)


def make_torchrl_logger(kind: str, directory: str | Path, name: str, *,
                        state_dict: Mapping[str, Any] | None = None) -> Logger:
    """TorchRL's ``kind`` logger (``"tensorboard"`` or ``"wandb"``) writing under ``directory``.

    TensorBoard's event files go to ``<directory>/tensorboard/``; W&B keeps its files in
    ``<directory>/wandb/`` and names the run ``name`` (project ``$WANDB_PROJECT``, default
    ``trakdis``; ``WANDB_MODE=offline`` works as usual). ``state_dict`` (a ``Logger.state_dict()``
    saved in a checkpoint) continues the same event directory or W&B run.
    """
    check_logger_backend(kind)
    if kind == "csv":
        raise ValueError("the CSV log is WideCSVLogger; make_torchrl_logger opens 'tensorboard' or 'wandb'")
    directory = str(directory)
    exp_name = "tensorboard" if kind == "tensorboard" else name
    if state_dict is not None:  # the run directory may have moved since: write where it is now
        state_dict = {**state_dict, "log_dir": directory, "exp_name": exp_name}
    kwargs = {"wandb_kwargs": {"project": os.environ.get("WANDB_PROJECT", "trakdis")}} if kind == "wandb" else {}
    return get_logger(kind, directory, exp_name, state_dict=state_dict, **kwargs)
