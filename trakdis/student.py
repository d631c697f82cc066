"""The TraKDis student: the teacher's Decision Transformer reading an encoder's estimates from the image.

Its parts loaded and checked together (:func:`load_teacher_and_encoder`, :func:`check_unseen_picker_mask`),
the student made of them (:func:`weight_copied_student`: ``distill.py``'s starting point), and the episodes
of that weight copy: the states it visits, on which ``train_encoder.py --teacher`` trains the encoder
(:func:`student_rollout_steps`), and its scores, by which ``train_encoder.py --select-episodes`` chooses among
encoders (:func:`weight_copy_scores`, raced: :func:`weight_copy_race`).

Its distillation (``distill.py``): the options of the student and of what it learns from, and the parts they
make (:class:`StudentConfig`: the student, its loss, the expert data in its buffer, the policies that act in
the rollouts), a round's rollouts of DAgger's mixture (:class:`DAggerRollouts`), the run's resume state
(:func:`distill_state`) and its evaluations, the kept snapshot's included (:class:`StudentEvaluations`).

Above :mod:`trakdis.evaluation` (it plays episodes) and :mod:`trakdis.policies` (it builds on loaded policies).
"""
from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar, Literal, Mapping, Optional, Sequence

import numpy as np
import torch
from tensordict import TensorDict
from torch import nn

from trakdis.data import DataConfig, TrajectoryReplayBuffer, load_encoded_dataset
from trakdis.envs import close_env, task_defaults, task_spec
from trakdis.evaluation import CollectorName, EpisodeStream, episode_score, race_survivors, run_episodes
from trakdis.modules import NormalizedEncoder, copy_teacher_weights, find_dt_actor, make_dt_actor
from trakdis.objectives import DTDistillationLoss, MaskedOnlineDTLoss
from trakdis.policies import PolicyHandle, load_encoder, load_teacher
from trakdis.training import SnapshotSelection, mixture_shares
from trakdis.transforms import PickerOdometry
from trakdis.transforms.normalization import normalizer_parts, normalizer_with_keys
from trakdis.transforms.visibility import OutOfViewFill
from trakdis.utils import limits
from trakdis.utils.limits import check_option, check_options
from trakdis.utils.logger import latest_run_file
from trakdis.utils.run import Run, RunState

__all__ = [
    "weight_copied_student",
    "check_unseen_picker_mask",
    "load_teacher_and_encoder",
    "student_rollout_steps",
    "weight_copy_scores",
    "weight_copy_race",
    "StudentConfig",
    "DAggerRollouts",
    "StudentEvaluations",
    "distill_state",
]


def weight_copied_student(teacher: PolicyHandle, encoder: nn.Module, *, weight_copy: bool = True,
                          normalizer_keys: tuple[str, ...] = ("state_estimate",), proprio_dims: tuple = (),
                          picker_odometry: bool = False, hold_radius: float = 0.0,
                          device: str = "cpu") -> tuple[PolicyHandle, Any]:
    """The TraKDis student of a loaded ``teacher`` and its :class:`~trakdis.modules.DTModelConfig`.

    A DT of the teacher's sizes reading ``"state_estimate"`` (``encoder``'s estimate from the
    image, run in the acting env), starting as a copy of the teacher's weights (``weight_copy``;
    else fresh weights), acting with the teacher's return-to-go, env options and state statistics
    (a normaliser of ``normalizer_keys``); ``proprio_dims``: dims of the estimate taken from the
    true state when acting; ``picker_odometry``: the estimate's pickers fused with the student's own
    commands (``PickerOdometry``) when acting, with ``hold_radius`` its held corner."""
    dt_cfg = find_dt_actor(teacher.actor).config  # the sizes the teacher's file was checked and built with
    student = make_dt_actor(dt_cfg, observation_key="state_estimate", device=device)
    if weight_copy:
        copy_teacher_weights(student, teacher.actor)
    norm = teacher.normalizer  # its out-of-view fill too (--mask-unseen-pickers): the student reads what the teacher read
    handle = PolicyHandle("student", teacher.task, teacher.horizon, actor=student, encoder=encoder,
                          observation_key="state_estimate", target_return=teacher.target_return,
                          rtg_scale=teacher.rtg_scale, env_kwargs=teacher.env_kwargs,
                          normalizer=None if norm is None else normalizer_with_keys(norm, normalizer_keys),
                          proprio_dims=tuple(proprio_dims), picker_odometry=picker_odometry,
                          hold_radius=hold_radius if picker_odometry else 0.0)
    return handle, dt_cfg


