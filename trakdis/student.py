"""The TraKDis student: the teacher's Decision Transformer reading an encoder's estimates from the image.

Its parts loaded and checked together (:func:`load_teacher_and_encoder`, :func:`check_unseen_picker_mask`),
the student made of them (:func:`weight_copied_student`: ``distill.py``'s starting point), and the episodes
of that weight copy: the states it visits, on which ``train_encoder.py --teacher`` trains the encoder
(:func:`student_rollout_steps`), and its scores, by which ``train_encoder.py --select-episodes`` chooses among
encoders (:func:`weight_copy_scores`, raced: :func:`weight_copy_race`).

Above :mod:`trakdis.evaluation` (it plays episodes) and :mod:`trakdis.policies` (it builds on loaded policies).
"""
from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch
from tensordict import TensorDict
from torch import nn

from trakdis.envs import close_env, task_spec
from trakdis.evaluation import EpisodeStream, episode_score, race_survivors, run_episodes
from trakdis.modules import NormalizedEncoder, copy_teacher_weights, find_dt_actor, make_dt_actor
from trakdis.policies import PolicyHandle, load_encoder, load_teacher
from trakdis.transforms.normalization import normalizer_parts, normalizer_with_keys
from trakdis.transforms.visibility import OutOfViewFill
from trakdis.utils import limits
from trakdis.utils.logger import latest_run_file

__all__ = [
    "weight_copied_student",
    "check_unseen_picker_mask",
    "load_teacher_and_encoder",
    "student_rollout_steps",
    "weight_copy_scores",
    "weight_copy_race",
]


def weight_copied_student(teacher: PolicyHandle, encoder: nn.Module, *, weight_copy: bool = True,
                          normalizer_keys: tuple[str, ...] = ("state_estimate",), proprio_dims: tuple = (),
                          picker_odometry: bool = False, device: str = "cpu") -> tuple[PolicyHandle, Any]:
    """The TraKDis student of a loaded ``teacher`` and its :class:`~trakdis.modules.DTModelConfig`.

    A DT of the teacher's sizes reading ``"state_estimate"`` (``encoder``'s estimate from the
    image, run in the acting env), starting as a copy of the teacher's weights (``weight_copy``;
    else fresh weights), acting with the teacher's return-to-go, env options and state statistics
    (a normaliser of ``normalizer_keys``); ``proprio_dims``: dims of the estimate taken from the
    true state when acting; ``picker_odometry``: the estimate's pickers fused with the student's own
    commands (``PickerOdometry``) when acting."""
    dt_cfg = find_dt_actor(teacher.actor).config  # the sizes the teacher's file was checked and built with
    student = make_dt_actor(dt_cfg, observation_key="state_estimate", device=device)
    if weight_copy:
        copy_teacher_weights(student, teacher.actor)
    norm = teacher.normalizer  # its out-of-view fill too (--mask-unseen-pickers): the student reads what the teacher read
    handle = PolicyHandle("student", teacher.task, teacher.horizon, actor=student, encoder=encoder,
                          observation_key="state_estimate", target_return=teacher.target_return,
                          rtg_scale=teacher.rtg_scale, env_kwargs=teacher.env_kwargs,
                          normalizer=None if norm is None else normalizer_with_keys(norm, normalizer_keys),
                          proprio_dims=tuple(proprio_dims), picker_odometry=picker_odometry)
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
