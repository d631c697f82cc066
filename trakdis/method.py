"""TraKDis as stages of its recipes: the one definition of what each stage runs by default.

``recipes/pipeline.py`` runs the method on one task; ``benchmarks/table1.py`` runs it, its ablations
and the image baselines over tasks and seeds. Both build the teacher's, the encoder's and the
student's arguments here (Table I its baselines' too), so that the TraKDis of Table I is the
pipeline's. Each function returns a recipe's command-line arguments, the method's defaults first
and a caller's ``extra`` options last (the later flag wins).

    teacher = stages.run("online_dt", "t", "policy.pt", teacher_stage_args("ClothFold"))
    encoder = stages.run("train_encoder", "e", "encoder.pt", encoder_stage_args("ClothFold", teacher))
    student = stages.run("distill", "s", "policy.pt", student_stage_args("ClothFold", teacher, encoder))
"""
from __future__ import annotations

import functools
import json
import shlex
from os import PathLike
from pathlib import Path
from typing import Any

from trakdis.envs.task_defaults import task_defaults
from trakdis.evaluation import pick_candidate, read_final_scores
from trakdis.utils.checkpoint import atomic_write_bytes
from trakdis.utils.config import parse_config
from trakdis.utils.stages import Stages

TEACHER_ARGS = "--train-state-noise 0.01 --state-scale-floor 0.02 --online-rounds 0"
"""recipes/online_dt.py: the offline teacher trained on states with 1 cm of Gaussian noise, so that its
weights act on an encoder's estimates (docs/recipes/distill.md)"""
MAIN_JOB_RESETS = "--data.episodes 40 --model.log-std-min -2.5 --online-labels executed"
"""recipes/online_dt.py's main-job defaults that the teacher stage resets, before ``TEACHER_ARGS`` or a caller's: the
encoder's 40 demonstrations (one dataset for both stages), DTModelConfig's log-std floor, Online DT's labels. Not when
the caller names a ``--preset``: every preset sets these itself, and explicit flags would override it."""
ENCODER_ARGS = "--extra-noise 0.5 --members 3 --select-episodes 30"
"""recipes/train_encoder.py: noisy-expert images added to training; three encoders trained side by side, the
one whose weight copy folds best on 30 train-split episodes kept (which draw the copy gets was the largest
effect on the student, docs/recipes/train_encoder.md); raced in chunks of 10 (--select-chunk), a copy clearly
behind stops early"""
CANDIDATE_SEED_STRIDE = 1000
"""Teacher candidate ``i`` of a run with seed ``s`` trains with seed ``s + CANDIDATE_SEED_STRIDE * i`` (candidate 0:
the run's own seed), so the candidates of Table I's consecutive seeds never share one"""
STUDENT_ARGS = ""
"""recipes/distill.py: its own defaults (weight copy, distillation on the expert data, picker odometry, the per-task
snapshot selection and expert-action term)"""


def _flags(*, parallel: bool = False, mask_unseen_pickers: bool = False) -> list[str]:
    return (["--mask-unseen-pickers"] if mask_unseen_pickers else []) + (["--parallel"] if parallel else [])


def teacher_candidates(task: str, requested: int | None = None) -> int:
    """The teacher candidates of ``task``: ``requested``, or the task's default (``TaskDefaults.teacher_candidates``,
    trakdis.envs.task_defaults)."""
    return task_defaults(task).teacher_candidates if requested is None else int(requested)


def check_teacher_selection(candidates: int | None, select_episodes: int, margin: float = 0.0) -> None:
    """Raise if the teacher candidates' options cannot run (``candidates`` ``None``: a task's default, which may be
    more than one): the one check of ``teacher_stage`` and of the configurations that pass them on."""
    compared = candidates is None or candidates > 1
    if (candidates is not None and candidates < 1) or (compared and select_episodes < 2) or not margin >= 0:
        raise ValueError(f"--teacher-candidates {candidates}: >= 1; --teacher-select-episodes {select_episodes}: >= 2 "
                         f"to compare candidates; --teacher-select-margin {margin}: >= 0")


def data_args(task: str) -> list[str]:
    """The expert data options every stage of ``task`` gets (from its ``TaskDefaults.close_radius``,
    trakdis.envs.task_defaults), so that all read one dataset (and Table I's image baselines the same)."""
    radius = task_defaults(task).close_radius
    return [] if radius is None else ["--data.close-radius", f"{radius:g}"]