def check_unseen_picker_mask(teacher: PolicyHandle, encoder_file: Mapping[str, Any], *, encoder_source: str) -> bool:
    """Whether ``teacher`` acts on out-of-view-masked states (``online_dt.py --mask-unseen-pickers``:
    its normaliser carries an :class:`~trakdis.transforms.OutOfViewFill`); a ``ValueError`` naming
    both files and the flag unless the encoder (``encoder_file``: an encoder file's dict, read from
    ``encoder_source``; ``train_encoder.py --mask-unseen-pickers`` records ``mask_unseen_pickers``
    and ``out_of_view_fill``) was trained on labels masked the same way."""
    fill = None if teacher.normalizer is None else normalizer_parts(teacher.normalizer)[1]
    encoder_masked = bool(encoder_file.get("mask_unseen_pickers", False))
    if (fill is not None) != encoder_masked:
        def how(masked):
            return "with --mask-unseen-pickers" if masked else "without --mask-unseen-pickers"

        raise ValueError(f"teacher {teacher.source} was trained {how(fill is not None)} (online_dt.py) but encoder "
                         f"{encoder_source} {how(encoder_masked)} (train_encoder.py): the student would read estimates "
                         f"of states the teacher never saw; train both with the same --mask-unseen-pickers")
    if fill is not None and encoder_file.get("out_of_view_fill") is not None:
        theirs = OutOfViewFill.from_dict(encoder_file["out_of_view_fill"])
        same = (theirs.image_size == fill.image_size and theirs.starts == fill.starts
                and torch.allclose(theirs.camera_matrix, fill.camera_matrix) and torch.equal(theirs.fill, fill.fill))
        if not same:
            raise ValueError(f"teacher {teacher.source} and encoder {encoder_source} were trained with "
                             f"--mask-unseen-pickers but different masks ({fill!r} vs {theirs!r})")
    return fill is not None


def load_teacher_and_encoder(teacher: str | Path, encoder: str | Path, *, root: str | Path, device: str = "cpu",
                             max_params: int = limits.MAX_PARAMS,
                             ) -> tuple[PolicyHandle, NormalizedEncoder, dict[str, Any], Path]:
    """``(teacher, encoder, encoder_file, encoder_path)``: the teacher and the encoder a student is
    made of (``distill.py``). ``teacher``: a teacher's policy file or ``online_dt`` run directory;
    ``encoder``: an ``encoder.pt`` or ``train_encoder`` run directory; either ``"latest"``: the newest
    run of that recipe under ``root`` (:func:`~trakdis.utils.logger.latest_run_file`, whose error
    names ``--teacher`` / ``--encoder``). The encoder is loaded for the teacher's task, and both must
    have been trained with ``--mask-unseen-pickers`` or neither (:func:`check_unseen_picker_mask`:
    the teacher's normaliser carries the fill to the student). ``max_params``: the parameter limit of
    both files (:func:`load_policy`)."""
    handle = load_teacher(latest_run_file(str(teacher), root, "online_dt", "policy.pt", flag="--teacher"),
                          device=device, max_params=max_params)
    encoder_path = latest_run_file(str(encoder), root, "train_encoder", "encoder.pt", flag="--encoder")
    module, encoder_file = load_encoder(encoder_path, task=handle.task, max_params=max_params)
    check_unseen_picker_mask(handle, encoder_file, encoder_source=str(encoder_path))
    return handle, module, encoder_file, encoder_path


