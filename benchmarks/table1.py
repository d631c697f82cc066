"""The paper's Table I and ablation curves, regenerated in one command.

    python benchmarks/table1.py --name t1                          # 3 tasks x 3 seeds, 100 trials each
    python benchmarks/table1.py --name t1 --resume                 # continue after a kill
    python benchmarks/table1.py --name q --quick                   # small sizes (same as --preset quick)
    python benchmarks/table1.py --name t1 --report                 # the table so far (runs nothing; beside the run)
    python benchmarks/table1.py --name t1 --tasks ClothFold --seeds 5
    python benchmarks/table1.py --name t1 --ray                    # stages as Ray tasks on every core
    python benchmarks/table1.py --name t1 --ray-address auto --eval-chunk 20   # on a Ray cluster (docs/scaling.md)

For every task and seed (``--seed``, ``--seed`` + 1, ... ``--seeds`` of them) it runs, each as an
ordinary run of its recipe under ``<root>/<recipe>/<name>-<task>-s<seed>-<stage>``:

* the teacher (``online_dt.py``, ``--teacher-args``), the encoder (``train_encoder.py``,
  ``--encoder-args``) and the student (``distill.py``, ``--student-args``): the full method, TraKDis;
* the ablations: No-Aug (the student on an encoder trained with ``--no-aug``: no flip, so no test-time
  flip either; the default encoder does not shift), No-Pretrain (``distill.py --no-weight-copy``), the paper's
  No-Distill (``distill.py --no-weight-copy --no-distill``: a DT on fresh weights fed the encoder's estimates,
  trained on the expert's actions with the teacher's offline updates and optimiser:
  ``trakdis.method.no_distill_stage_args``) and one more row, No-Distill (weight copy) (``distill.py --no-distill``:
  the teacher's weights fine-tuned on the expert's actions, method ``no_distill_copy``);
* the baselines: BC-image (``bc_image.py``, ``--bc-args``) and DT-image (``dt_image.py``,
  ``--dt-image-args``);
* ``evaluate.py`` for each of them and for the scripted expert: ``--trials`` eval-split episodes,
  the same configurations for every method of a seed;
* the robustness study (the paper's Fig. 7; with TraKDis, unless ``--noise-levels`` is empty): a
  second student distilled with ``--estimate-noise`` of Gaussian noise on its estimated state
  (``distill.py --estimate-noise``), and both students evaluated at each of ``--noise-levels``
  (``evaluate.py --noise-levels``, ``--noise-trials`` episodes per level, the same configurations;
  TraKDis at noise 0 is its own evaluation above when the two trial counts agree, not played again).

A stage whose output file exists is skipped and an interrupted one resumed, so ``--resume`` (or
the same command again) continues where a kill stopped it. ``--methods`` picks a subset. The
evaluations run as low-priority background processes, one at a time, as soon as their policy exists,
beside the training stages that follow (``--overlap``; ``--no-overlap``: in turn; the same numbers). With ``--ray``
or ``--ray-address`` every stage is a Ray task instead, run once the stages it reads have, the 3 tasks x 3 seeds side
by side (``trakdis.utils.ray_stages``; ``--eval-chunk``: evaluations in parts): the same numbers.
The full run takes hours; ``--report`` writes the files below into ``report/`` beside them, from the
evaluations finished so far, from another shell while it runs, and starts nothing.

Writes ``<root>/table1/<name>/``: ``table1.md`` (the paper's layout, ours beside the paper's
numbers, then per method mean +- std, 25th / 50th / 75th percentiles over all episodes of all
seeds and the spread of the per-seed means), ``table1.csv``, ``curves_<task>.png`` (eval
normalized performance over the distillation updates of the full method and the ablations: mean
over seeds with a +-1 std band), ``timings.csv`` (wall seconds per stage) and, with the robustness
study, ``robustness.csv`` (per task, student and noise level: the score and its share of the
noise-free score; also a section of ``table1.md``) and ``robustness_<task>.png``.
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(ROOT))

from trakdis.envs.specs import TASKS, TaskName  # noqa: E402
from trakdis.utils.checkpoint import atomic_write_bytes  # noqa: E402
from trakdis.evaluation import (evaluation_parts, markdown_table, paired_difference, read_final_scores,  # noqa: E402
                                standard_error)
from trakdis.method import (ENCODER_ARGS, TEACHER_ARGS, baseline_stage_args, check_teacher_selection,  # noqa: E402
                            encoder_stage_args, no_distill_stage_args, student_stage_args, teacher_candidates,
                            teacher_stage, teacher_stage_args)
from trakdis.utils.config import load_config, parse_config  # noqa: E402
from trakdis.utils.plot import plot_mean_std  # noqa: E402
from trakdis.utils.run import Run, RunConfig  # noqa: E402
from trakdis.utils.ray_stages import RayConfig, RayStages, StageFailed, make_stages  # noqa: E402
from trakdis.utils.stages import Stages  # noqa: E402

RECIPES = ROOT / "recipes"

Method = Literal["expert", "teacher", "trakdis", "bc_image", "dt_image", "no_aug", "no_pretrain", "no_distill",
                 "no_distill_copy"]
METHODS: tuple[str, ...] = ("expert", "teacher", "trakdis", "bc_image", "dt_image", "no_aug", "no_pretrain",
                            "no_distill", "no_distill_copy")
LABELS = {"expert": "expert (state)", "teacher": "teacher (state)", "trakdis": "TraKDis (image)",
          "bc_image": "BC-image", "dt_image": "DT-image", "no_aug": "No-Aug", "no_pretrain": "No-Pretrain",
          "no_distill": "No-Distill", "no_distill_copy": "No-Distill (weight copy)", "trakdis_noise": "TraKDis+noise"}
# the paper's Fig. 6 (same x axis: distill updates) and the extra No-Distill arm
CURVE_METHODS = ("trakdis", "no_aug", "no_pretrain", "no_distill", "no_distill_copy")
STUDENT_OF_TEACHER = CURVE_METHODS  # the same arms: each built on the teacher (and its encoder)
# A method's stages (its distill run, its evaluation) are named after its key, but the No-Distill arms': the weight
# copy's keeps the names it had when it was the key no_distill, the paper's gets new ones, so that --resume or
# --report of a run saved before the paper's arm existed finds its weight-copy stages under no_distill_copy and never
# reads them as the paper's arm (which such a run trains afresh under its own names).
STAGE_NAMES = {"no_distill": "no_distill_paper", "no_distill_copy": "no_distill"}

# The paper's Table I (W. Chen and N. Rojas, RA-L 2024; ../shared/docs/method.md): mean and, where
# given, std over 100 trials. A reference beside our numbers, not a result of this code.
PAPER_TABLE1 = {
    "ClothFold": {"expert": (0.706, 0.159), "teacher": (0.740, 0.111), "trakdis": (0.583, 0.190),
                  "bc_image": (0.159, None), "dt_image": (0.305, None)},
    "ClothFoldDiagonalPinned": {"expert": (0.907, 0.009), "teacher": (0.902, 0.004), "trakdis": (0.916, 0.002),
                                "bc_image": (0.613, None), "dt_image": (0.469, None)},
    "ClothFoldDiagonalUnpinned": {"expert": (0.926, 0.012), "teacher": (0.921, 0.004), "trakdis": (0.944, 0.004),
                                  "bc_image": (0.663, None), "dt_image": (0.512, None)},
}


@dataclass
class Table1Config(RayConfig, RunConfig):
    """Table I (expert, teacher, TraKDis, BC-image, DT-image) and the ablations, over tasks and seeds."""

    tasks: tuple[TaskName, ...] = TASKS
    """tasks (default: all three)"""
    seeds: int = 3
    """seeds per method: --seed, --seed + 1, ..."""
    methods: tuple[Method, ...] = METHODS
    """methods to run and tabulate"""
    trials: int = 100
    """evaluation episodes per policy and seed (eval split)"""
    teacher_args: str = TEACHER_ARGS
    """options of recipes/online_dt.py (the method's teacher, as recipes/pipeline.py runs it: trakdis.method;
    the stage collects the images for the encoder and evaluates nothing itself, unless these say otherwise)"""
    teacher_candidates: int | None = None
    """teacher stages per seed (default: the task's TaskDefaults.teacher_candidates: 3 on the diagonal folds, 1
    on ClothFold) (candidate i: seed + 1000 i); the one that folds best on --teacher-select-episodes
    train-split episodes is kept (--teacher-select-margin; trakdis.method.teacher_stage);
    the stages after it are named after the kept candidate (<name>-<task>-s<seed>-c<i>-...)"""
    teacher_select_episodes: int = 30
    """train-split episodes each teacher candidate plays (with --teacher-candidates > 1)"""
    teacher_select_margin: float = 0.0
    """paired standard errors by which a teacher candidate must beat candidate 0 to replace it (0: the best mean)"""
    encoder_args: str = ENCODER_ARGS
    """options of recipes/train_encoder.py (the method's encoder, trained also on the teacher's weight-copied
    student's images and chosen by its episodes: trakdis.method; No-Aug adds --no-aug)"""
    student_args: str = "--eval-every 2 --eval-episodes 20 --no-eval-teacher"
    """options of recipes/distill.py beside the method's (every student arm, the curves' evaluations; the
    ablations add their flags, the paper's No-Distill its budget: trakdis.method.no_distill_stage_args)"""
    bc_args: str = ""
    """options of recipes/bc_image.py"""
    dt_image_args: str = ""
    """options of recipes/dt_image.py"""
    noise_levels: tuple[float, ...] = (0.0, 1e-5, 1e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1)
    """robustness study: std of the Gaussian noise on the estimated state at evaluation, in metres
    (1e-3: 1 mm), the paper's 0 .. 1e-3 and larger ones until the score halves; none: no study"""
    estimate_noise: float = 1e-3
    """std of the noise on the estimated state the robust student is distilled with (distill.py --estimate-noise;
    metres; the paper's 1e-3)"""
    SAVED_AS: ClassVar[dict] = {"train_noise": "estimate_noise"}  # the option's earlier name (--train-noise)

    @staticmethod
    def upgrade_saved(data: dict) -> dict:
        """A run saved before the paper's No-Distill existed (it has ``train_noise``) named the weight-copy arm
        ``no_distill``: on --resume and --report it is that run's ``no_distill_copy``."""
        if "train_noise" in data and "methods" in data:
            data = {**data, "methods": [("no_distill_copy" if m == "no_distill" else m) for m in data["methods"]]}
        return data
    # options saved by earlier runs name flags renamed since: read as the new ones on --resume
    SAVED_FLAGS: ClassVar[dict] = {"teacher_args": {"--state-noise": "--train-state-noise"},
                                   "student_args": {"--state-noise": "--estimate-noise"}}
    noise_trials: int = 0
    """evaluation episodes per noise level and student (0: --trials, and TraKDis's noise-free level is then
    its --trials evaluation)"""
    parallel: bool = True
    """evaluations (the table's, the robustness study's and the students' curves) on 2 worker processes
    (--no-parallel: in turn; the same numbers)"""
    overlap: bool = True
    """the table's and the robustness study's evaluations as low-priority background processes, one at a
    time, beside the training stages that follow them (--no-overlap: each in turn when its policy exists;
    the same numbers)"""
    report: bool = False
    """start nothing: tabulate the evaluations of the run --name that have finished so far (it may still be
    running), as it was configured (--tasks / --methods may narrow it), into <its folder>/report/ (the same files);
    nothing of the run itself is written"""

    def __post_init__(self):
        super().__post_init__()  # --seed, --threads, --device
        check_teacher_selection(self.teacher_candidates, self.teacher_select_episodes, self.teacher_select_margin)
        if self.seeds < 1 or self.trials < 1 or self.noise_trials < 0:
            raise ValueError(f"--seeds {self.seeds} / --trials {self.trials}: both must be >= 1; "
                             f"--noise-trials {self.noise_trials}: >= 0")
        bad = [s for s in (*self.noise_levels, self.estimate_noise) if not (np.isfinite(s) and s >= 0)]
        if bad:
            raise ValueError(f"--noise-levels / --estimate-noise: every std must be finite and >= 0, got {bad[0]!r}")
        if self.noise_levels and 0.0 not in self.noise_levels:
            raise ValueError(f"--noise-levels {list(self.noise_levels)}: include 0 (the noise-free score "
                             "that the others are compared with)")
        if not self.tasks or not self.methods:
            raise ValueError("--tasks and --methods need at least one value each")


# --quick: one seed, 20 trials, short encoder/student/baseline training (the encoder: one member, 5 epochs and one
# round of 10 weight-copy episodes, no noisy expert's dataset), no robustness study. The teacher keeps its 1500
# offline updates: with 500 it never grasped. Every student arm keeps its last round and its curve has two points
# (the copy, the last round): a 10-episode snapshot selection would decide the arms' order rather than their
# training, and would cost a third of the run. The method's 10 x 50 updates would cost 6 more minutes and do not
# order ClothFold's arms at 20 trials either (docs/table1.md).
PRESETS = {"quick": {
    "seeds": 1,
    "trials": 20,
    "encoder_args": "--epochs 5 --student-rounds 1 --student-episodes 10 --student-epochs 2",
    "student_args": "--rounds 4 --updates-per-round 25 --eval-every 4 --eval-episodes 10 --select-episodes 0 "
                    "--no-eval-teacher",
    "bc_args": "--epochs 5",
    "dt_image_args": "--updates 300",
    "noise_levels": (),  # no robustness study (add it with --noise-levels 0 1e-3 1e-2 ...)
    "teacher_candidates": 1,  # the diagonal folds' three would take it past 30 minutes
}}

def run_task_seed(stages: Stages, cfg: Table1Config, name: str, task: str,
                  seed: int) -> tuple[dict[str, Path], dict[str, tuple[Path, ...]], dict[str, Path]]:
    """All stages of one task and seed; returns ``{method: evaluation run directory}``, for the
    robustness study ``{student: the evaluation run directories that cover the noise levels}``, and
    ``{student arm: its distill run directory}`` (the curves). With ``--overlap`` the
    evaluations are queued (``stages.submit``) as soon as their policy exists, and have run once the
    caller's ``stages.queued()`` block is left; else each runs in turn when its policy exists."""
    base = chain = f"{name}-{task}-s{seed}"  # chain: the stages after the teacher, named after the kept candidate
    stage = functools.partial(stages.run, seed=seed)  # every stage of this task and seed
    evaluation = functools.partial(stages.submit if cfg.overlap else stages.run, "evaluate", seed=seed)
    # side by side (Ray), the stages that would collect one of the task's datasets at once wait for its first
    data, extra = (functools.partial(stages.first_of, f"{task}-{kind}", seed=seed) for kind in ("data", "extra"))
    parallel = ["--parallel"] if cfg.parallel else ["--no-parallel"]
    methods = set(cfg.methods)
    needs_teacher = methods & {"teacher", *STUDENT_OF_TEACHER}
    policies: dict[str, Path] = {}
    evals: dict[str, Path] = {}
    teacher = encoder = None

    def evaluate(method: str, policy_args: list[str]) -> None:  # --trials episodes of one method
        prefix = chain if method in STUDENT_OF_TEACHER or method == "teacher" else base
        evals[method] = evaluation(f"{prefix}-eval-{STAGE_NAMES.get(method, method)}", "summary.csv",
                                   [*policy_args, "--trials", str(cfg.trials), "--videos", "0", *parallel],
                                   parts=evaluation_parts(cfg.trials, cfg.eval_chunk))

    def made(method: str, directory: Path) -> Path:  # a method's policy exists: evaluate it (and the expert)
        policies[method] = directory
        # (the policy file is missing only under --report, whose stages run nothing: the expert is then named below)
        if "expert" in methods and "expert" not in evals and (stages.wait(directory) / "policy.pt").exists():
            from trakdis.policies import load_policy

            # the expert plays episodes of the other policies' length
            evaluate("expert", ["--policy", "expert", "--task", task, "--horizon", str(load_policy(directory).horizon)])
        if method in methods:
            evaluate(method, ["--policy", str(directory)])
        return directory

    if needs_teacher:
        # with the images the encoder stage reads (one collection, not two); evaluated by evaluate.py
        teacher, kept = teacher_stage(stages, f"{base}-teacher", teacher_stage_args(task, cfg.teacher_args), seed=seed,
                                      candidates=teacher_candidates(task, cfg.teacher_candidates),
                                      select_episodes=cfg.teacher_select_episodes,
                                      margin=cfg.teacher_select_margin, parallel=cfg.parallel, group=f"{task}-data")
        chain = f"{base}-c{kept}" if kept else base
        made("teacher", teacher)

    def encoder_stage(run_name: str, *flags: str) -> Path:  # the method's encoder (+ an ablation's flags)
        return extra("train_encoder", run_name, "encoder.pt",
                     [*encoder_stage_args(task, teacher, cfg.encoder_args, parallel=cfg.parallel), *flags])

    def student_stage(run_name: str, encoder: Path, *flags: str) -> Path:  # the method's student (+ flags)
        return stage("distill", run_name, "policy.pt",
                     [*student_stage_args(task, teacher, encoder, cfg.student_args, parallel=cfg.parallel), *flags])

    if methods & {"trakdis", "no_pretrain", "no_distill", "no_distill_copy"}:
        encoder = encoder_stage(f"{chain}-encoder")
    arms = {"trakdis": [], "no_pretrain": ["--no-weight-copy"],
            "no_distill": lambda: no_distill_args(cfg, task, teacher, encoder), "no_distill_copy": ["--no-distill"]}
    for method, flags in arms.items():
        if method in methods:
            made(method, student_stage(f"{chain}-{STAGE_NAMES.get(method, method)}", encoder,
                                       *(flags() if callable(flags) else flags)))
    if "no_aug" in methods:
        made("no_aug", student_stage(f"{chain}-no_aug", encoder_stage(f"{chain}-encoder-noaug", "--no-aug")))
    # the baselines learn from the method's demonstrations and evaluate nothing themselves: evaluate.py does
    # (their --*-args may say otherwise)
    if "bc_image" in methods:
        made("bc_image", data("bc_image", f"{base}-bc_image", "policy.pt", baseline_stage_args(task, cfg.bc_args)))
    if "dt_image" in methods:
        made("dt_image", data("dt_image", f"{base}-dt_image", "policy.pt",
                              baseline_stage_args(task, cfg.dt_image_args)))
    if "expert" in methods and "expert" not in evals:  # the expert alone
        evaluate("expert", ["--policy", "expert", "--task", task, "--horizon", "100"])
    robust = {}
    if cfg.noise_levels and "trakdis" in methods:
        students = {"trakdis": policies["trakdis"],
                    "trakdis_noise": student_stage(f"{chain}-trakdis_noise", encoder, "--estimate-noise",
                                                   str(cfg.estimate_noise))}
        trials = cfg.noise_trials or cfg.trials
        for method, policy in students.items():
            # TraKDis's own evaluation is its noise-free level (the same seed, trials and workers: the same
            # configurations, equal to the last digit), so its ladder plays the other levels only
            reuse = method == "trakdis" and trials == cfg.trials
            levels = [str(x) for x in cfg.noise_levels if not (reuse and x == 0)]
            robust[method] = ((evals["trakdis"],) if reuse else ()) + (
                (evaluation(f"{chain}-noise-{method}", "summary.csv",
                            ["--policy", str(policy), "--trials", str(trials), "--videos", "0", *parallel,
                             "--noise-levels", *levels], parts=evaluation_parts(trials, 0, noise_levels=levels)),)
                if levels else ())
    students = {m: policies[m] for m in CURVE_METHODS if m in policies}
    return {m: evals[m] for m in METHODS if m in evals}, robust, students


@functools.lru_cache(maxsize=None)
def recipe_module(recipe: str):
    """``recipes/<recipe>.py`` imported once, to parse a stage's arguments (its configuration and presets)."""
    from trakdis.utils.stages import import_recipe

    return import_recipe(RECIPES / f"{recipe}.py", prefix="trakdis_table1_")


def no_distill_args(cfg: Table1Config, task: str, teacher: Path, encoder: Path) -> list[str]:
    """The paper's No-Distill's flags after the student stage's (:func:`trakdis.method.no_distill_stage_args`): the
    teacher stage's and the student stage's arguments parsed as their recipes parse them."""
    online_dt, distill = recipe_module("online_dt"), recipe_module("distill")
    teacher_cfg = parse_config(online_dt.OnlineDTConfig, teacher_stage_args(task, cfg.teacher_args),
                               presets=online_dt.PRESETS)
    student_cfg = parse_config(distill.DistillConfig, student_stage_args(task, teacher, encoder, cfg.student_args),
                               presets=distill.PRESETS)
    return no_distill_stage_args(teacher_cfg, student_cfg)


class FinishedStages:
    """``--report``'s stages: each call returns the run directory that :func:`run_task_seed` names (its names, in
    one place) and starts nothing; :func:`finished` then keeps the evaluations that have written their summary.
    ``run`` is the report's own (its ``report/`` folder: a teacher candidates' choice is recorded there, not in the
    benchmark run's folder)."""

    def __init__(self, run: Run):
        self.pipeline = run

    def run(self, recipe: str, run_name: str, output: str, args: list[str], *, seed: int | None = None,
            **scheduling) -> Path:
        return Path(self.pipeline.cfg.root) / recipe / run_name

    submit = run

    def first_of(self, group: str, *args, **kwargs) -> Path:
        return self.run(*args, **kwargs)

    def wait(self, directory: Path) -> Path:
        return directory

    @contextlib.contextmanager
    def queued(self) -> Iterator["FinishedStages"]:
        yield self


def finished(evals: dict, robust: dict, students: dict) -> tuple[dict, dict, dict, int, int]:
    """The evaluations that have finished (per seed, ``None`` where not yet, so that seeds stay paired), the
    robustness ladders all of whose evaluations have, the students whose training has (their curves); the count of
    evaluations before and after."""
    done = lambda d: (d / "summary.csv").exists()  # noqa: E731  written last by recipes/evaluate.py
    total = sum(len(v) for v in (*evals.values(), *robust.values()))
    evals = {k: kept for k, v in evals.items() if any(kept := [d if done(d) else None for d in v])}
    robust = {k: kept for k, v in robust.items() if (kept := [ds for ds in v if ds and all(map(done, ds))])}
    students = {k: kept for k, v in students.items() if (kept := [d for d in v if (d / "policy.pt").exists()])}
    return evals, robust, students, total, sum(d is not None for v in evals.values() for d in v) + sum(
        len(v) for v in robust.values())


REPORT_FLAGS = ("tasks", "methods")
"""--report reads the run as it was configured; these may narrow what it tabulates (any other setting would name or
label its stages otherwise), beside the settings of this invocation alone (``REPORT_OWN``)"""
REPORT_OWN = ("name", "root", "resume", "report", "progress", "threads", "logger", "device", "stop_after", "ray",
              "ray_address", "ray_cpus", "eval_chunk")


def open_report(cfg: Table1Config, argv: list[str]) -> Run:
    """The run ``--name`` of ``cfg`` (``argv`` parsed on the defaults) as saved (its ``config.json``; ``--tasks`` /
    ``--methods`` on top), writing into its ``report/`` folder only: the run's own files (its final table among them)
    are left as they are."""
    directory = Path(cfg.root) / "table1" / str(cfg.name)
    if cfg.name is None or not (directory / "config.json").is_file():
        raise FileNotFoundError(f"--report: {directory / 'config.json'} does not exist: name a run of this "
                                "benchmark with --name (and --root)")
    own = load_config(Table1Config, directory / "config.json")
    cfg = parse_config(Table1Config, argv, presets=PRESETS, description=__doc__, default=own)
    changed = [f.name for f in dataclasses.fields(Table1Config) if f.name not in (*REPORT_FLAGS, *REPORT_OWN)
               and getattr(cfg, f.name) != getattr(own, f.name)]
    if changed:
        raise ValueError(f"--report tabulates run {directory} as it was configured: only --tasks and --methods may "
                         f"narrow it, not --{changed[0].replace('_', '-')}")
    (directory / "report").mkdir(exist_ok=True)
    return Run("table1", cfg, directory / "report")


def summarize_method(finals_per_seed: list[np.ndarray]) -> dict:
    """Pooled episodes of all seeds (mean, std, percentiles) and the spread of the per-seed means."""
    pooled = np.concatenate(finals_per_seed)
    seed_means = np.array([f.mean() for f in finals_per_seed])
    return {"seeds": len(finals_per_seed), "n": int(pooled.size), "mean": float(pooled.mean()), "std": float(pooled.std()),
            "p25": float(np.percentile(pooled, 25)), "p50": float(np.percentile(pooled, 50)),
            "p75": float(np.percentile(pooled, 75)), "seed_mean_std": float(seed_means.std()),
            "seed_mean_min": float(seed_means.min()), "seed_mean_max": float(seed_means.max())}


def _paper(task: str, method: str) -> str:
    mean, std = PAPER_TABLE1.get(task, {}).get(method, (None, None))
    if mean is None:
        return "-"
    return f"{mean:.3f}" if std is None else f"{mean:.3f} +- {std:.3f}"


def versus_trakdis(ours: list[np.ndarray | None], theirs: list[np.ndarray | None]) -> dict:
    """TraKDis minus another method, paired per episode within each seed (the same configurations): the mean over
    seeds of the per-seed differences, its standard error over seeds (over the episodes with one seed), and on how
    many seeds the difference is positive. Entries are per-seed scores (``None``: not evaluated yet)."""
    diffs = [paired_difference(b, a) for a, b in zip(ours, theirs) if a is not None and b is not None]
    if not diffs:
        return {"minus": np.nan, "minus_se": np.nan, "seeds_above": np.nan, "paired_seeds": 0}
    means = np.array([d for d, _ in diffs])
    se = standard_error(means) if len(means) > 1 else diffs[0][1]
    return {"minus": float(means.mean()), "minus_se": se, "seeds_above": int((means > 0).sum()),
            "paired_seeds": len(means)}


def write_tables(run: Run, cfg: Table1Config, evals: dict[tuple[str, str], list[Path | None]],
                 note: str = "") -> pd.DataFrame:
    """``evals``: per task and method its evaluations, one per seed in seed order (``None``: not finished)."""
    scores = {key: [None if d is None else read_final_scores(d) for d in dirs] for key, dirs in evals.items()}
    rows = []
    for (task, method), per_seed in scores.items():
        versus = {} if method == "trakdis" or (task, "trakdis") not in scores else {
            f"trakdis_{k}": v for k, v in versus_trakdis(scores[task, "trakdis"], per_seed).items()}
        rows.append({"task": task, "method": method, **summarize_method([f for f in per_seed if f is not None]),
                     "paper": _paper(task, method), **versus})
    frame = pd.DataFrame(rows)
    atomic_write_bytes(run.dir / "table1.csv", frame.to_csv(index=False).encode())
    methods = [m for m in METHODS if m in cfg.methods]
    wide = []
    for task in cfg.tasks:
        ours = {LABELS[m]: "" for m in methods}
        for r in rows:
            if r["task"] == task:
                ours[LABELS[r["method"]]] = f"{r['mean']:.3f} +- {r['std']:.3f}"
        wide.append({"task": f"{task} (ours)", **ours})
        wide.append({"task": f"{task} (paper)", **{LABELS[m]: _paper(task, m) for m in methods}})
    versus = [f"{r['trakdis_minus']:+.3f} +- {r['trakdis_minus_se']:.3f} ({r['trakdis_seeds_above']:.0f}/"
              f"{r['trakdis_paired_seeds']:.0f})" if r.get("trakdis_paired_seeds", 0) > 0 else "" for r in rows]
    detail = frame.assign(method=frame["method"].map(LABELS), **{"TraKDis - this": versus})[
        ["task", "method", "seeds", "n", "mean", "std", "p25", "p50", "p75", "seed_mean_std", "seed_mean_min",
         "seed_mean_max", "paper", "TraKDis - this"]]
    text = [f"# Table I, regenerated ({cfg.seeds} seeds x {cfg.trials} eval-split trials per method and task)", "",
            "Normalized performance at the episode's end; mean +- std over all episodes of all seeds. "
            "The paper's numbers (100 trials, one run) are beside ours; '-': the paper gives none.", "",
            *([note, ""] if note else []),
            *(["No-Distill: the paper's ablation (a DT on fresh weights trained on the expert's actions, the "
               "teacher's offline budget); No-Distill (weight copy), not in the paper: the teacher's weights "
               "fine-tuned on the expert's actions.", ""] if {"no_distill", "no_distill_copy"} & set(methods) else []),
            markdown_table(pd.DataFrame(wide)), "",
            "Per method: percentiles over all episodes; `seed_mean_*`: the spread of the per-seed means; "
            "`TraKDis - this`: paired per episode within each seed, the mean over seeds +- its standard error over "
            "seeds (over episodes with one seed), and on how many seeds TraKDis is above.", "",
            markdown_table(detail), ""]
    atomic_write_bytes(run.dir / "table1.md", "\n".join(text).encode())
    return frame


def write_curves(run: Run, cfg: Table1Config, students: dict[tuple[str, str], list[Path]]) -> list[Path]:
    paths = []
    for task in cfg.tasks:
        curves = {}
        for method in (m for m in CURVE_METHODS if m in cfg.methods):
            logs = [d / "log.csv" for d in students.get((task, method), [])]
            series = []
            for log in logs:
                if log.exists():
                    frame = pd.read_csv(log)
                    if "eval/normalized_performance" in frame.columns:
                        series.append(frame.dropna(subset=["eval/normalized_performance"])
                                      .groupby("step")["eval/normalized_performance"].last())
            if series:
                joined = pd.concat(series, axis=1)  # steps x seeds (NaN where a seed lacks a step)
                curves[LABELS[method]] = (joined.index.to_numpy(float), joined.to_numpy(float).T)
        if curves:
            paths.append(plot_mean_std(curves, run.dir / f"curves_{task}.png", title=task,
                                       ylabel="eval normalized performance (mean +- std over seeds)",
                                       xlabel="distillation updates"))
    return paths


def write_robustness(run: Run, cfg: Table1Config,
                     robust: dict[tuple[str, str], list[tuple[Path, ...]]]) -> list[Path]:
    """The robustness study: per task, student and noise level, the score over all seeds' episodes, the
    spread of the per-seed means and the share of the noise-free score kept (``robustness.csv``, a
    section appended to ``table1.md``); per task a PNG of the score against the noise level."""
    if not robust:
        return []
    levels = sorted(cfg.noise_levels)
    rows, pngs, wide = [], [], []
    for task in cfg.tasks:
        curves = {}
        for method in ("trakdis", "trakdis_noise"):
            if (task, method) not in robust:
                continue
            episodes = {}  # per seed: its evaluations' episodes (a level evaluated twice: the first kept)
            for dirs in robust[task, method]:
                frames = pd.concat([pd.read_csv(d / "episodes.csv") for d in dirs], ignore_index=True)
                episodes[dirs] = frames.drop_duplicates(["state_noise", "episode"]).sort_values("episode")
            finals = []  # levels x seeds
            for level in levels:
                finals.append([])
                for dirs, e in episodes.items():
                    at = e.loc[np.isclose(e["state_noise"], level, rtol=1e-9, atol=0), "final_normalized_performance"]
                    if at.empty:  # a finished stage of an earlier configuration (--resume with other levels)
                        raise ValueError(f"{' and '.join(str(d / 'episodes.csv') for d in dirs)}: no episode at state "
                                         f"noise {level:g} (their levels: {sorted(e['state_noise'].unique())}): run "
                                         f"with the levels it was made with, or under a new --name")
                    finals[-1].append(at.to_numpy(float))
            stats = [summarize_method(f) for f in finals]
            zero = levels.index(0.0)
            clean = stats[zero]["mean"]
            kept = [st["mean"] / clean if clean > 0 else float("nan") for st in stats]
            # the same configurations at every level: the change from the noise-free score, episode by episode
            paired = [paired_difference(np.concatenate(finals[zero]), np.concatenate(f)) for f in finals]
            halved = next((lv for lv, k in zip(levels, kept) if k <= 0.5), None)
            rows += [{"task": task, "method": method, "state_noise": lv, **st, "kept": k, "change": d, "change_se": se}
                     for lv, st, k, (d, se) in zip(levels, stats, kept, paired)]
            trained_at = levels.index(cfg.estimate_noise) if cfg.estimate_noise in levels else None
            wide.append({"task": task, "student": LABELS[method],
                         **{f"{lv:g}": f"{st['mean']:.3f} +- {st['std']:.3f}" + (f" ({k:.0%})" if np.isfinite(k) else "")
                            for lv, st, k in zip(levels, stats, kept)},
                         "halves at": "-" if halved is None else f"{halved:g}",
                         **({f"change at {cfg.estimate_noise:g} (paired)":
                             f"{paired[trained_at][0]:+.3f} +- {paired[trained_at][1]:.3f}"} if trained_at is not None else {})})
            curves[LABELS[method]] = (np.arange(len(levels)), np.array([[f.mean() for f in per] for per in finals]).T)
        if curves:
            pngs.append(plot_mean_std(curves, run.dir / f"robustness_{task}.png", title=task,
                                      ylabel="eval normalized performance (mean +- std over seeds)",
                                      xlabel="std of the noise on the estimated state (m)",
                                      xticks=[(i, f"{lv:g}") for i, lv in enumerate(levels)]))
    atomic_write_bytes(run.dir / "robustness.csv", pd.DataFrame(rows).to_csv(index=False).encode())
    text = ["## Robustness: Gaussian noise on the estimated state (the paper's Fig. 7)", "",
            f"Each cell: mean +- std over all episodes of all seeds ({cfg.noise_trials or cfg.trials} per level and "
            f"seed) and, in brackets, the share of the noise-free score kept (none when that score is <= 0); "
            "the state is in metres (1e-3: 1 mm). "
            f"'TraKDis+noise': distilled with noise of std {cfg.estimate_noise:g}. "
            "'halves at': the smallest level that keeps half of the noise-free score or less ('-': none); "
            "'change (paired)': the score at that level minus the noise-free one on the same configurations, "
            "mean +- standard error over episodes.", "",
            markdown_table(pd.DataFrame(wide)), ""]
    md = run.dir / "table1.md"
    atomic_write_bytes(md, (md.read_text() + "\n" + "\n".join(text)).encode())
    return pngs


def main(argv=None) -> pd.DataFrame:
    argv = list(sys.argv[1:] if argv is None else argv)
    argv = [a for x in argv for a in (("--preset", "quick") if x == "--quick" else (x,))]
    parsed = parse_config(Table1Config, argv, presets=PRESETS, description=__doc__)
    report = parsed.report
    run = open_report(parsed, argv) if report else Run.start("table1", Table1Config, argv, presets=PRESETS,
                                                             description=__doc__)
    cfg = run.cfg
    seeds = list(range(cfg.seed, cfg.seed + cfg.seeds))
    stages = FinishedStages(run) if report else make_stages(run, RECIPES, timings_path=run.dir / "timings.csv")
    evals: dict[tuple[str, str], list[Path]] = {}
    robust: dict[tuple[str, str], list[tuple[Path, ...]]] = {}
    students: dict[tuple[str, str], list[Path]] = {}
    start = time.perf_counter()
    chains = [(task, seed) for task in cfg.tasks for seed in seeds]

    def chain(task: str, seed: int):
        try:
            return run_task_seed(stages, cfg, cfg.name, task, seed)
        except FileNotFoundError as err:  # --report: a teacher candidates' selection not played yet
            if not report:
                raise
            run.print(f"{task} seed {seed}: nothing to tabulate yet ({err})")
        except StageFailed:  # under Ray: reported with the others when the queue drains
            pass
        return None

    with stages.queued():  # leaving it: every evaluation has run
        if isinstance(stages, RayStages):  # each chain submits its stages from its own thread, waiting where it reads
            for recipe in ("online_dt", "distill"):  # one import each, not one per thread
                recipe_module(recipe)
            with ThreadPoolExecutor(len(chains), thread_name_prefix="table1-chain") as pool:
                results = list(pool.map(lambda c: chain(*c), chains))
        else:
            results = [chain(task, seed) for task, seed in chains]
        for (task, seed), result in zip(chains, results):
            if result is None:
                continue
            done, noise, arms = result
            for method, directory in arms.items():
                students.setdefault((task, method), []).append(directory)
            for method, directory in done.items():
                evals.setdefault((task, method), []).append(directory)
            for method, directories in noise.items():
                robust.setdefault((task, method), []).append(directories)
    note = ""
    if report:
        evals, robust, students, total, n_done = finished(evals, robust, students)
        if not evals:
            raise FileNotFoundError(f"--report: no evaluation of run {run.dir.parent} has finished yet "
                                    f"({total} to come)")
        note = (f"So far: the {n_done} of {total} evaluations that have finished (`--report` while the run goes on; "
                "the seeds column says how many seeds each row has).")
        run.print(note)
    write_tables(run, cfg, evals, note=note)
    pngs = write_curves(run, cfg, students) + write_robustness(run, cfg, robust)
    if not report:
        run.print(f"wall time {time.perf_counter() - start:.0f} s; the stages run so far: "
                  f"{sum(stages.timings.values()):.0f} s (timings.csv; background stages overlap the others)")
    run.print(f"wrote {run.dir / 'table1.md'}" + "".join(f", {p.name}" for p in pngs))
    print((run.dir / "table1.md").read_text())
    return pd.read_csv(run.dir / "table1.csv")


if __name__ == "__main__":
    main(sys.argv[1:])
