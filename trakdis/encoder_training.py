"""The state encoder's training run (``train_encoder.py``): its resume state (:func:`encoder_state`), its labels
(:func:`mask_unseen_labels`), its validation (:func:`validation_errors`, printed: :func:`error_groups`) and the
epoch it keeps (:func:`keep_best_epoch`), and what a teacher's weight copy adds (:class:`WeightCopyConfig`):
rounds of the weight-copied student's rollouts whose images join the training data (:class:`StudentRounds`, a
data mixture), and the choice among encoders trained side by side by their weight copy's scores
(:func:`select_member`).

    state = encoder_state(run, encoder, optim)
    rounds = StudentRounds(state, teacher, rounds=2, episodes=20, first_epoch=20, epochs_per_round=5, seed=5000)
    while state["epoch"] < total_epochs:
        if rounds.due():
            rounds.play(encoder, run)
        train_epoch(loss, optim, rounds.training_data(train), 128, ...)
        state["epoch"] += 1
        keep_best_epoch(state, encoder, validation_errors(loss, encoder, val, spec.state_error_cm))
"""
from __future__ import annotations

import copy
import functools
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn

from trakdis.modules import EncoderEnsemble
from trakdis.policies import PolicyHandle
from trakdis.student import student_rollout_steps, weight_copy_race
from trakdis.training import eval_batches
from trakdis.transforms import OutOfViewFill
from trakdis.utils.limits import check_options
from trakdis.utils.run import Run, RunState

__all__ = ["StudentRounds", "WeightCopyConfig", "encoder_state", "error_groups", "keep_best_epoch", "mask_unseen_labels",
           "select_member", "validation_errors"]


@dataclass
class WeightCopyConfig:
    """What a teacher's weight copy (the teacher's weights acting on the encoder's estimates) adds to the
    encoder's training (a base of ``train_encoder.py``'s config dataclass, so the flags stay ``--teacher``,
    ``--student-rounds``, ``--select-episodes``, ...): rounds of its rollouts whose images join the training
    data (:class:`StudentRounds`), and the choice among encoders trained side by side by its scores
    (:func:`select_member`)."""

    select_episodes: int = 0
    """with --members K > 1 and --teacher: keep the one member whose weight copy (the teacher's weights on its
    estimates) scores best on this many train-split episodes, instead of the members' mean (0: the mean)"""
    select_chunk: int = 10
    """--select-episodes in chunks of this many: after each, a member whose weight copy is below the leading one's
    by more than 2 standard errors of their paired difference plays no more (racing; 0: all play every episode)"""
    teacher: str = ""
    """teacher policy file or online_dt run directory: also train on the weight-copied student's images"""
    student_rounds: int = 2  # rounds of (student rollouts, training) with --teacher
    student_episodes: int = 20  # student rollouts per round
    student_epochs: int = 5  # passes over all training images after each round's rollouts

    def __post_init__(self):  # while parsing (tyro), before the run directory exists
        check_options(self, counts=("student_rounds", "student_episodes", "student_epochs"))
        if self.select_chunk < 0:
            raise ValueError(f"--select-chunk {self.select_chunk}: must be >= 0 (0: no racing)")
        parent = getattr(super(), "__post_init__", None)
        if parent is not None:
            parent()

    @property
    def with_rounds(self) -> bool:
        """Whether the training has student rounds (a ``--teacher`` and ``--student-rounds`` > 0)."""
        return bool(self.teacher) and self.student_rounds > 0

    @property
    def round_epochs(self) -> int:
        """The epochs the student rounds add after the first ones (0 without rounds)."""
        return self.student_rounds * self.student_epochs if self.with_rounds else 0

    def student_rounds_of(self, state: RunState, teacher: PolicyHandle | None, *, first_epoch: int, seed: int,
                          image_size: int = 32, label_fill: OutOfViewFill | None = None,
                          parallel: bool = False) -> StudentRounds:
        """The :class:`StudentRounds` of these options: ``--student-rounds`` rounds of ``--student-episodes``
        episodes of ``teacher``'s weight copy after the first ``first_epoch`` epochs, then every
        ``--student-epochs`` (none without a ``--teacher``); the other arguments are its own."""
        return StudentRounds(state, teacher if self.with_rounds else None, rounds=self.student_rounds,
                             episodes=self.student_episodes, first_epoch=first_epoch,
                             epochs_per_round=self.student_epochs, seed=seed, image_size=image_size,
                             label_fill=label_fill, parallel=parallel)

    def check_student_rounds(self) -> None:
        """A ``ValueError`` unless the student rounds can run: with a ``--teacher`` and ``--student-rounds`` > 0,
        ``--student-episodes`` and ``--student-epochs`` >= 1 (checked when the run starts)."""
        if self.teacher and self.student_rounds > 0 and min(self.student_episodes, self.student_epochs) < 1:
            raise ValueError(f"--student-rounds {self.student_rounds} >= 0 needs --student-episodes "
                             f"({self.student_episodes}) and --student-epochs ({self.student_epochs}) >= 1")