def student_rollout_steps(teacher: PolicyHandle, encoder: nn.Module, *, episodes: int, seed: int,
                          image_size: int = 32, num_envs: int = 2, parallel: bool = False,
                          label_fill: OutOfViewFill | None = None) -> tuple[TensorDict, dict[str, float]]:
    """``(steps, metrics)``: the ``"pixels"`` and true ``"state"`` of every step of ``episodes``
    train-split episodes of the weight-copied student of ``teacher`` acting on a frozen copy of
    ``encoder``'s estimates (the states the student visits; ``train_encoder.py --teacher``), and how
    they went: ``normalized_performance`` (mean at the episodes' end) and the estimate's error per
    state group (``task_spec(task).state_error_cm``; against the state the teacher reads, its
    out-of-view pickers masked when its normaliser carries a fill). The returned ``"state"`` is raw,
    or masked by ``label_fill`` (the labels of an encoder trained with ``--mask-unseen-pickers``).
    ``parallel``: the ``num_envs`` envs step in worker processes (``ParallelEnv``; the same episodes)."""
    res = _weight_copy_episodes(teacher, encoder, episodes=episodes, seed=seed, image_size=image_size,
                                num_envs=num_envs, parallel=parallel, keep_episodes=True, desc="student rollouts")
    steps = torch.cat([ep.select("pixels", "state", "state_estimate").to_tensordict() for ep in res.episodes])
    fill = None if teacher.normalizer is None else normalizer_parts(teacher.normalizer)[1]
    target = steps["state"] if fill is None else fill.mask(steps["state"])  # what the encoder is trained to output
    err = task_spec(teacher.task, horizon=teacher.horizon).state_error_cm((steps["state_estimate"] - target).abs())
    steps = steps.exclude("state_estimate")
    if label_fill is not None:
        steps.set("state", label_fill.mask(steps["state"]))
    return steps, {"normalized_performance": float(res.final_performance.mean()), **err}


def weight_copy_scores(teacher: PolicyHandle, encoder: nn.Module, *, episodes: int, seed: int, image_size: int = 32,
                       num_envs: int = 2, parallel: bool = False) -> np.ndarray:
    """The final normalized performance ``[episodes]`` of ``episodes`` train-split episodes (configurations
    drawn with ``seed``: the same for every encoder) of the weight-copied student of ``teacher`` acting on
    a frozen copy of ``encoder``'s estimates: how well the teacher's weights fold with this encoder
    (``train_encoder.py --select-episodes``, a selection among encoders). ``parallel``: as in
    :func:`student_rollout_steps`."""
    res = _weight_copy_episodes(teacher, encoder, episodes=episodes, seed=seed, image_size=image_size,
                                num_envs=num_envs, parallel=parallel, keep_episodes=False, desc="weight copy")
    return np.asarray(res.final_performance, dtype=np.float64)


