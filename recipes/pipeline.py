"""The whole TraKDis method on one task, in one command: teacher -> encoder -> student -> table.

    python recipes/pipeline.py                                   # ClothFold, default sizes
    python recipes/pipeline.py --task ClothFoldDiagonalUnpinned --name unpinned
    python recipes/pipeline.py --name cf --resume                # continue after a kill
    python recipes/pipeline.py --name cf --ray                   # stages as Ray tasks on every core (docs/scaling.md)

1. ``recipes/online_dt.py``: the expert dataset (on ClothFold, grasps closed within 1 cm for every stage:
   ``TaskDefaults.close_radius``) and the privileged teacher (by default offline, on states with 1 cm of
   Gaussian noise: ``--teacher-args``). With ``--teacher-candidates N`` the teacher stage runs N times (other
   seeds) and the one that folds best on ``--teacher-select-episodes`` train-split episodes is kept
   (``trakdis.method.teacher_stage``); the stages after it are then named ``<name>-c<i>-...``.
2. ``recipes/train_encoder.py``: the state encoder on the same dataset's images, a noisy expert's,
   and those the weight-copied student visits (``--teacher``, rounds of its rollouts); three trained
   side by side, the one the weight copy folds best with kept (``--members 3 --select-episodes 30``, raced:
   a member clearly behind after 10 or 20 of them plays no more).
3. ``recipes/distill.py``: the image-only student (weight copy, distillation on the expert data; on the
   diagonal folds the snapshot kept by its train-split selection episodes, on ClothFold the last round's, with
   the expert's actions beside the teacher's labels).
4. ``recipes/evaluate.py`` for the scripted expert, the teacher and the student on the same
   ``--trials`` eval-split configurations (same seed), then one Markdown table: mean, std,
   25/50/75th percentiles and the ratio to the teacher. The expert's episodes (from the start), then the
   teacher's, run in a low-priority background process, on the core that the teacher's, the encoder's
   and the student's training leave idle (``--no-background-evaluations``: after them); the student's,
   the encoder stage's rollouts and selection episodes and the student stage's selection episodes, on
   2 worker processes (``--no-parallel``: in turn). The numbers are the same.
   The stages evaluate nothing themselves (``--eval-episodes 0``; a stage's own ``--eval-episodes`` in its
   ``--*-args`` wins): the table has the evaluations. Each stage's default options: ``trakdis.method``.

Each stage is an ordinary run of its recipe under ``<root>/<recipe>/<name>-<stage>``; a stage whose
output file exists is skipped and an interrupted one is resumed, so ``--resume`` continues the
pipeline. Extra options go to one stage with ``--teacher-args="..."``, ``--encoder-args="..."``,
``--student-args="..."`` (with ``=``: the value starts with ``--``); ``--mask-unseen-pickers`` goes to
the teacher and encoder stages (the student inherits it from the teacher). Writes
``<root>/pipeline/<name>/summary.md`` and ``summary.csv``. With ``--ray`` (or ``--ray-address``) every stage is a
Ray task, run as soon as the stages it reads have (``trakdis.utils.ray_stages``): the same numbers.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import ClassVar
from pathlib import Path

import pandas as pd

from trakdis.envs.specs import TaskName
from trakdis.evaluation import evaluation_parts, write_summary_table
from trakdis.method import (ENCODER_ARGS, STUDENT_ARGS, TEACHER_ARGS, check_stage_args, check_teacher_selection,
                            encoder_stage_args, student_stage_args, teacher_candidates, teacher_stage,
                            teacher_stage_args)
from trakdis.policies import load_policy
from trakdis.utils.config import parse_config
from trakdis.utils.limits import check_options
from trakdis.utils.ray_stages import RayConfig, make_stages
from trakdis.utils.run import Run, RunConfig

RECIPES = Path(__file__).resolve().parent


@dataclass
class PipelineConfig(RayConfig, RunConfig):
    """The whole method on one task: teacher, encoder, student, and one evaluation table."""

    task: TaskName = "ClothFold"
    """cloth task"""
    trials: int = 100  # evaluation episodes per policy (eval split, the same configurations for all three)
    teacher_args: str = TEACHER_ARGS
    """extra options for recipes/online_dt.py (default: the offline teacher trained on states with
    1 cm of Gaussian noise, so that its weights act on an encoder's estimates; trakdis.method)"""
    teacher_candidates: int | None = None
    """teacher stages run (default: the task's TaskDefaults.teacher_candidates: 3 on the diagonal folds, 1 on
    ClothFold) (candidate i: --seed + 1000 i); the one that folds best on --teacher-select-episodes
    train-split episodes is kept (--teacher-select-margin; trakdis.method.teacher_stage)"""
    teacher_select_episodes: int = 30
    """train-split episodes each teacher candidate plays (with --teacher-candidates > 1)"""
    teacher_select_margin: float = 0.0
    """paired standard errors by which a teacher candidate must beat candidate 0 to replace it (0: the best mean)"""
    encoder_args: str = ENCODER_ARGS
    """extra options for recipes/train_encoder.py (default: noisy-expert images added to training; three
    encoders trained side by side, the one whose weight copy folds best on 30 train-split episodes kept;
    trakdis.method)"""
    student_args: str = STUDENT_ARGS
    """extra options for recipes/distill.py"""
    # options saved by earlier runs name flags renamed since: read as the new ones on --resume
    SAVED_FLAGS: ClassVar[dict] = {"teacher_args": {"--state-noise": "--train-state-noise"},
                                   "student_args": {"--state-noise": "--estimate-noise"}}
    mask_unseen_pickers: bool = False
    """pass --mask-unseen-pickers to the teacher and encoder stages (pickers out of the camera view masked)"""
    background_evaluations: bool = True
    """evaluate the scripted expert (from the start), then the teacher, in a low-priority background process while
    the stages train (--no-background-evaluations: after them, on 2 worker processes with --parallel)"""
    parallel: bool = True
    """evaluate the teacher and the student, and play the encoder's and the student's rollouts and selection
    episodes, on 2 worker processes (--no-parallel: in turn; the same numbers)"""

    def __post_init__(self):  # checked while the command line is parsed, before any stage runs
        check_teacher_selection(self.teacher_candidates, self.teacher_select_episodes, self.teacher_select_margin)
        check_options(self, sizes=("trials",))
        super().__post_init__()


def main(argv=None) -> pd.DataFrame:
    run = Run.start("pipeline", PipelineConfig, argv, description=__doc__)
    cfg, name = run.cfg, run.dir.name
    stages = make_stages(run, RECIPES)
    mask = cfg.mask_unseen_pickers
    parallel = ["--parallel"] if cfg.parallel else []  # the evaluations
    teacher_args = teacher_stage_args(cfg.task, cfg.teacher_args, mask_unseen_pickers=mask)
    online_dt = stages.recipe("online_dt")  # the expert plays episodes of the teacher's length
    horizon = parse_config(online_dt.OnlineDTConfig, teacher_args, presets=online_dt.PRESETS).horizon
    check_stage_args(stages, cfg)  # the later stages' options now, not after the teacher's training
    evaluate = ["--task", cfg.task, "--horizon", str(horizon), "--trials", str(cfg.trials), "--videos", "0"]
    directories, policies, parts = {}, {"expert": "expert"}, evaluation_parts(cfg.trials, cfg.eval_chunk)
    background = ("expert", "teacher") if cfg.background_evaluations else ()
    with stages.queued():  # submitted evaluations run in the background, in turn, beside the foreground stages
        if "expert" in background:  # from the start, on the core that the teacher's training leaves idle
            directories["expert"] = stages.submit("evaluate", f"{name}-eval-expert", "summary.csv",
                                                  ["--policy", "expert", *evaluate], parts=parts)
        teacher, kept = teacher_stage(stages, f"{name}-teacher", teacher_args, seed=cfg.seed,
                                      candidates=teacher_candidates(cfg.task, cfg.teacher_candidates),
                                      select_episodes=cfg.teacher_select_episodes,
                                      margin=cfg.teacher_select_margin, parallel=cfg.parallel, group="data")
        chain = f"{name}-c{kept}" if kept else name  # the stages after the teacher, named after the kept candidate
        policies["teacher"] = str(teacher)
        if load_policy(stages.wait(teacher)).horizon != horizon:  # a resumed teacher stage with another --horizon
            raise ValueError(f"{teacher / 'policy.pt'}: horizon {load_policy(teacher).horizon}, but the teacher's "
                             f"arguments give {horizon}; run the pipeline under another --name")
        if "teacher" in background:  # beside the encoder's and the student's training
            directories["teacher"] = stages.submit("evaluate", f"{chain}-eval-teacher", "summary.csv",
                                                   ["--policy", policies["teacher"], *evaluate], parts=parts)
        encoder = stages.run("train_encoder", f"{chain}-encoder", "encoder.pt",
                             encoder_stage_args(cfg.task, teacher, cfg.encoder_args, parallel=cfg.parallel,
                                                mask_unseen_pickers=mask))
        student = stages.run("distill", f"{chain}-student", "policy.pt",
                             student_stage_args(cfg.task, teacher, encoder, cfg.student_args, parallel=cfg.parallel))
        policies["student"] = str(student)
        for label, policy in policies.items():  # not in the background, or still waiting there: here, on 2 workers
            prefix = name if label == "expert" else chain
            if label not in directories or stages.withdraw(f"{prefix}-eval-{label}"):
                directories[label] = stages.run("evaluate", f"{prefix}-eval-{label}", "summary.csv",
                                                ["--policy", policy, *evaluate, *parallel], parts=parts)
    rows = [{**pd.read_csv(directories[label] / "summary.csv").iloc[0].to_dict(), "policy": label}
            for label in policies]  # expert, teacher, student
    teacher_mean = rows[1]["mean"]
    for row in rows:
        row["x_teacher"] = row["mean"] / teacher_mean if teacher_mean else float("nan")
    write_summary_table(rows, run.dir / "summary.csv", run.dir / "summary.md",
                        columns=("task", "policy", "n", "mean", "std", "p25", "p50", "p75", "x_teacher"))
    run.finish()
    stages.report()
    print((run.dir / "summary.md").read_text())
    return pd.read_csv(run.dir / "summary.csv")


if __name__ == "__main__":
    main(sys.argv[1:])