def encoder_state(run: Run, encoder: nn.Module, optim: torch.optim.Optimizer, *,
                  schedule: Any | None = None) -> RunState:
    """The resume state of an encoder run, its counters at the checkpoint's top level: ``epoch`` (the step),
    ``best`` (the epoch kept: :func:`keep_best_epoch`), the student rounds' (:meth:`StudentRounds.counters`) and
    ``member_scores`` (:func:`select_member`), with the states of ``encoder``, ``optim`` and the learning-rate
    ``schedule`` if any."""
    return RunState(run, {"epoch": 0, "best": {"val_mae": float("inf"), "state_dict": None, "epoch": -1},
                          **StudentRounds.counters(), "member_scores": {}},
                    step_key="epoch", counters_key=None, encoder=encoder, optim=optim,
                    **({} if schedule is None else {"schedule": schedule}))


def mask_unseen_labels(fill: OutOfViewFill | None, train: TensorDictBase, val: TensorDictBase | None, *,
                       log: Callable[[str], None] = print) -> None:
    """The labels of an encoder trained with ``--mask-unseen-pickers``: the ``"state"`` of the training and
    validation steps as the teacher reads it, each picker out of the image replaced by ``fill``'s sentinel
    (which the encoder then learns to output for it); the share out of view is logged. ``fill`` None: the
    labels stay the true states."""
    if fill is None:
        return
    log(f"--mask-unseen-pickers: {1 - float(fill.visible(train['state']).float().mean()):.1%} of the training "
        f"images' picker positions are out of view (label {[round(v, 3) for v in fill.fill.tolist()]})")
    train.set("state", fill.mask(train["state"]))
    if val is not None:
        val.set("state", fill.mask(val["state"]))


def validation_errors(loss_module: nn.Module, encoder: nn.Module, data: TensorDictBase | None,
                      state_error_cm: Callable[[torch.Tensor], dict[str, float]], *, batch_size: int = 1024,
                      device: str | torch.device = "cpu") -> dict[str, float]:
    """``encoder``'s error on the validation steps ``data`` (``"pixels"`` to ``"state"``): ``state_error_cm`` of
    the absolute errors (a task spec's: ``mae`` and the error per state group in cm); ``{"mae": nan}`` without
    validation steps (``data`` None). Without gradients, ``loss_module`` (the training loss, holding the
    encoder's modules) in eval mode (:func:`~trakdis.training.eval_batches`)."""
    if data is None:
        return {"mae": float("nan")}
    errors = eval_batches(loss_module, data, batch_size, functools.partial(_absolute_error, encoder), device=device)
    return state_error_cm(torch.cat(errors))


def error_groups(errors: Mapping[str, float]) -> str:
    """The per-group errors of :func:`validation_errors` as printed: ``"corners 1.23 cm, pickers 0.45 cm"``."""
    return ", ".join(f"{k.removesuffix('_cm')} {v:.2f} cm" for k, v in errors.items() if k != "mae")


def _absolute_error(encoder: nn.Module, batch: TensorDictBase) -> torch.Tensor:
    return (encoder(batch["pixels"]) - batch["state"]).abs()


def keep_best_epoch(state: RunState, encoder: nn.Module, errors: Mapping[str, float], *, always: bool = False) -> bool:
    """Model selection on the validation steps: the epoch just trained (``state["epoch"]``) becomes the one
    kept, ``state["best"]`` (``val_mae``, a copy of ``encoder``'s weights, ``epoch``, ``val_error_cm``: the
    other ``errors``), when its mean absolute error ``errors["mae"]`` is below the kept one's, or ``always``
    (no validation steps; or epochs after the student rounds began, which aim at other states than the
    validation's: the newest encoder is kept). Returns whether it was kept."""
    if always or errors["mae"] < state["best"]["val_mae"]:
        state["best"] = {"val_mae": errors["mae"], "state_dict": copy.deepcopy(encoder.state_dict()),
                         "epoch": state["epoch"], "val_error_cm": {k: v for k, v in errors.items() if k != "mae"}}
        return True
    return False