def weight_copy_race(teacher: PolicyHandle, encoders: Sequence[nn.Module], *, episodes: int, seed: int,
                     chunk: int = 10, margin: float = 2.0, image_size: int = 32, num_envs: int = 2,
                     parallel: bool = False, on_chunk: Callable[[dict, list], None] | None = None,
                     ) -> dict[int, np.ndarray]:
    """:func:`weight_copy_scores` of each of ``encoders``, raced: they play the episodes in chunks of
    ``chunk`` (0: all at once), and after each chunk an encoder whose weight copy's mean is below the
    leader's by more than ``margin`` standard errors of their paired difference plays no more
    (:func:`~trakdis.evaluation.race_survivors`). Each plays in its own
    :class:`~trakdis.evaluation.EpisodeStream`, so an encoder's scores are the first episodes of its
    :func:`weight_copy_scores` (all of them for those that finish). ``on_chunk(scores, survivors)``
    after each chunk. Returns ``{index: scores of the episodes it played}``."""
    if episodes < 1 or chunk < 0:
        raise ValueError(f"weight_copy_race: episodes ({episodes}) must be >= 1 and chunk ({chunk}) >= 0")
    scores: dict[int, list[float]] = {k: [] for k in range(len(encoders))}
    alive, played, streams = list(scores), 0, {}  # streams: index -> (its stream, its env)

    def stop(k: int) -> None:
        stream, env = streams.pop(k)
        stream.close()
        close_env(env)

    try:
        while alive and played < episodes:
            n = min(chunk or episodes, episodes - played)
            for k in alive:
                if k not in streams:  # its configurations drawn with seed, as weight_copy_scores draws them
                    handle, env = _weight_copy_env(teacher, encoders[k], num_envs=num_envs, parallel=parallel,
                                                   image_size=image_size)
                    streams[k] = EpisodeStream(env, handle.make_policy(), max_steps=teacher.horizon, seed=seed), env
                scores[k] += [episode_score(next(streams[k][0])) for _ in range(n)]
            played += n
            if played < episodes:
                alive = race_survivors({k: scores[k] for k in alive}, margin=margin)
                for k in set(streams) - set(alive):
                    stop(k)
            if on_chunk is not None:
                on_chunk(scores, list(alive))
    finally:
        for k in list(streams):
            stop(k)
    return {k: np.asarray(v, dtype=np.float64) for k, v in scores.items()}


def _weight_copy_env(teacher: PolicyHandle, encoder: nn.Module, *, num_envs: int, parallel: bool, image_size: int):
    """The weight-copied student of ``teacher`` on a frozen copy of ``encoder``, and its train-split env."""
    handle, _ = weight_copied_student(teacher, copy.deepcopy(encoder).cpu().eval())
    return handle, handle.make_env(num_envs=num_envs, parallel=parallel, split="train", image_size=image_size)


def _weight_copy_episodes(teacher: PolicyHandle, encoder: nn.Module, *, episodes: int, seed: int, image_size: int,
                          num_envs: int, parallel: bool, keep_episodes: bool, desc: str):
    handle, env = _weight_copy_env(teacher, encoder, num_envs=num_envs, parallel=parallel, image_size=image_size)
    try:
        return run_episodes(env, handle.make_policy(), episodes, max_steps=teacher.horizon, keep_episodes=keep_episodes,
                            seed=seed, desc=desc)
    finally:
        close_env(env)


