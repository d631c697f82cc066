"""The stages of a pipeline as Ray tasks, on every core of a machine or on a cluster.

:class:`RayStages` has the interface of :class:`~trakdis.utils.stages.Stages` (``run``, ``submit``, ``wait``,
``queued``, ``report``), but :meth:`RayStages.run` returns at once: the stage becomes a Ray task that
declares the CPUs it uses, and runs as soon as the stages it needs have finished. Those are the
stages whose run directories its arguments name (``--teacher runs/online_dt/x``), and those given
as ``after``: their Ray object refs are the task's arguments, so Ray, not a waiting loop, orders
the graph (teacher -> encoder -> student -> evaluations). Code that reads a stage's output first
calls :meth:`RayStages.wait` on its directory::

    stages = make_stages(run, Path(__file__).parent)       # Stages, or RayStages with --ray / --ray-address
    with stages.queued():                                   # leaving it: every stage has run
        teacher = stages.run("online_dt", "t", "policy.pt", [...])
        encoder = stages.run("train_encoder", "e", "encoder.pt", ["--teacher", str(teacher)])  # after t
        stages.wait(teacher)                                 # before reading runs/online_dt/t/policy.pt

A stage whose output file exists is skipped, and an interrupted one gets ``--resume``, as with
:class:`Stages`. Each task runs its recipe's ``main`` in a Ray worker process (imported there once,
as :class:`Stages` runs it in its own process), its output in ``<pipeline run dir>/<run_name>.log``.
A stage that fails is reported with that log; the stages that do not need it go on, and
:meth:`RayStages.drain` lists the failed ones once the others have run.

``ray`` is an optional dependency (``pip install -e ".[ray]"``), imported only here, when a
:class:`RayStages` is made.
"""
from __future__ import annotations

import contextlib
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Optional, Sequence

from .limits import check_option
from .run import Run
from .stages import Parts, Stages, import_recipe

__all__ = ["RayConfig", "RayStages", "StageFailed", "import_ray", "make_stages", "start_ray"]


def import_ray():
    """``ray``, or an ImportError that says how to install it."""
    try:
        import ray
    except ImportError as err:
        raise ImportError('--ray / --ray-address need Ray: pip install -e ".[ray]" (on every node of a '
                          'cluster)') from err
    return ray


def start_ray(address: str | None = None, num_cpus: int | None = None) -> None:
    """Connect to the Ray cluster at ``address`` (``"auto"``: the one ``ray start`` began on this node), or start
    a local Ray on ``num_cpus`` CPUs (default: every core); nothing if Ray is already initialised."""
    ray = import_ray()
    if ray.is_initialized():
        return
    if address:
        ray.init(address=address, include_dashboard=False)
    else:  # a small object store: the stages pass file paths, not tensors
        ray.init(num_cpus=num_cpus or os.cpu_count(), include_dashboard=False, object_store_memory=256 * 2**20)


@dataclass
class RayConfig:
    """Where a pipeline's stages run (a base of its config dataclass, before :class:`~trakdis.utils.run.RunConfig`)."""

    ray: bool = False
    """run the stages as Ray tasks on a local Ray that uses every core (--ray-cpus), as many at once as their
    CPUs allow (pip install -e ".[ray]"); default: one after another in this process"""
    ray_address: Optional[str] = None
    """run the stages on the Ray cluster at this address (auto: the one `ray start` began on this node); --root
    and the working directory must be on storage every node sees at the same path (NFS or similar)"""
    ray_cpus: Optional[int] = None
    """CPUs of the local Ray started by --ray (default: every core)"""
    eval_chunk: int = 0
    """under Ray: cut each noise-free evaluation into parts of this many episodes (a multiple of its envs), each
    a Ray task, merged into the same episodes.csv and summary.csv (0: whole evaluations)"""

    def __post_init__(self):
        check_option("eval_chunk", self.eval_chunk, ge=0, integer=True)
        if self.ray_cpus is not None:
            check_option("ray_cpus", self.ray_cpus, ge=1, integer=True)
        parent = getattr(super(), "__post_init__", None)
        if parent is not None:
            parent()

    @property
    def use_ray(self) -> bool:
        return bool(self.ray or self.ray_address)