def teacher_stage_args(task: str, extra: str = TEACHER_ARGS, *, mask_unseen_pickers: bool = False) -> list[str]:
    """``recipes/online_dt.py``: the expert dataset, collected with the images the encoder stage reads
    (one collection, not two), and the privileged teacher, with the grasp head where the task's
    ``TaskDefaults.grasp_head`` says so; it evaluates nothing itself (the callers do)."""
    extra_args = shlex.split(extra)
    preset = any(a == "--preset" or a.startswith("--preset=") for a in extra_args)
    resets = [] if preset else shlex.split(MAIN_JOB_RESETS)
    grasp_head = ["--model.grasp-head"] if task_defaults(task).grasp_head else []  # --model.no-grasp-head in extra wins
    return ["--task", task, *resets, *grasp_head, *data_args(task), "--collect-pixels",
            *_flags(mask_unseen_pickers=mask_unseen_pickers), "--eval-episodes", "0", *extra_args]


def encoder_stage_args(task: str, teacher: str | PathLike, extra: str = ENCODER_ARGS, *, parallel: bool = True,
                       mask_unseen_pickers: bool = False) -> list[str]:
    """``recipes/train_encoder.py``: the encoder, also trained on the images of the ``teacher``'s weight-copied
    student (its rounds of rollouts) and chosen by that copy's episodes; ``parallel``: those episodes on 2
    worker processes (the same episodes)."""
    return ["--task", task, *data_args(task), "--teacher", str(teacher),
            *_flags(parallel=parallel, mask_unseen_pickers=mask_unseen_pickers), *shlex.split(extra)]


def student_stage_args(task: str, teacher: str | PathLike, encoder: str | PathLike, extra: str = STUDENT_ARGS, *,
                       parallel: bool = True) -> list[str]:
    """``recipes/distill.py``: the image-only student of ``task``, the ``teacher``'s weights reading the ``encoder``'s
    estimates, distilled; it evaluates nothing itself unless ``extra`` says so."""
    return [*data_args(task), "--teacher", str(teacher), "--encoder", str(encoder), "--eval-episodes", "0",
            *_flags(parallel=parallel), *shlex.split(extra)]