# --------------------------------------------------------------------------- distillation (distill.py)
@dataclass
class StudentConfig:
    """The student and what it learns from (a base of ``distill.py``'s config dataclass, so the flags stay
    ``--weight-copy``, ``--distill``, ``--act``, ...): its starting point and inputs, its labels (the
    teacher's, or with ``--no-distill`` the expert data's own actions), its data (the expert dataset
    through the encoder, the rollouts of ``--act``'s policies) and its loss."""

    weight_copy: bool = True
    """initialise the student with the teacher's weights (--no-weight-copy: fresh weights, never kept by the
    selection; No-Pretrain, with --no-distill the paper's No-Distill)"""
    distill: bool = True  # learn from the teacher's actions (--no-distill: imitate the expert dataset instead)
    estimate_noise: float = 0.0
    """std of Gaussian noise on the estimated state of every training window (robustness)"""
    SAVED_AS: ClassVar[dict] = {"state_noise": "estimate_noise"}  # the option's earlier name (--state-noise)
    proprio_pickers: bool = False  # the student's picker positions from proprioception (the true state), not the encoder
    picker_odometry: Literal["auto", "on", "off"] = "auto"
    """the encoder's picker estimates fused with the student's own commands (no proprioception); auto: on if the data's
    actions are the executed ones (measured on the three tasks over 3 seeds each: docs/recipes/distill.md)"""
    hold_radius: Optional[float] = None
    """with the picker odometry: a close within this distance (metres) of the source corner, as estimated, holds the
    corner's estimate at the picker's while it stays closed (PickerOdometry; default: per task, as measured in
    docs/recipes/distill.md; 0: off)"""
    act: Literal["student", "teacher", "mixed"] = "teacher"  # who acts in the rollouts (student: DAgger; mixed: decaying)
    teacher_context: Literal["window", "step"] = "window"  # what the teacher reads to label a step: window or step alone
    expert_data: bool = True  # distil on the expert dataset's episodes (--data.*): images through the encoder
    episodes_per_round: int = 0  # episodes rolled out per round into the distillation data (0: the expert data only)
    loss_function: Literal["nll", "mse"] = "nll"  # the student's NLL of the teacher's action (paper), or squared error
    grasp_labels: Literal["probability", "decision"] = "probability"
    """with a grasp head, the teacher's grasps as labels: its probabilities (both movement branches, weighted by
    them) or each step's more likely grasp (the movement of its branch)"""
    return_to_go: Literal["acting", "hindsight"] = "acting"  # rollouts' return-to-go: the acting countdown, or reached
    kl_coef: float = 0.0  # weight of an extra teacher-student KL term (0: the paper's NLL only)
    expert_coef: Optional[float] = None
    """weight of the student's NLL of the expert's own actions beside the teacher's, on the expert data (knowledge
    distillation's hard labels; 0: the paper's loss, the teacher's actions alone; default: per task, as measured in
    docs/recipes/distill.md; 0 wherever the data has rollouts)"""
    data: DataConfig = field(default_factory=DataConfig)  # expert dataset for --no-distill and --expert-data

    def __post_init__(self):  # checked while parsing, before the run directory exists
        if self.episodes_per_round < 0 or (self.distill and self.episodes_per_round == 0 and not self.expert_data):
            raise ValueError(f"--episodes-per-round {self.episodes_per_round}: distillation needs rollouts (>= 1) "
                             "or --expert-data")
        if self.expert_coef is not None and not self.expert_coef >= 0:  # also NaN
            raise ValueError(f"--expert-coef {self.expert_coef}: must be >= 0")
        if self.expert_coef and not self.expert_actions:
            raise ValueError(f"--expert-coef {self.expert_coef}: the expert's actions exist on the expert data alone "
                             "(--expert-data, --episodes-per-round 0, with distillation)")
        if self.picker_odometry == "on" and not self.proprio_pickers and self.data.action_labels != "executed":
            raise ValueError(f"--picker-odometry integrates the executed actions: --data.action-labels "
                             f"{self.data.action_labels!r} needs 'executed'")
        check_options(self, nonnegative=("estimate_noise", "kl_coef"))
        if self.hold_radius is not None:
            check_option("hold_radius", self.hold_radius, ge=0, lt=1)
        if self.hold_radius and not self.odometry:
            raise ValueError(f"--hold-radius {self.hold_radius}: the held corner is part of the picker odometry, "
                             f"which is off here (--picker-odometry {self.picker_odometry}"
                             f"{', --proprio-pickers' if self.proprio_pickers else ''})")
        parent = getattr(super(), "__post_init__", None)
        if parent is not None:
            parent()

    @property
    def odometry(self) -> bool:
        """Whether the student's pickers are fused with its commands: --picker-odometry, auto resolved to on where the
        data's actions are the executed ones; never with --proprio-pickers (they give the pickers outright)."""
        auto = self.picker_odometry == "auto" and self.data.action_labels == "executed"
        return (self.picker_odometry == "on" or auto) and not self.proprio_pickers

    def resolved_hold_radius(self, task: str) -> float:
        """``--hold-radius``, or unset the task's ``TaskDefaults.hold_radius``; 0 without the picker odometry."""
        if not self.odometry:
            return 0.0
        return self.hold_radius if self.hold_radius is not None else task_defaults(task).hold_radius

    @property
    def expert_actions(self) -> bool:
        """Whether every distillation window holds the expert's own actions (the expert data, no rollouts)."""
        return self.distill and self.expert_data and self.episodes_per_round == 0

    @property
    def relabel_return_to_go(self) -> bool:
        """Whether the buffer recomputes the return-to-go of the episodes it stores from their rewards (hindsight):
        the expert data's (with --no-distill or --expert-data) and, with --return-to-go hindsight, the rollouts'."""
        return not self.distill or self.expert_data or self.return_to_go == "hindsight"

    def resolved_expert_coef(self, task: str) -> float:
        """``--expert-coef``, or unset the task's ``TaskDefaults.expert_coef`` where the windows hold the expert's
        own actions (else 0)."""
        if self.expert_coef is not None:
            return self.expert_coef
        return task_defaults(task).expert_coef if self.expert_actions else 0.0

    def proprio_dims(self, task: str) -> tuple[int, ...]:
        """The state dims the student reads from proprioception, the true state (``--proprio-pickers``: the
        pickers'; else none)."""
        pickers = task_spec(task).state_groups["pickers"]
        return tuple(range(pickers.start, pickers.stop)) if self.proprio_pickers else ()

    def make_student(self, teacher: PolicyHandle, encoder: nn.Module, *, device: str = "cpu") -> tuple[PolicyHandle, Any]:
        """:func:`weight_copied_student` of ``teacher`` on ``encoder``'s estimates with these options: the
        teacher's weights (``--weight-copy``), its statistics standardising both the true ``"state"`` and the
        ``"state_estimate"`` (the encoder's estimates live in state units), :meth:`proprio_dims` and
        :attr:`odometry` with :meth:`resolved_hold_radius`."""
        return weight_copied_student(teacher, encoder, weight_copy=self.weight_copy, device=device,
                                     normalizer_keys=("state", "state_estimate"),
                                     proprio_dims=self.proprio_dims(teacher.task), picker_odometry=self.odometry,
                                     hold_radius=self.resolved_hold_radius(teacher.task))

    def make_loss(self, student: nn.Module, teacher_actor: nn.Module, *, action_eps: float,
                  expert_coef: float = 0.0) -> nn.Module:
        """The student's loss: :class:`~trakdis.objectives.DTDistillationLoss` of the frozen ``teacher_actor``'s
        actions (``--loss-function``, ``--grasp-labels``, ``--kl-coef``, ``--teacher-context``; ``expert_coef``: the
        weight of the expert's own actions beside them), or with ``--no-distill``
        :class:`~trakdis.objectives.MaskedOnlineDTLoss` of the expert data's actions without the entropy bonus."""
        if self.distill:
            return DTDistillationLoss(student, teacher_actor, kl_coef=self.kl_coef, loss_function=self.loss_function,
                                      action_eps=action_eps, teacher_context=self.teacher_context,
                                      expert_coef=expert_coef, grasp_labels=self.grasp_labels)
        return MaskedOnlineDTLoss(student, lambda_entropy=0.0, action_eps=action_eps)

    def load_expert_data(self, buffer: TrajectoryReplayBuffer, encoder: nn.Module, teacher: PolicyHandle, *, seed: int,
                         log: Callable[[str], None] = print, progress: bool = True) -> None:
        """With ``--no-distill`` (the expert's actions as targets) or ``--expert-data`` (the teacher's labels on
        their true states): the expert dataset's episodes into ``buffer``, their images through the frozen
        ``encoder`` (:func:`~trakdis.data.load_encoded_dataset`), with :attr:`odometry` its picker estimates fused
        with the recorded actions, as the student reads them when acting. Otherwise nothing."""
        if self.distill and not self.expert_data:
            return
        keys = ("action", "reward", *(("state",) if self.proprio_pickers or self.distill else ()))
        data, lengths, path = load_encoded_dataset(self.data, encoder, task=teacher.task, horizon=teacher.horizon,
                                                   seed=seed, keys=keys, log=log, progress=progress)
        if self.odometry:  # what the student reads when acting: the fused pickers
            fuse = PickerOdometry.for_task(teacher.task, teacher.env_kwargs,
                                           hold_radius=self.resolved_hold_radius(teacher.task))
            data.set("state_estimate", fuse.filter(data["state_estimate"], data["action"]))
        buffer.load_offline(data, lengths)
        log(f"{'--expert-data' if self.distill else '--no-distill'}: {data.shape[0]} expert episodes from {path}")

    def acting_policies(self, teacher: PolicyHandle, student: PolicyHandle, encoder: nn.Module) -> list[PolicyHandle]:
        """The policies whose episodes a round rolls out (``--act``; none without distillation or rollouts): the
        teacher, its rollouts carrying the encoder's estimate too (fused the student's way), the student, or both
        (DAgger's decaying mixture: :class:`DAggerRollouts`)."""
        if not (self.distill and self.episodes_per_round):
            return []
        estimating = dataclasses.replace(teacher, encoder=encoder, picker_odometry=self.odometry,
                                         hold_radius=self.resolved_hold_radius(teacher.task))
        return {"teacher": [estimating], "student": [student], "mixed": [estimating, student]}[self.act]