def make_stages(run: Run, recipes: str | Path, **kwargs: Any) -> Stages:
    """The stages of ``run``: :class:`RayStages` when its configuration (a :class:`RayConfig`) asks for Ray, else
    :class:`Stages`; ``kwargs``: their other arguments (``timings_path``)."""
    cfg = run.cfg
    if getattr(cfg, "ray", False) or getattr(cfg, "ray_address", None):
        return RayStages(run, recipes, address=cfg.ray_address, num_cpus=cfg.ray_cpus, **kwargs)
    return Stages(run, recipes, **kwargs)


class StageFailed(RuntimeError):
    """A stage's recipe raised (or exited non-zero); ``key`` names the stage, ``log`` holds its output."""

    def __init__(self, key: str, log: str, message: str = ""):
        super().__init__(f"stage {key} failed ({message}); see {log}")
        self.key, self.log, self.message = key, log, message

    def __reduce__(self):  # raised in a worker, read in the driver
        return type(self), (self.key, self.log, self.message)


_MODULES: dict[str, Any] = {}  # the recipes a worker process has imported


@contextlib.contextmanager
def _output_to(path: str) -> Iterator[None]:
    """This process's stdout and stderr (file descriptors 1 and 2, so also those of the processes it starts) into
    ``path`` (appended), restored afterwards."""
    sys.stdout.flush(), sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as log:
        os.dup2(log.fileno(), 1), os.dup2(log.fileno(), 2)
        try:
            yield
        finally:
            sys.stdout.flush(), sys.stderr.flush()
            os.dup2(saved[0], 1), os.dup2(saved[1], 2)
            os.close(saved[0]), os.close(saved[1])


def run_stage(recipes: str, recipe: str, argv: list[str], log: str, cwd: str, key: str, *needs: Any) -> float:
    """A Ray task: ``recipes/<recipe>.py``'s ``main(argv)`` in this worker process, in the directory ``cwd``, its
    output in ``log``; returns its wall seconds. ``needs``: the results of the stages it reads (Ray starts the
    task once they exist)."""
    os.chdir(cwd)
    start = time.perf_counter()
    with _output_to(log):
        try:
            path = str(Path(recipes) / f"{recipe}.py")
            if path not in _MODULES:
                _MODULES[path] = import_recipe(path, prefix="trakdis_ray_recipe_")
            _MODULES[path].main(list(argv))
        except SystemExit as err:  # a recipe's refusal of its options, or an exit code
            if err.code not in (0, None):
                print(f"{key}: exited with {err.code}", file=sys.stderr)
                raise StageFailed(key, log, f"exit code {err.code}") from None
        except Exception as err:
            import traceback

            traceback.print_exc()
            raise StageFailed(key, log, f"{type(err).__name__}: {err}") from None
    return time.perf_counter() - start


def merge_parts(merge: Any, part_dirs: list[str], directory: str, whole: tuple, *parts: Any) -> float:
    """A Ray task: ``merge(part directories, directory)`` once the parts have run (``parts``: their results), or,
    when it returns False (they cannot stand for the stage), the stage run whole (``whole``: :func:`run_stage`'s
    arguments). Returns its wall seconds."""
    recipes, recipe, argv, log, cwd, key = whole
    os.chdir(cwd)
    start = time.perf_counter()
    with _output_to(log):
        joined = merge([Path(d) for d in part_dirs], Path(directory))
        print(f"{key}: {len(part_dirs)} parts " + ("merged" if joined else "cannot stand for it: run whole"))
    if not joined:
        run_stage(*whole)
    return time.perf_counter() - start


@dataclass
class _Task:
    ref: Any
    key: str
    log: Path
    directory: Path


