"""A loaded policy and its acting environment.

:func:`load_policy` turns a policy file (read and checked by
:func:`~trakdis.policies.files.read_policy_file`), or the string ``"expert"`` (the scripted expert),
into a :class:`PolicyHandle` that builds its acting environment (:func:`make_acting_env`: batched
over ``num_envs``, with the return-to-go countdown, the frozen encoder and optional state noise) and
its acting module; :meth:`PolicyHandle.save` writes a Decision Transformer's policy file.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from torch import nn
from torchrl.envs import Compose, ObservationNorm, TransformedEnv

from trakdis.envs import ExpertPolicy, make_batched_env
from trakdis.modules import DTActingPolicy, NormalizedPolicy
from trakdis.transforms import EncoderTransform, ImageResize, PickerOdometry, ReturnToGo, StateNoise
from trakdis.transforms.normalization import ProprioceptionOverride
from trakdis.utils import limits
from trakdis.utils.checkpoint import FileFormatError

from .files import IMAGE_POLICY_KINDS, read_policy_file, save_policy

__all__ = ["make_acting_env", "PolicyHandle", "load_policy", "load_teacher"]


# --------------------------------------------------------------------------- acting environments
def make_acting_env(task: str, *, target_return: float | None = None, rtg_scale: float = 1.0,
                    encoder: nn.Module | None = None, state_noise: float = 0.0, noise_seed: int | None = None,
                    video_size: int | None = None, encoder_key: str = "state_estimate", picker_odometry: bool = False,
                    hold_radius: float = 0.0, **batched_kwargs):
    """A batched env with the acting transforms of a DT policy.

    ``encoder`` (student): ``EncoderTransform`` writes ``"state_estimate"`` from ``"pixels"``
    (pixels are switched on); ``state_noise`` adds Gaussian noise to ``"state_estimate"``
    (``"state"`` for a teacher); ``target_return`` adds the ``ReturnToGo`` countdown.
    ``picker_odometry`` (with an encoder): ``PickerOdometry`` fuses the estimate's pickers with the
    actions sent, before the noise; ``hold_radius`` > 0 (with it): a picker that closes that near its
    source corner holds the corner's estimate at its own (``PickerOdometry``'s held corner).
    ``encoder_key``: where the encoder writes (an image baseline's trunk: ``"image_features"``;
    the state noise then goes there too).

    ``video_size``: render ``"pixels"`` at this size (for videos) and write the agent's view,
    resized to ``image_size``, to ``"pixels_agent"`` (which the encoder then reads). A resized
    large render is close to, but not bit-identical with, a native small render.
    """
    if not (math.isfinite(state_noise) and state_noise >= 0):  # -1 or nan were skipped silently
        raise ValueError(f"state_noise must be a finite std >= 0, got {state_noise!r}")
    agent_key, agent_size = "pixels", batched_kwargs.get("image_size", 32)  # what the encoder reads
    transforms = []
    if video_size is not None:
        batched_kwargs.update(from_pixels=True, image_size=int(video_size))
        agent_key = "pixels_agent"
        transforms.append(ImageResize(in_keys=["pixels"], out_keys=[agent_key], size=agent_size))
    if encoder is not None:
        batched_kwargs["from_pixels"] = True
    env = make_batched_env(task, **batched_kwargs)
    if encoder is not None:
        transforms.append(EncoderTransform(encoder, in_keys=[agent_key], out_keys=[encoder_key]))
        if picker_odometry:
            transforms.append(PickerOdometry.for_task(task, batched_kwargs.get("env_kwargs"), in_keys=[encoder_key],
                                                      image_size=agent_size, hold_radius=hold_radius))
    elif picker_odometry:
        raise ValueError("picker_odometry fuses an encoder's estimates: it needs an encoder")
    if hold_radius and not (encoder is not None and picker_odometry):
        raise ValueError(f"hold_radius {hold_radius}: the held corner is part of the picker odometry (picker_odometry "
                         "with an encoder)")
    if state_noise > 0:
        key = encoder_key if encoder is not None else "state"
        transforms.append(StateNoise(state_noise, in_keys=[key], seed=noise_seed))
    if target_return is not None:
        transforms.append(ReturnToGo(target_return, rtg_scale=rtg_scale))
    return TransformedEnv(env, Compose(*transforms)) if transforms else env


# --------------------------------------------------------------------------- loaded policies
@dataclass
class PolicyHandle:
    """A loaded policy: ``kind`` in ``{"expert", "teacher", "student", "bc_image", "dt_image"}``.

    The image baselines (``"bc_image"``, ``"dt_image"``) hold their CNN trunk as ``encoder`` (run in
    the env by ``EncoderTransform``, writing ``observation_key`` = ``"image_features"``) and their
    head as ``actor`` (``bc_image``: a TanhNormal actor on the features; ``dt_image``: a DT actor,
    acted with ``DTActingPolicy`` like a teacher or student)."""

    kind: str
    task: str
    horizon: int
    actor: nn.Module | None = None
    encoder: nn.Module | None = None
    observation_key: str = "state"
    target_return: float = -1.0
    rtg_scale: float = 1.0
    expert_noise: float = 0.0
    env_kwargs: dict = field(default_factory=dict)
    source: str = ""
    normalizer: ObservationNorm | Compose | None = None
    """standardisation of the observation the DT reads (a state normaliser,
    :func:`~trakdis.transforms.state_normalizer`; None: raw)"""
    proprio_dims: tuple = ()
    """dims of the student's estimate taken from the true state (picker positions), if any"""
    picker_odometry: bool = False
    """the student's picker estimates fused with its own commands (``PickerOdometry`` in its env)"""
    hold_radius: float = 0.0
    """with ``picker_odometry``: a close this near (metres) to the source corner holds the corner's estimate at the
    picker's (``PickerOdometry``'s held corner; 0: off)"""

    @property
    def uses_pixels(self) -> bool:
        return self.encoder is not None

    def make_env(self, *, num_envs: int = 1, split: str = "eval", seed: int | None = None, state_noise: float = 0.0,
                 noise_seed: int | None = None,
                 parallel: bool = False, from_pixels: bool | None = None, image_size: int = 32,
                 target_return: float | None = None, video_size: int | None = None):
        """The acting env of this policy (pixels on for a student, or when ``from_pixels``)."""
        is_dt = self.kind not in ("expert", "bc_image")
        odometry = self.picker_odometry and self.encoder is not None
        return make_acting_env(
            self.task,
            target_return=(self.target_return if target_return is None else target_return) if is_dt else None,
            rtg_scale=self.rtg_scale, encoder=self.encoder, state_noise=state_noise,
            noise_seed=noise_seed if noise_seed is not None else (None if seed is None else seed + 7919),
            num_envs=num_envs, parallel=parallel, seed=seed, split=split,
            from_pixels=bool(from_pixels) or self.uses_pixels, image_size=image_size,
            env_kwargs={**self.env_kwargs, "horizon": self.horizon}, video_size=video_size,
            picker_odometry=odometry, hold_radius=self.hold_radius if odometry else 0.0,
            **({"encoder_key": self.observation_key} if self.kind in IMAGE_POLICY_KINDS else {}),
        )

    def make_policy(self, *, seed: int | None = None):
        """A TensorDict module writing ``"action"``: the DT acting wrapper, or the scripted expert."""
        if self.kind == "expert":
            return ExpertPolicy(self.task, noise=self.expert_noise, seed=seed)
        if self.kind == "bc_image":  # stateless: the actor on the env's image features
            return self.actor.eval()
        self.actor.eval()
        policy = DTActingPolicy(self.actor, observation_key=self.observation_key)
        pre = ProprioceptionOverride(self.proprio_dims) if self.proprio_dims else None
        if self.normalizer is None and pre is None:
            return policy
        return NormalizedPolicy(policy, self.normalizer, self.observation_key, pre=pre)

    def save(self, path: str | Path, dt_config, *, encoder_file: Mapping[str, Any] | None = None,
             extra: Mapping[str, Any] | None = None) -> Path:
        """Write this Decision Transformer policy (teacher or student) with :func:`~trakdis.policies.save_policy`, from
        the handle's own fields; ``dt_config``: its actor's :class:`~trakdis.modules.DTModelConfig`."""
        return save_policy(path, kind=self.kind, task=self.task, horizon=self.horizon, dt_config=dt_config,
                           actor=self.actor, observation_key=self.observation_key, target_return=self.target_return,
                           rtg_scale=self.rtg_scale, normalizer=self.normalizer, env_kwargs=self.env_kwargs,
                           encoder_file=encoder_file, extra=extra)