@dataclass
class DAggerRollouts:
    """A :func:`~trakdis.training.train_rounds` ``roll_out`` of distillation: round ``r`` plays ``episodes``
    episodes (mean actions, train split) of each of ``handles`` in its env of ``envs``, reseeded with ``seed +
    1000 (r + 1) + 100 i`` for the ``i``-th, and adds their true and estimated states, actions and
    return-to-go to ``buffer``. ``mixed`` (two handles, the teacher's and the student's): DAgger's decaying
    mixture, the round's episodes shared between them by :func:`~trakdis.training.mixture_shares` over
    ``rounds``. Logs ``rollout/<kind>_normalized_performance`` of each and ``round`` = ``r + 1``."""

    handles: Sequence[PolicyHandle]
    envs: Sequence[Any]
    buffer: TrajectoryReplayBuffer
    episodes: int
    rounds: int
    horizon: int
    seed: int
    collector: CollectorName = "sync"
    mixed: bool = False

    def __call__(self, r: int) -> tuple[dict[str, Any], str]:
        metrics, parts = {}, []
        shares = mixture_shares(self.episodes, r, self.rounds) if self.mixed else [self.episodes]
        for i, (handle, n) in enumerate(zip(self.handles, shares)):
            if n > 0:
                res = run_episodes(self.envs[i], handle.make_policy(), n, max_steps=self.horizon, deterministic=True,
                                   keep_episodes=True, desc=f"rollout ({handle.kind})", collector=self.collector,
                                   seed=self.seed + 1000 * (r + 1) + 100 * i)
                self.buffer.add_episodes(res.episodes, keys=("state", "state_estimate", "action", "return_to_go"))
                metrics[f"rollout/{handle.kind}_normalized_performance"] = float(res.final_performance.mean())
                parts.append(f"rollout ({handle.kind}) {res.final_performance.mean():.3f}")
        return {**metrics, "round": r + 1}, ", ".join(parts)


