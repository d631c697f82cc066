"""The method's per-task rules, in one table beside :class:`~trakdis.envs.specs.TaskSpec`.

:class:`TaskSpec` holds the facts of a task (shapes, horizon, mirror); :class:`TaskDefaults` holds what the
method does differently per task, each rule measured (the doc named beside each field has the numbers). The
recipes, ``trakdis.modules`` and ``trakdis.method`` read it through :func:`task_defaults`; an option a caller
gives still wins over the table. Pure Python (no MuJoCo import), so every part of the package may import it.
"""

from __future__ import annotations

import dataclasses

from trakdis.envs.specs import TASKS, check_task

__all__ = ["TaskDefaults", "TASK_DEFAULTS", "task_defaults"]


@dataclasses.dataclass(frozen=True)
class TaskDefaults:
    """What the method does on one task when no option says otherwise.

    Attributes:
        select_episodes: recipes/distill.py's ``--select-episodes`` default: 0 keeps the last round, else the
            train-split episodes that pick the snapshot (distillation can lower the weight copy on the diagonal
            folds, not on ClothFold; docs/recipes/distill.md).
        expert_coef: recipes/distill.py's ``--expert-coef`` default when the windows hold the expert's own
            actions (on ClothFold the expert's actions raise the student, on the diagonal folds they lower it
            below the copy; docs/recipes/distill.md).
        test_time_flip: recipes/train_encoder.py's ``--test-time-flip auto`` turns the flip on (it lifted the
            weight copy on every ClothFold seed, went both ways on the diagonal folds;
            docs/recipes/train_encoder.md).
        hidden_grasp: the recipes' DTs leave the grasp commands out of the action tokens (the ClothFold teacher
            copied its previous grasp token and missed the first close; hiding it lowered the diagonal folds'
            student; docs/recipes/online_dt.md).
        teacher_candidates: teacher stages run when a caller names no number (one draw often lands far below
            the others on the diagonal folds; on ClothFold the draws are close and 30 episodes do not rank them;
            docs/recipes/distill.md).
        grasp_head: the method's teacher (and so its student, a copy of it) models the grasp with the grasp head
            (``--model.grasp-head``: a Bernoulli grasp and the movement of its branch; without it a pinned-fold
            teacher trained on noisy states lifts the open picker while unsure whether to close and collapses
            on some seeds; on ClothFold and the unpinned fold it releases late and is not the default there;
            docs/recipes/online_dt.md).
        hold_radius: the student's held-corner radius (recipes/distill.py's ``--hold-radius`` default, metres; 0:
            off): on the pinned fold its students lifted the corner and opened again where the encoder read the
            lifted corner still down; measured there alone (docs/recipes/distill.md).
        close_radius: the expert data's grasp-close radius (``--data.close-radius``) of every stage of the
            method, ``None`` for the data's default (a policy acting on blurred states closes about 1.5 cm
            farther out than its demonstrations, beyond ClothFold's reach from 2 cm; docs/recipes/pipeline.md).
    """

    select_episodes: int
    expert_coef: float
    test_time_flip: bool
    hidden_grasp: bool
    teacher_candidates: int
    close_radius: float | None = None
    grasp_head: bool = False
    hold_radius: float = 0.0


TASK_DEFAULTS = {
    "ClothFold": TaskDefaults(select_episodes=0, expert_coef=1.0, test_time_flip=True, hidden_grasp=True,
                              teacher_candidates=1, close_radius=0.01),
    "ClothFoldDiagonalPinned": TaskDefaults(select_episodes=30, expert_coef=0.0, test_time_flip=False,
                                            hidden_grasp=False, teacher_candidates=3, grasp_head=True,
                                            hold_radius=0.03),
    "ClothFoldDiagonalUnpinned": TaskDefaults(select_episodes=30, expert_coef=0.0, test_time_flip=False,
                                              hidden_grasp=False, teacher_candidates=3),
}
"""One :class:`TaskDefaults` per task of :data:`~trakdis.envs.specs.TASKS`."""

assert set(TASK_DEFAULTS) == set(TASKS), "every task needs its TaskDefaults"


def task_defaults(task: str) -> TaskDefaults:
    """The method's per-task rules of ``task`` (a ``ValueError`` naming the choices for an unknown one)."""
    return TASK_DEFAULTS[check_task(task)]