def load_policy(spec: str | Path, *, task: str | None = None, horizon: int | None = None,
                expert_noise: float = 0.0, device: str = "cpu", max_params: int = limits.MAX_PARAMS,
                max_activation_bytes: int = limits.MAX_ACTIVATION_BYTES) -> PolicyHandle:
    """``"expert"`` or the path of a policy file (or of a run directory holding ``policy.pt``);
    ``horizon``: the episode length it acts for (None: the file's).

    A file is untrusted input, read by :func:`~trakdis.policies.files.read_policy_file`: it must hold
    only the entries trakdis writes, each of its type and range, and describe models of at most
    ``max_params`` parameters and ``max_activation_bytes`` of activations per acting window (raise
    them for a larger policy you trust). Anything else is a
    :class:`~trakdis.utils.checkpoint.FileFormatError` naming the file and the entry."""
    if horizon is not None and not (limits.is_int(horizon) and 1 <= horizon <= limits.MAX_HORIZON):
        raise ValueError(f"horizon must be >= 1 (an int, at most {limits.MAX_HORIZON}; None: the policy's own), "
                         f"got {horizon!r}")
    if str(spec) == "expert":
        if task is None:
            raise ValueError("the expert policy needs --task")
        return PolicyHandle("expert", task, 100 if horizon is None else horizon, expert_noise=expert_noise, source="expert")
    fields = read_policy_file(spec, task=task, device=device, max_params=max_params,
                              max_activation_bytes=max_activation_bytes)
    if horizon is not None:
        fields["horizon"] = horizon
    return PolicyHandle(**fields)


def load_teacher(spec: str | Path, *, task: str | None = None, horizon: int | None = None,
                 device: str = "cpu", **limits_kw: int) -> PolicyHandle:
    """:func:`load_policy` of a teacher's policy file (or run directory); a file of another kind, or
    a teacher for another ``task`` or ``horizon`` (each checked when given), is a
    :class:`~trakdis.utils.checkpoint.FileFormatError`."""
    teacher = load_policy(spec, device=device, **limits_kw)
    if teacher.kind != "teacher" or task not in (None, teacher.task) or horizon not in (None, teacher.horizon):
        expected = "".join([f" for {task}" if task else "", f" (horizon {horizon})" if horizon else ""])
        raise FileFormatError(f"{teacher.source}: a {teacher.kind} for {teacher.task} (horizon {teacher.horizon}); "
                              f"expected a teacher{expected}")
    return teacher