def distill_state(run: Run, updater: Any, buffer: TrajectoryReplayBuffer) -> RunState:
    """The resume state of a distillation run: its counters ``rounds`` and ``updates`` (the step), the
    evaluations' means (:class:`StudentEvaluations`), with the states of ``updater`` and ``buffer``."""
    return RunState(run, {"rounds": 0, "updates": 0, **StudentEvaluations.counters()}, step_key="updates",
                    updater=updater, buffer=buffer)


class StudentEvaluations:
    """The evaluations of a distillation run, on the eval episodes of ``protocol`` (an
    :class:`~trakdis.evaluation.EvalProtocol`; none when it plays 0 episodes) in ``env``, logged at
    ``state["updates"]``: the student (``handle``, a :class:`~trakdis.policies.PolicyHandle`) with the
    encoder's error on the states it visits (:meth:`__call__`), before training (:meth:`initial`), every
    few rounds (:meth:`after_round`) and at the end (:meth:`final`: the kept snapshot's), and the teacher
    (:meth:`teacher`). Their means live in ``state`` (:meth:`counters`: ``teacher_eval``, ``initial_eval``,
    ``round_evals`` by round, ``final_eval``), so a resumed run plays none of them again."""

    def __init__(self, run: Run, protocol: Any, handle: PolicyHandle, env: Any, state: RunState):
        self.run, self.protocol, self.handle, self.env, self.state = run, protocol, handle, env, state

    @staticmethod
    def counters() -> dict[str, Any]:
        """The state's entries of the evaluations, none done yet (``final_eval`` is set by :meth:`final`)."""
        return {"initial_eval": None, "teacher_eval": None, "round_evals": {}}

    def __call__(self, tag: str, prefix: str = "eval") -> float | None:
        """The student now: its mean normalized performance (None: no evaluation episodes)."""
        if not self.protocol.episodes:
            return None
        return self.protocol.run(self.run, self.handle, self.env, step=self.state["updates"], tag=tag, prefix=prefix,
                                 keep_mode=self.handle.actor,
                                 state_error_cm=task_spec(self.handle.task).state_error_cm).summary()["mean"]

    def teacher(self, teacher: PolicyHandle, *, parallel: bool = False) -> None:
        """The teacher on the same episodes, unless done, on its own env, closed afterwards
        (:meth:`~trakdis.evaluation.EvalProtocol.run_snapshot`)."""
        if self.protocol.episodes and self.state["teacher_eval"] is None:
            self.state["teacher_eval"] = self.protocol.run_snapshot(
                self.run, teacher, step=self.state["updates"], tag="teacher", prefix="eval_teacher", parallel=parallel,
                keep_mode=self.handle.actor, desc="eval (teacher)").summary()["mean"]

    def initial(self) -> None:
        """The student before training (the weight copy), unless done."""
        if self.state["initial_eval"] is None:
            self.state["initial_eval"] = self("student before training")

    def after_round(self, r: int) -> None:
        """The student after round ``r`` (:func:`~trakdis.training.train_rounds`' ``evaluate``), kept by round."""
        self.state["round_evals"][r] = self(f"student after round {r}")

    def final(self, rounds: int, selection: SnapshotSelection | None = None) -> float | None:
        """The run's final score, ``state["final_eval"]``: the student after the last of ``rounds`` (the curve's
        last point; ``rounds`` 0: the weights did not change, the initial evaluation stands), then, with a
        ``selection``, the kept snapshot's (:meth:`~trakdis.training.SnapshotSelection.finish` restores it):
        its evaluation on the curve where there is one (logged again as ``eval_kept/`` at this step), else
        evaluated afresh as ``eval_kept/``."""
        final = self("student after distillation") if rounds > 0 else self.state["initial_eval"]
        if selection is not None:
            best = selection.finish(rounds, self.run.print)
            if best != rounds and self.protocol.episodes:
                final = self.state["initial_eval"] if best == 0 else self.state["round_evals"].get(best)
                if final is None:
                    final = self(f"the kept student (round {best})", prefix="eval_kept")
                else:
                    self.run.log(self.state["updates"], {"eval_kept/normalized_performance": final})
                    self.run.print(f"the kept student (round {best}): its evaluation on the curve, {final:.3f}")
        self.state["final_eval"] = final
        return final

    def report(self) -> str:
        """The printed line of the teacher's, the initial and the final evaluation."""
        scores = [f"{k} {'not evaluated' if self.state[v] is None else format(self.state[v], '.3f')}"
                  for k, v in (("teacher", "teacher_eval"), ("student before", "initial_eval"), ("after", "final_eval"))]
        return f"eval normalized performance: {', '.join(scores)} ({self.protocol.episodes} episodes)"
