"""Recipes run one after another as the stages of a pipeline run (``recipes/pipeline.py``).

Each stage is an ordinary run of a recipe script, ``<root>/<recipe>/<run_name>``: skipped when its
output file exists, resumed (``--resume``) when a checkpoint or a log shows it was interrupted, so
that the pipeline itself resumes by running again. A stage runs in this process (the recipe
imported from its file, its ``main(argv)`` called) or, with ``background=True``, as a low-priority
subprocess on the core the foreground stages leave idle (:meth:`Stages.wait` for it)::

    stages = Stages(run, Path(__file__).parent)
    teacher = stages.run("online_dt", "cf-teacher", "policy.pt", ["--task", "ClothFold"])
    encoder = stages.run("train_encoder", "cf-encoder", "encoder.pt", ["--teacher", str(teacher)])
    stages.report()                    # wall seconds per stage

Stages that need nothing from the ones after them (evaluations) can be queued instead, to run in the
background beside the foreground stages, at most ``max_background`` at a time::

    with stages.queued():              # leaving the block waits for the queue (after an error: stops it)
        teacher = stages.run("online_dt", "cf-teacher", "policy.pt", [...])
        stages.submit("evaluate", "cf-eval-teacher", "summary.csv", ["--policy", str(teacher)])
        encoder = stages.run("train_encoder", "cf-encoder", "encoder.pt", [...])   # beside the evaluation
        if stages.withdraw("cf-eval-teacher"):   # not started yet: run it here instead
            stages.run("evaluate", "cf-eval-teacher", "summary.csv", [..., "--parallel"])

The common options (``--name``, ``--root``, ``--seed``, ``--threads``, ``--no-progress``,
``--logger``) come from the pipeline run's :class:`~trakdis.utils.run.RunConfig` (``seed=``: another
seed for one stage). With ``timings_path``, the wall seconds per stage are kept in that CSV (rewritten
after each stage, read back by a resumed pipeline).
"""
from __future__ import annotations

import contextlib
import importlib.util
import os
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Callable, Iterator, Sequence

import pandas as pd

from .checkpoint import atomic_write_bytes
from .run import Run

__all__ = ["BackgroundStage", "Parts", "Stages", "import_recipe"]