class StudentRounds:
    """The encoder's training data with a teacher (``train_encoder.py --teacher``), a data mixture: the expert's
    training steps and, after the first ``first_epoch`` epochs and then every ``epochs_per_round`` epochs, the
    steps of a round of ``episodes`` episodes of the weight-copied student of ``teacher`` acting on the
    encoder as it is then (:func:`~trakdis.student.student_rollout_steps`, configurations drawn with ``seed``
    plus the round's index; their labels masked by ``label_fill`` if given): the states the student visits,
    which expert images never show. Every round's steps are kept, in ``state`` (:meth:`counters`:
    ``student_steps``, plain tensors, as the checkpoint loader reads them, and ``rounds_done``), so a resumed
    run neither plays a round twice nor loses its images. ``teacher`` None or ``rounds`` 0: no rounds."""

    def __init__(self, state: RunState, teacher: PolicyHandle | None, *, rounds: int, episodes: int, first_epoch: int,
                 epochs_per_round: int, seed: int, image_size: int = 32, label_fill: OutOfViewFill | None = None,
                 parallel: bool = False):
        self.state, self.teacher, self.rounds, self.episodes = state, teacher, rounds, episodes
        self.first_epoch, self.epochs_per_round, self.seed, self.image_size = first_epoch, epochs_per_round, seed, image_size
        self.label_fill, self.parallel = label_fill, parallel

    @staticmethod
    def counters() -> dict[str, Any]:
        """The state's entries, no round played yet."""
        return {"rounds_done": 0, "student_steps": None}

    def due(self) -> bool:
        """Whether a round's rollouts come before the next epoch (``state["epoch"]`` epochs done)."""
        return (self.teacher is not None and self.rounds > 0
                and self.state["epoch"] == self.first_epoch + self.state["rounds_done"] * self.epochs_per_round)

    def play(self, encoder: nn.Module, run: Run) -> None:
        """The next round: its steps joined to the earlier rounds', the student's score and the encoder's error on
        its states logged at ``state["epoch"]`` (``student/*``) and printed."""
        new, metrics = student_rollout_steps(self.teacher, encoder, episodes=self.episodes, image_size=self.image_size,
                                             seed=self.seed + self.state["rounds_done"], label_fill=self.label_fill,
                                             parallel=self.parallel)
        new = new.to_dict()  # plain tensors: the checkpoint loader refuses TensorDicts
        old = self.state["student_steps"]
        self.state["student_steps"] = new if old is None else {k: torch.cat([old[k], v]) for k, v in new.items()}
        self.state["rounds_done"] += 1
        run.log(self.state["epoch"], {f"student/{k}": v for k, v in metrics.items()})
        run.print(f"student round {self.state['rounds_done']}/{self.rounds}: normalized performance "
                  f"{metrics['normalized_performance']:.3f}, encoder error on its states: corners "
                  f"{metrics['corners_cm']:.2f} cm, pickers {metrics['pickers_cm']:.2f} cm; +{len(new['state'])} images")

    def training_data(self, expert: TensorDictBase) -> TensorDictBase:
        """The steps of the next epoch: ``expert``'s (``[N]``), then every round's."""
        steps = self.state["student_steps"]
        return expert if steps is None else torch.cat([expert, TensorDict(steps, batch_size=[len(steps["state"])])])


def select_member(run: Run, state: RunState, teacher: PolicyHandle, encoder: EncoderEnsemble, *, episodes: int,
                  seed: int, chunk: int = 10, parallel: bool = False,
                  state_mirror: tuple[Sequence[int], Sequence[float]] | None = None) -> int:
    """The index of the member of ``encoder`` (encoders trained alike, side by side) whose weight copy folds best:
    which of them the teacher's weights act well with is not told by their errors on held-out images, their
    own episodes tell. Each member (reading the mirrored view too with ``state_mirror``) plays the same
    ``episodes`` train-split episodes (configurations drawn with ``seed``), raced in chunks of ``chunk``
    (:func:`~trakdis.student.weight_copy_race`: a member clearly behind plays no more); the one with the best
    mean among those that played all is kept. The scores live in ``state["member_scores"]`` (saved at once: a
    run killed during the race plays it again, one resumed after it does not); logged as ``select/*``."""
    if len(state["member_scores"]) < len(encoder.members):
        members = [EncoderEnsemble([member], state_mirror=state_mirror) for member in encoder.members]
        state["member_scores"] = {k: v.tolist() for k, v in weight_copy_race(
            teacher, members, episodes=episodes, seed=seed, chunk=chunk, parallel=parallel,
            on_chunk=functools.partial(_report_race, run.print)).items()}
        state.save()
    scores = state["member_scores"]
    for k, v in scores.items():
        run.print(f"member {k}: weight copy {sum(v) / len(v):.3f} on {len(v)} train-split episodes")
    means = {k: sum(v) / len(v) for k, v in scores.items()}
    played = max(map(len, scores.values()))
    selected = max((k for k, v in scores.items() if len(v) == played), key=means.get)  # of those that played all
    run.log(state[state.step_key], {f"select/member{k}_normalized_performance": m for k, m in means.items()})
    run.print(f"--select-episodes: member {selected} kept")
    return selected


def _report_race(log: Callable[[str], None], scores: Mapping[int, Sequence[float]], survivors: Sequence[int]) -> None:
    log(f"weight copies after {max(map(len, scores.values()))} episodes: " + ", ".join(
        f"member {k} {sum(v) / len(v):.3f}" + ("" if k in survivors else f" (stops at {len(v)})")
        for k, v in scores.items() if v))