def no_distill_stage_args(teacher: Any, student: Any) -> list[str]:
    """``recipes/distill.py`` flags, after a student stage's (:func:`student_stage_args`), of the paper's No-Distill
    ablation (section IV-D: "the decision transformer and the CNN encoder [trained] to imitate the heuristic expert
    demonstrations", one of the variants without the teacher's weights): a DT of the teacher's sizes on fresh weights
    (``--no-weight-copy``) reading the method's encoder's estimates, trained on the expert dataset's own actions
    (``--no-distill``), the last round's weights kept. ``teacher``: the teacher stage's parsed configuration
    (``recipes/online_dt.py``'s ``OnlineDTConfig``); ``student``: the student stage's (``DistillConfig``), whose
    ``rounds`` the updates are spread over (the same evaluation points on the curve as the other arms).

    The teacher's weights fine-tuned on the expert's actions (``--no-distill`` alone) is another, stronger arm:
    ``benchmarks/table1.py``'s ``no_distill_copy``."""
    # Budget: a DT on fresh weights is trained, not fine-tuned, so it gets the teacher's offline recipe (its updates,
    # windows per update, optimiser and lr schedule), not the weight copy's short low-lr fine-tune, on which a fresh
    # DT barely leaves its initialisation (No-Pretrain's rows in docs/table1.md).
    # Encoder: the method's (pre-trained with augmentation on the simulator's states), kept frozen, its estimates
    # computed once, as for the method's student: the arm then differs from TraKDis in the teacher's weights and
    # labels alone, where a jointly fine-tuned encoder would be a second difference (distill.py trains no encoder).
    # Selection: none (the last round's, as the teacher's offline phase keeps its last update): the train-split
    # selection keeps its first snapshot unless a later one beats it measurably, a guard of the weight copy; with
    # fresh weights that would favour the least trained snapshot.
    rounds = max(int(student.rounds), 1)
    optim = {f: getattr(teacher, f) for f in ("optimizer", "lr", "weight_decay", "warmup_steps", "grad_clip")}
    return ["--no-weight-copy", "--no-distill", "--updates-per-round", str(-(-int(teacher.offline_updates) // rounds)),
            "--batch-size", str(teacher.batch_size), "--min-lr-fraction", str(teacher.min_lr_fraction),
            *[a for f, v in optim.items() for a in (f"--{f.replace('_', '-')}", str(v))], "--select-episodes", "0"]


def baseline_stage_args(task: str, extra: str = "") -> list[str]:
    """``recipes/bc_image.py`` / ``recipes/dt_image.py``: an image baseline of ``task`` on the method's expert data
    (:func:`data_args`); it evaluates nothing itself (the callers do)."""
    return ["--task", task, *data_args(task), "--eval-episodes", "0", *shlex.split(extra)]


def teacher_stage(stages: Stages, run_name: str, args: list[str], *, seed: int, candidates: int = 1,
                  select_episodes: int = 30, margin: float = 0.0, parallel: bool = True,
                  group: str | None = None) -> tuple[Path, int]:
    """The privileged teacher: ``recipes/online_dt.py`` with ``args`` as the stage ``run_name``. With ``candidates``
    > 1 the stage runs that many times, candidate ``i`` as ``<run_name>-c<i>`` with seed ``seed +
    CANDIDATE_SEED_STRIDE * i`` (candidate 0 is the plain stage, bit for bit), each plays the same
    ``select_episodes`` train-split episodes (``recipes/evaluate.py --split train``: configurations no evaluation
    plays), and the one with the best mean is kept unless candidate 0 is within ``margin`` paired standard errors
    of it (:func:`~trakdis.evaluation.pick_candidate`; default 0: the best, ties to the earlier, as candidate 0 is
    one more draw of the same stage). A seed's teacher can fail outright while the others reach the expert
    (docs/recipes/distill.md); the train split tells them apart. The choice and every candidate's scores are
    written to ``<pipeline run dir>/<run_name>-selection.json``. Returns the kept teacher's run directory and its
    index (callers name the stages that depend on it after it). ``group``: the candidates are stages of that group
    (:meth:`~trakdis.utils.stages.Stages.first_of`: the first one collects the dataset, side by side the others
    wait for it)."""
    check_teacher_selection(candidates, select_episodes, margin)
    names = [run_name] + [f"{run_name}-c{i}" for i in range(1, candidates)]
    submit = stages.run if group is None else functools.partial(stages.first_of, group)
    teachers = [submit("online_dt", n, "policy.pt", args, seed=seed + CANDIDATE_SEED_STRIDE * i)
                for i, n in enumerate(names)]
    if candidates == 1:
        return teachers[0], 0
    selects = [stages.run("evaluate", f"{n}-select", "summary.csv",  # the same seed: the same configurations
                          ["--policy", str(teacher), "--split", "train", "--trials", str(select_episodes),
                           "--videos", "0", *(["--parallel"] if parallel else [])], seed=seed)
               for n, teacher in zip(names, teachers)]
    scores = [read_final_scores(stages.wait(select)).tolist() for select in selects]
    kept = pick_candidate(scores, margin=margin)
    means = [sum(s) / len(s) for s in scores]
    stages.pipeline.print(f"teacher candidates on {select_episodes} train-split episodes: "
                          + ", ".join(f"{n} {m:.3f}" for n, m in zip(names, means)) + f"; {names[kept]} kept")
    record = {"kept": kept, "teachers": [str(t) for t in teachers], "means": means, "scores": scores,
              "margin": margin}
    atomic_write_bytes(stages.pipeline.dir / f"{run_name}-selection.json", json.dumps(record, indent=1).encode())
    return teachers[kept], kept


def check_stage_args(stages: Stages, cfg: Any) -> None:
    """Parse the encoder and student stages' arguments (``--encoder-args``, ``--student-args``) with their
    recipes' configurations, before any stage runs: a bad option ends the pipeline at once, naming the flag
    that carried it, instead of after the teacher's training. The stage's error itself is printed above. ``cfg``:
    ``recipes/pipeline.py``'s configuration (``task``, ``encoder_args``, ``student_args``, ``parallel``,
    ``mask_unseen_pickers``)."""
    placeholder = stages.pipeline.dir / "not-yet-trained"  # stands for the files the earlier stages will write
    for flag, recipe, config, args, presets in (
            ("--encoder-args", "train_encoder", "TrainEncoderConfig",
             encoder_stage_args(cfg.task, placeholder, cfg.encoder_args, parallel=cfg.parallel,
                                mask_unseen_pickers=cfg.mask_unseen_pickers), None),
            ("--student-args", "distill", "DistillConfig",
             student_stage_args(cfg.task, placeholder, placeholder, cfg.student_args, parallel=cfg.parallel),
             "PRESETS")):
        module = stages.recipe(recipe)
        try:
            parse_config(getattr(module, config), args, presets=getattr(module, presets) if presets else None)
        except SystemExit as err:
            if err.code in (0, None):  # --help inside the arguments
                raise
            raise SystemExit(f"pipeline.py {flag}={getattr(cfg, flag[2:].replace('-', '_'))!r}: recipes/{recipe}.py "
                             f"refuses these options (its error is above); nothing was run") from None