# A background stage's process runs its recipe through this bootstrap (argv: the pipeline's pid, the
# script, its arguments) instead of a ``preexec_fn``, which is unsafe once the queue's thread starts
# processes: on Linux it asks for SIGTERM when the pipeline's process dies (PR_SET_PDEATHSIG; exits
# if that already happened), so that a killed pipeline leaves no stage running that its ``--resume``
# would start a second time on the same run directory. ``nice -n 10`` in front of it: low priority.
# Otherwise the script runs as ``python script.py`` would run it (its directory first on ``sys.path``).
_BOOTSTRAP = """import os, runpy, signal, sys
parent = int(sys.argv[1])
sys.argv = sys.argv[2:]
sys.path[0] = os.path.dirname(os.path.abspath(sys.argv[0]))  # as `python script.py` has it (not -c's cwd)
if sys.platform.startswith("linux"):
    import ctypes
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # 1: PR_SET_PDEATHSIG
    if os.getppid() != parent:
        sys.exit("the pipeline that started this stage has exited")
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def import_recipe(path: str | Path, prefix: str = "trakdis_recipe_") -> ModuleType:
    """Import the script ``path`` as a module named ``<prefix><stem>`` (recipes are scripts, not a package)."""
    path = Path(path)
    spec = importlib.util.spec_from_file_location(f"{prefix}{path.stem}", path)
    if spec is None or spec.loader is None:
        raise FileNotFoundError(f"no recipe script at {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


@dataclass(frozen=True)
class Parts:
    """A stage that may run as parts side by side: part ``i`` as ``<run_name>-part<i>`` with the stage's arguments
    followed by ``args[i]``, then ``merge(part directories, the stage's directory)`` writes the stage's output from
    theirs and returns True, or returns False when they cannot stand for it (the stage then runs whole). ``merge``
    must be importable by name (a module-level function): a worker on another machine calls it."""

    args: tuple[tuple[str, ...], ...]
    merge: Callable[[list[Path], Path], bool]


@dataclass
class BackgroundStage:
    """A stage running as a subprocess (:meth:`Stages.run` with ``background=True``)."""

    proc: subprocess.Popen
    directory: Path
    key: str
    started: float = field(default_factory=time.perf_counter)


class Stages:
    """The stages of ``run`` (the pipeline's own run, ``self.pipeline``), recipes from the directory ``recipes``; ``timings``
    holds each stage's wall seconds under ``"<recipe>/<run_name>"`` (a background one with
    ``" (background)"``), kept in ``timings_path`` if given."""

    def __init__(self, run: Run, recipes: str | Path, *, timings_path: str | Path | None = None,
                 max_background: int = 1):
        if max_background < 1:
            raise ValueError(f"max_background must be >= 1, got {max_background}")
        self.pipeline, self.recipes = run, Path(recipes)
        self.max_background = int(max_background)
        self._queue: list[tuple[str, str, str, list[str], int | None]] = []  # submitted, not started yet
        self._running: list[BackgroundStage] = []  # started by the queue
        self._lock = threading.RLock()  # the queue and the timings, shared with the queue's thread
        self._failure: BaseException | None = None  # a queued stage's failure, seen by the queue's thread
        self.timings_path = None if timings_path is None else Path(timings_path)
        self.timings: dict[str, float] = {}
        if self.timings_path is not None and self.timings_path.exists():
            self.timings = pd.read_csv(self.timings_path).set_index("stage")["seconds"].to_dict()
        self._modules: dict[str, ModuleType] = {}

    def run(self, recipe: str, run_name: str, output: str, args: list[str], *, seed: int | None = None,
            background: bool = False, after: Sequence[Path] = (), cpus: int | None = None,
            parts: Parts | None = None) -> Path | BackgroundStage:
        """Run ``<recipes>/<recipe>.py`` as ``<root>/<recipe>/<run_name>`` unless its ``output`` file
        exists; returns the run directory. With ``background``, start it as a low-priority subprocess
        instead (its output in ``<pipeline run dir>/<run_name>.log``) and return it for :meth:`wait`.
        ``after`` (stages it needs beyond those its arguments name), ``cpus`` and ``parts`` are for a scheduler
        that runs stages side by side (:class:`~trakdis.utils.ray_stages.RayStages`): here the stages run in
        turn, each whole."""
        directory = self.directory(recipe, run_name)
        if (directory / output).exists():
            self.pipeline.print(f"{recipe}: {directory / output} exists, skipped")
            return directory
        common = self.common_args(recipe, run_name, seed=seed, progress=not background)
        script = self.recipes / f"{recipe}.py"
        if background:
            log_path = self.pipeline.dir / f"{run_name}.log"
            self.pipeline.print(f"{recipe}: {run_name} started in the background (log: {log_path})")
            with open(log_path, "w") as log:
                nice = ["nice", "-n", "10"] if shutil.which("nice") else []
                proc = subprocess.Popen([*nice, sys.executable, "-c", _BOOTSTRAP, str(os.getpid()), str(script),
                                         *common, *args], stdout=log, stderr=subprocess.STDOUT)
            return BackgroundStage(proc, directory, f"{recipe}/{run_name} (background)")
        self.pump()  # a queued stage may start beside this one
        start = time.perf_counter()
        self.recipe(recipe).main([*common, *args])
        self._record(f"{recipe}/{run_name}", time.perf_counter() - start)
        self.pipeline.print(f"{recipe}: done in {self.timings[f'{recipe}/{run_name}']:.0f} s ({directory})")
        return directory

    def directory(self, recipe: str, run_name: str) -> Path:
        """The run directory of the stage ``run_name`` of ``recipe``: ``<root>/<recipe>/<run_name>``."""
        return Path(self.pipeline.cfg.root) / recipe / run_name

    def common_args(self, recipe: str, run_name: str, *, seed: int | None = None, progress: bool = True) -> list[str]:
        """The options every stage gets from the pipeline's run (``--name`` ... ``--logger``; ``--resume`` when the
        stage's directory shows an interrupted run)."""
        cfg = self.pipeline.cfg
        seed = cfg.seed if seed is None else seed
        common = ["--name", run_name, "--root", cfg.root, "--seed", str(seed), "--threads", str(cfg.threads)]
        if not cfg.progress or not progress:
            common.append("--no-progress")
        if cfg.logger != "csv":
            common += ["--logger", cfg.logger]
        directory = self.directory(recipe, run_name)
        if any((directory / f).exists() for f in ("checkpoint.pt", "log.csv", "config.json")):
            common.append("--resume")  # an interrupted stage continues (a recipe without a checkpoint starts over)
        return common

    def first_of(self, group: str, recipe: str, run_name: str, output: str, args: list[str], **kwargs) -> Path:
        """:meth:`run` for a stage of ``group``: stages that would write one file at once if they ran side by side
        (a dataset that the first of them collects). A scheduler that runs stages side by side runs every later
        stage of the group after the first one; here the stages run in turn anyway."""
        return self.run(recipe, run_name, output, args, **kwargs)

    def recipe(self, recipe: str) -> ModuleType:
        """The recipe script ``<recipes>/<recipe>.py`` imported as a module (once): its ``main``, its configuration."""
        if recipe not in self._modules:
            self._modules[recipe] = import_recipe(self.recipes / f"{recipe}.py")
        return self._modules[recipe]

    def _record(self, key: str, seconds: float) -> None:
        with self._lock:
            self.timings[key] = seconds
            if self.timings_path is not None:
                frame = pd.DataFrame({"stage": list(self.timings), "seconds": list(self.timings.values())})
                atomic_write_bytes(self.timings_path, frame.to_csv(index=False).encode())

    def wait(self, job: Path | BackgroundStage) -> Path:
        """Wait for a stage that :meth:`run` started in the background (a directory: it was skipped)
        and return its run directory; a failed one raises, naming its log."""
        if not isinstance(job, BackgroundStage):
            return job
        name = job.directory.name
        if job.proc.wait() != 0:
            raise RuntimeError(f"background stage {name} failed (exit code {job.proc.returncode}); "
                               f"see {self.pipeline.dir / name}.log")
        self._record(job.key, time.perf_counter() - job.started)
        self.pipeline.print(f"{name}: done in the background ({job.directory})")
        return job.directory

    def submit(self, recipe: str, run_name: str, output: str, args: list[str], *, seed: int | None = None,
               **scheduling) -> Path:
        """Queue a stage (the arguments of :meth:`run`) to run in the background as soon as fewer than
        ``max_background`` queued stages run (inside :meth:`queued`, whose thread starts it while the
        foreground stages run). Returns its run directory, which holds ``output`` once :meth:`drain`
        returned. ``scheduling``: :meth:`run`'s ``after``, ``cpus`` and ``parts`` (unused here)."""
        with self._lock:
            self._queue.append((recipe, run_name, output, list(args), seed))
        self.pump()
        return Path(self.pipeline.cfg.root) / recipe / run_name

    def withdraw(self, run_name: str) -> bool:
        """Take the submitted stage ``run_name`` out of the queue if it has not started yet (the caller runs it
        itself, e.g. in the foreground on more cores); False once it started, or if it was never submitted."""
        with self._lock:
            for i, queued in enumerate(self._queue):
                if queued[1] == run_name:
                    del self._queue[i]
                    return True
        return False

    def pump(self) -> None:
        """Collect the queued stages that finished (a failed one raises, naming its log, here or, when
        the queue's thread saw it, at the next call) and start waiting ones while fewer than
        ``max_background`` run."""
        with self._lock:
            if self._failure is not None:
                failure, self._failure = self._failure, None
                raise failure
            for job in [j for j in self._running if j.proc.poll() is not None]:
                self._running.remove(job)
                self.wait(job)
            while self._queue and len(self._running) < self.max_background:
                recipe, run_name, output, args, seed = self._queue.pop(0)
                job = self.run(recipe, run_name, output, args, seed=seed, background=True)
                if isinstance(job, BackgroundStage):  # else: its output existed, skipped
                    self._running.append(job)

    def _poll(self, stop: threading.Event, seconds: float) -> None:  # the queue's thread
        # PR_SET_PDEATHSIG follows the thread that started a process: this one ends only once the queue
        # is drained, or on a failure, which stops the queue's other stages anyway.
        # The failure is recorded under the same hold of the lock as the pump() that saw it: released in
        # between, the main thread's pump() could find the failed stage gone and start the next one.
        while not stop.wait(seconds):
            with self._lock:
                try:
                    self.pump()
                except BaseException as err:  # noqa: BLE001 - handed to the main thread's next pump()
                    self._failure = err
                    return

    def drain(self, poll_seconds: float = 0.5) -> None:
        """Wait until every submitted stage has run."""
        while True:
            with self._lock:  # the queue's thread moves a stage from the queue to the running ones under it
                self.pump()
                if not (self._queue or self._running):
                    return
            time.sleep(poll_seconds)

    @contextlib.contextmanager
    def queued(self, poll_seconds: float = 0.5) -> Iterator["Stages"]:
        """A block whose submitted stages run beside its foreground ones, each started (by a thread
        polling every ``poll_seconds``) as soon as a slot is free: leaving the block waits for them
        (:meth:`drain`); an error terminates the running ones and drops the waiting ones."""
        stop = threading.Event()
        poller = threading.Thread(target=self._poll, args=(stop, poll_seconds), name="stages-queue", daemon=True)
        poller.start()
        try:
            yield self
            self.drain(poll_seconds)
        finally:
            stop.set()
            poller.join()
            with self._lock:
                self._queue.clear()
                for job in self._running:
                    if job.proc.poll() is None:
                        job.proc.terminate()
                for job in self._running:
                    job.proc.wait()
                self._running.clear()
                self._failure = None

    def report(self) -> None:
        """Print the pipeline's wall time and each stage's (nothing if every stage was skipped)."""
        if self.timings:
            stages = ", ".join(f"{k} {v:.0f}" for k, v in self.timings.items())
            self.pipeline.print(f"wall time {time.time() - self.pipeline.t0:.0f} s; stages (s): {stages}")