class RayStages(Stages):
    """The stages of ``run`` as Ray tasks (see the module's text), on the cluster at ``address`` or on a local Ray
    of ``num_cpus`` CPUs (started here unless Ray is initialised); ``recipes`` and ``timings_path`` as for
    :class:`Stages`."""

    def __init__(self, run: Run, recipes: str | Path, *, address: str | None = None, num_cpus: int | None = None,
                 timings_path: str | Path | None = None):
        super().__init__(run, recipes, timings_path=timings_path)
        start_ray(address, num_cpus)
        self.ray = import_ray()
        self.recipes = self.recipes.resolve()  # a worker's working directory is set per task
        self._tasks: dict[Path, _Task] = {}  # run directory -> its task, every stage submitted
        self._done: set[Path] = set()  # those collected (their time recorded, or their failure)
        self.failures: dict[str, str] = {}  # stage -> what went wrong, one line each
        self._firsts: dict[str, Path] = {}  # group -> the first stage of it (first_of)
        resources = self.ray.cluster_resources()
        run.print(f"stages as Ray tasks on {int(resources.get('CPU', 0))} CPUs of {len(self.ray.nodes())} node(s)")

    def _key(self, directory: Path) -> Path:
        return Path(os.path.abspath(directory))

    def _needs(self, args: Sequence[str], after: Sequence[Path]) -> list[Any]:
        """The refs of the submitted stages that ``args`` name (a run directory, an argument of its own) or
        ``after`` lists."""
        named = {self._key(Path(a)) for a in args if isinstance(a, (str, Path)) and str(a) and not str(a).startswith("-")}
        named |= {self._key(Path(a)) for a in after}
        with self._lock:
            return [task.ref for d, task in self._tasks.items() if d in named]

    def _submit(self, recipe: str, run_name: str, argv: list[str], cpus: int, needs: list[Any]) -> tuple[Any, tuple]:
        key, log = f"{recipe}/{run_name}", self.pipeline.dir / f"{run_name}.log"
        whole = (str(self.recipes), recipe, argv, str(log.resolve()), os.getcwd(), key)
        task = self.ray.remote(run_stage).options(num_cpus=cpus, max_retries=0, name=key)
        return task.remote(*whole, *needs), whole

    def run(self, recipe: str, run_name: str, output: str, args: list[str], *, seed: int | None = None,
            background: bool = False, after: Sequence[Path] = (), cpus: int | None = None,
            parts: Parts | None = None) -> Path:
        """Submit the stage as a Ray task of ``cpus`` CPUs (default: the pipeline's ``--threads``) that runs
        after the stages its arguments name and those in ``after``; returns its run directory at once (skipped,
        as with :class:`Stages`, when its ``output`` exists). With ``parts`` (two or more), each part is a task
        and a last one merges them. ``background`` changes nothing: every stage runs beside the others."""
        directory = self.directory(recipe, run_name)
        key = self._key(directory)
        with self._lock:
            if key in self._tasks and key not in self._done:  # submitted already, not collected yet
                return directory
            self._done.discard(key)
            if (directory / output).exists():
                self.pipeline.print(f"{recipe}: {directory / output} exists, skipped")
                return directory
            cpus = max(1, self.pipeline.cfg.threads) if cpus is None else cpus
            needs = self._needs(args, after)
            argv = [*self.common_args(recipe, run_name, seed=seed, progress=False), *map(str, args)]
            if parts is not None and len(parts.args) > 1:
                part_dirs, refs = [], []
                for i, extra in enumerate(parts.args):
                    name = f"{run_name}-part{i}"
                    part_dirs.append(str(self.directory(recipe, name).resolve()))
                    if not (self.directory(recipe, name) / output).exists():
                        part_argv = [*self.common_args(recipe, name, seed=seed, progress=False), *map(str, args),
                                     *map(str, extra)]
                        refs.append(self._submit(recipe, name, part_argv, cpus, needs)[0])
                        part = self.directory(recipe, name)
                        self._tasks[self._key(part)] = _Task(refs[-1], f"{recipe}/{name}",
                                                             self.pipeline.dir / f"{name}.log", part)
                whole = (str(self.recipes), recipe, argv, str((self.pipeline.dir / f"{run_name}.log").resolve()),
                         os.getcwd(), f"{recipe}/{run_name}")
                merge = self.ray.remote(merge_parts).options(num_cpus=cpus, max_retries=0, name=f"{recipe}/{run_name}")
                ref = merge.remote(parts.merge, part_dirs, str(directory.resolve()), whole, *refs, *needs)
            else:
                ref, _ = self._submit(recipe, run_name, argv, cpus, needs)
            self._tasks[key] = _Task(ref, f"{recipe}/{run_name}", self.pipeline.dir / f"{run_name}.log", directory)
        self.pipeline.print(f"{recipe}: {run_name} submitted (log: {self.pipeline.dir / run_name}.log)")
        return directory

    submit = run

    def first_of(self, group: str, recipe: str, run_name: str, output: str, args: list[str], **kwargs) -> Path:
        """:meth:`run` after the first stage submitted in ``group`` (that one: as it is), e.g. the stages of one
        task that would otherwise collect its dataset at once (a second collection of a dataset is refused)."""
        with self._lock:
            first = self._firsts.get(group)
            after = [*kwargs.pop("after", ()), *([] if first is None else [first])]
            directory = self.run(recipe, run_name, output, args, after=after, **kwargs)
            self._firsts.setdefault(group, directory)
            return directory

    def withdraw(self, run_name: str) -> bool:
        """Never: a submitted stage is Ray's to schedule."""
        return False

    def pump(self) -> None:
        """Nothing to start: Ray starts each task once the stages it needs have finished."""

    def _collect(self, task: _Task) -> None:
        """Record a finished task's time, or its failure (in :attr:`failures`)."""
        with self._lock:
            key = self._key(task.directory)
            if key in self._done:
                return
            self._done.add(key)
        try:
            seconds = self.ray.get(task.ref)
        except self.ray.exceptions.RayTaskError as err:
            cause = getattr(err, "cause", None)
            if isinstance(cause, StageFailed) and cause.key != task.key:
                self.failures[task.key] = f"not run: it needs {cause.key}, which failed (see {cause.log})"
            elif isinstance(cause, StageFailed):
                self.failures[task.key] = f"failed ({cause.message}); see {cause.log}"
            else:
                self.failures[task.key] = f"failed ({err}); see {task.log}"
            self.pipeline.print(f"{task.key}: {self.failures[task.key]}")
            return
        self._record(task.key, seconds)
        self.pipeline.print(f"{task.key}: done in {seconds:.0f} s ({task.directory})")

    def wait(self, job: Path) -> Path:
        """Wait for the stage whose run directory is ``job`` (if it was submitted) and return that directory; a
        failed one raises :class:`StageFailed`, naming its log."""
        task = self._tasks.get(self._key(Path(job)))
        if task is None:
            return Path(job)
        self._collect(task)
        if task.key in self.failures:
            raise StageFailed(task.key, str(task.log), self.failures[task.key])
        return Path(job)

    def drain(self, poll_seconds: float = 0.5) -> None:
        """Wait until every submitted stage has run, or failed; then raise a RuntimeError listing the failed ones
        (each with its log), if any."""
        by_ref = {task.ref: task for task in list(self._tasks.values())}
        pending = [ref for ref, task in by_ref.items() if self._key(task.directory) not in self._done]
        while pending:
            ready, pending = self.ray.wait(pending, num_returns=1)
            for ref in ready:
                self._collect(by_ref[ref])
        if self.failures:
            raise RuntimeError(f"{len(self.failures)} stage(s) did not finish; the others did (run the same command "
                               "with --resume once fixed):\n" + "\n".join(f"  {k}: {v}" for k, v in self.failures.items()))

    @contextlib.contextmanager
    def queued(self, poll_seconds: float = 0.5) -> Iterator["RayStages"]:
        """A block whose stages have all run when it is left (:meth:`drain`); an error inside it cancels the
        stages still pending."""
        try:
            yield self
        except BaseException:
            for task in self._tasks.values():
                if self._key(task.directory) not in self._done:
                    self.ray.cancel(task.ref, force=True)
            raise
        self.drain()
