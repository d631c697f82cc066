"""Saved policies: policy files, encoder files, and a loaded policy's acting environment.

A *policy file* (``policy.pt``, written by ``online_dt.py`` and ``distill.py``) is a checkpoint
dict holding everything needed to act without the recipe's config:

``kind`` (``"teacher"`` / ``"student"``), ``task``, ``horizon``, ``dt_config`` (a
:class:`~trakdis.modules.DTConfig` dict), ``observation_key``, ``actor`` (state dict),
``target_return`` and ``rtg_scale`` (acting return-to-go), ``env_kwargs``, ``normalizer`` (a
:class:`~trakdis.transforms.StateNormalizer` state, or None) and, for a student, ``encoder`` (an
encoder file's dict, see :func:`save_encoder`). The image baselines' files (kinds ``bc_image`` /
``dt_image``, :func:`save_image_policy`) hold their CNN trunk and head instead.

:func:`load_policy` turns a policy file, or the string ``"expert"`` (the scripted expert), into
a :class:`PolicyHandle` that builds its acting environment (:func:`make_acting_env`: batched over
``num_envs``, with the return-to-go countdown, the frozen encoder and optional state noise) and
its acting module.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch
from tensordict import TensorDict
from torch import nn

from trakdis.envs.batched import make_batched_env
from trakdis.envs.model import render_version
from trakdis.modules.encoder import EncoderEnsemble
from trakdis.modules.normalized import NormalizedEncoder, NormalizedPolicy
from trakdis.transforms.normalization import ProprioceptionOverride, StateNormalizer
from trakdis.transforms.visibility import OutOfViewFill
from trakdis.utils import limits
from trakdis.utils.checkpoint import CheckpointError, load_checkpoint, save_checkpoint

__all__ = [
    "make_acting_env",
    "PolicyHandle",
    "load_policy",
    "load_teacher",
    "save_policy",
    "save_encoder",
    "load_encoder",
    "encoder_from_dict",
    "check_render_version",
    "IMAGE_POLICY_KINDS",
    "save_image_policy",
    "weight_copied_student",
    "student_rollout_steps",
    "weight_copy_race",
    "weight_copy_scores",
    "check_unseen_picker_mask",
    "load_teacher_and_encoder",
]


# --------------------------------------------------------------------------- acting environments
def make_acting_env(task: str, *, target_return: float | None = None, rtg_scale: float = 1.0,
                    encoder: nn.Module | None = None, state_noise: float = 0.0, noise_seed: int | None = None,
                    video_size: int | None = None, encoder_key: str = "state_estimate", picker_odometry: bool = False,
                    **batched_kwargs):
    """A batched env with the acting transforms of a DT policy.

    ``encoder`` (student): ``EncoderTransform`` writes ``"state_estimate"`` from ``"pixels"``
    (pixels are switched on); ``state_noise`` adds Gaussian noise to ``"state_estimate"``
    (``"state"`` for a teacher); ``target_return`` adds the ``ReturnToGo`` countdown.
    ``picker_odometry`` (with an encoder): ``PickerOdometry`` fuses the estimate's pickers with the
    actions sent, before the noise.
    ``encoder_key``: where the encoder writes (an image baseline's trunk: ``"image_features"``;
    the state noise then goes there too).

    ``video_size``: render ``"pixels"`` at this size (for videos) and write the agent's view,
    resized to ``image_size``, to ``"pixels_agent"`` (which the encoder then reads). A resized
    large render is close to, but not bit-identical with, a native small render.
    """
    from torchrl.envs import Compose, TransformedEnv

    from trakdis.transforms import EncoderTransform, ImageResize, PickerOdometry, ReturnToGo, StateNoise

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
                                                      image_size=agent_size))
    elif picker_odometry:
        raise ValueError("picker_odometry fuses an encoder's estimates: it needs an encoder")
    if state_noise > 0:
        key = encoder_key if encoder is not None else "state"
        transforms.append(StateNoise(state_noise, in_keys=[key], seed=noise_seed))
    if target_return is not None:
        transforms.append(ReturnToGo(target_return, rtg_scale=rtg_scale))
    return TransformedEnv(env, Compose(*transforms)) if transforms else env


# --------------------------------------------------------------------------- what a file may hold
# The entries of policy and encoder files (the savers' and the recipes' extras): a file holding any
# other entry is refused, so that nothing unread (a large tensor, say) comes in with it.
POLICY_KEYS = frozenset({
    "format", "kind", "task", "horizon", "dt_config", "observation_key", "actor", "target_return", "rtg_scale",
    "env_kwargs", "encoder", "normalizer", "render_version", "bc_config", "trunk_config", "trunk",
    "proprio_dims", "picker_odometry", "selected_round", "selection_scores", "teacher", "weight_copy", "distill",
    "state_noise", "expert_coef", "select_episodes", "dataset", "epochs", "updates"})
"""Entries a policy file may hold (``save_policy`` / ``save_image_policy`` and the recipes' extras)."""
ENCODER_KEYS = frozenset({
    "format", "kind", "task", "render_version", "encoder_kwargs", "state_dict", "ensemble", "val_mae", "val_error_cm",
    "epoch", "aug", "dataset", "student_rounds", "member_scores", "selected_member", "mask_unseen_pickers",
    "out_of_view_fill"})
"""Entries an encoder file (or a student policy's ``encoder`` entry) may hold."""


def _check_keys(data: Mapping[str, Any], allowed: frozenset, source: str, what: str) -> None:
    unknown = sorted(str(k) for k in data if k not in allowed)
    if unknown:
        raise CheckpointError(f"{source}: unknown entries {unknown} in a {what} (trakdis writes only "
                              f"{sorted(allowed - {'format'})}): refused rather than loaded unread")


def _check_names(data: Mapping[str, Any], path: Path, keys: Sequence[str]) -> None:
    """The entries ``keys`` of a file's dict, where present, strings (a tensor there would be compared as one)."""
    for key in keys:
        if data.get(key) is not None and not isinstance(data[key], str):
            raise CheckpointError(f"{path}: {key!r} must be a name, got {type(data[key]).__name__}")


def _check_extra(extra: Mapping[str, Any] | None, allowed: frozenset, what: str) -> dict[str, Any]:
    extra = dict(extra or {})
    unknown = sorted(k for k in extra if k not in allowed)
    if unknown:  # the loaders refuse what they do not know: add a new entry to the allowed set first
        raise ValueError(f"{what}: extra entries {unknown} are not among trakdis.policies' allowed keys")
    return extra


def _file_limit_hint(max_params: int) -> str:
    return (f" (max_params={max_params}; trakdis.utils.limits.MAX_PARAMS by default): raise it with --max-params, "
            f"or load_policy/load_encoder(max_params=...), for a file you trust")


def _file_max_bytes(max_params: int) -> int:
    """The data a policy or encoder file within ``max_params`` holds at most: an actor, an encoder and an
    image trunk of float32 weights each within the limit, their optimiser-free extras and statistics."""
    return 16 * int(max_params) + 64 * 2**20


def _check_ints(source: str, where: str, config: Mapping[str, Any], bounds: Mapping[str, tuple[int, int]],
                max_params: int | None = None) -> None:
    """Each of ``bounds``' entries of ``config`` (where present) an int, or a list of ints, within its bounds
    (an upper bound equal to ``max_params``: a size that alone exceeds the parameter limit)."""
    for name, (low, high) in bounds.items():
        if name not in config:
            continue
        value = config[name]
        values = value if isinstance(value, (list, tuple)) else [value]
        if isinstance(value, (list, tuple)) and len(value) > limits.MAX_LAYERS:
            raise CheckpointError(f"{source}: {where}.{name} lists {len(value)} sizes, more than "
                                  f"{limits.MAX_LAYERS} (trakdis.utils.limits.MAX_LAYERS)")
        for v in values:
            if not (limits.is_int(v) and low <= v <= high):
                above = limits.is_int(v) and v > high and high == max_params
                raise CheckpointError(f"{source}: {where}.{name} must be {'ints' if values is value else 'an int'} in "
                                      f"[{low}, {high}], got {value!r}" + (
                                          f" (a size above the parameter limit{_file_limit_hint(max_params)})"
                                          if above else ""))


def _check_model_size(source: str, where: str, build: Callable[[], nn.Module], *, copies: int = 1,
                      activation_bytes: int = 0, max_params: int, max_activation_bytes: int) -> None:
    """Refuse a model of more than ``max_params`` parameters (``copies`` of ``build()``'s, counted on
    PyTorch's meta device: nothing allocated) or ``activation_bytes`` above ``max_activation_bytes``."""
    try:
        with torch.device("meta"):
            params = sum(p.numel() for p in build().parameters()) * copies
    except (TypeError, ValueError, RuntimeError, KeyError, IndexError) as err:
        raise CheckpointError(f"{source}: {where} does not describe a model ({type(err).__name__}: {err})") from err
    if params > max_params:
        raise CheckpointError(f"{source}: {where} describes a model of {params:,} parameters, more than the limit of "
                              f"{max_params:,}{_file_limit_hint(max_params)}")
    if activation_bytes > max_activation_bytes:
        raise CheckpointError(f"{source}: {where} needs about {activation_bytes / 2**20:,.0f} MiB of activations per "
                              f"acting window, more than the limit of {max_activation_bytes / 2**20:,.0f} MiB "
                              f"(trakdis.utils.limits.MAX_ACTIVATION_BYTES; load_policy(max_activation_bytes=...))")


def _dt_config(source: str, raw: Any, *, where: str = "dt_config", max_params: int, max_activation_bytes: int):
    """The :class:`~trakdis.modules.DTConfig` of a file's ``where`` entry, once its sizes are within the limits."""
    from trakdis.modules import DTConfig
    from trakdis.modules.decision_transformer import StochasticDTActor

    if not isinstance(raw, Mapping):
        raise CheckpointError(f"{source}: '{where}' must be a dict of DTConfig fields, got {type(raw).__name__}")
    unknown = sorted(str(k) for k in raw if k not in {f.name for f in dataclasses.fields(DTConfig)})
    if unknown:
        raise CheckpointError(f"{source}: {where} has unknown fields {unknown}")
    width = (1, max_params)
    _check_ints(source, where, raw, {"state_dim": width, "action_dim": width, "embed_dim": width, "n_head": width,
                                     "n_layer": (1, limits.MAX_LAYERS), "context_len": width, "max_timestep": width,
                                     "mlp_ratio": (1, 1024)}, max_params)
    for name in ("dropout", "attn_dropout", "log_std_min", "log_std_max", "init_log_std", "loc_bound"):
        if raw.get(name) is not None and not limits.is_number(raw[name]):
            raise CheckpointError(f"{source}: {where}.{name} must be a finite number, got {raw[name]!r}")
    hidden = raw.get("hidden_action_dims")
    if hidden is not None and not (isinstance(hidden, (list, tuple)) and len(hidden) <= raw.get("action_dim", 0)
                                   and all(limits.is_int(d) for d in hidden)):
        raise CheckpointError(f"{source}: {where}.hidden_action_dims must be a list of action dims, got {hidden!r}")
    if not isinstance(raw.get("activation", "gelu"), str):
        raise CheckpointError(f"{source}: {where}.activation must be a name, got {raw['activation']!r}")
    try:
        cfg = DTConfig(**raw)
    except (TypeError, ValueError) as err:
        raise CheckpointError(f"{source}: {where} is not a valid DTConfig ({err})") from err
    if cfg.state_dim is None or cfg.action_dim is None:
        raise CheckpointError(f"{source}: {where} lacks state_dim or action_dim")
    tokens, d = 3 * cfg.context_len, cfg.embed_dim  # a window's return, state and action tokens
    per_layer = cfg.n_head * tokens * tokens + tokens * d * (cfg.mlp_ratio + 8)  # attention scores, block outputs
    _check_model_size(source, where, lambda: StochasticDTActor(cfg), max_params=max_params,
                      activation_bytes=4 * (cfg.n_layer * per_layer + 4 * tokens * d),
                      max_activation_bytes=max_activation_bytes)
    return cfg


def _cnn_activation_bytes(kw: Mapping[str, Any]) -> int:
    """float32 activations of one image through a :class:`~trakdis.modules.StateEncoder` of ``kw``."""
    side, total = int(kw.get("image_size", 32)), 0
    total += (3 + 2 * bool(kw.get("coord_channels"))) * side * side
    padding = 1 if kw.get("head") == "keypoints" else 0
    for i, c in enumerate(kw.get("channels", (32, 32, 32, 32))):
        stride = int(kw.get("stem_stride", 2)) if i == 0 else 1
        side = max(1, (side + 2 * padding - 3) // max(stride, 1) + 1)
        total += 2 * int(c) * side * side
    return 4 * (total + 2 * int(kw.get("hidden_dim", 256)))


_CNN_KEYS = {"state_dim", "feature_dim", "image_size", "channels", "hidden_dim", "head", "stem_stride",
             "coord_channels", "pad"}


def _cnn_kwargs(source: str, raw: Any, where: str, *, out_key: str, max_params: int) -> dict[str, Any]:
    """A file's encoder or trunk config (``out_key``: ``state_dim`` or ``feature_dim``), its types and sizes checked."""
    if not isinstance(raw, Mapping):
        raise CheckpointError(f"{source}: '{where}' must be a dict, got {type(raw).__name__}")
    allowed = _CNN_KEYS - ({"state_dim", "feature_dim"} - {out_key}) - ({"pad"} if out_key == "state_dim" else set())
    unknown = sorted(str(k) for k in raw if k not in allowed)
    if unknown or out_key not in raw:
        raise CheckpointError(f"{source}: {where} must hold {out_key} and may hold {sorted(allowed - {out_key})}; "
                              f"got unknown {unknown}" if unknown else f"{source}: {where} lacks {out_key!r}")
    width = (1, max_params)
    _check_ints(source, where, raw, {out_key: width, "image_size": (11, 4096), "channels": width,
                                     "hidden_dim": width, "stem_stride": (1, 2), "pad": (0, 64)}, max_params)
    if "channels" in raw and not (isinstance(raw["channels"], (list, tuple)) and len(raw["channels"]) == 4):
        raise CheckpointError(f"{source}: {where}.channels must list the 4 conv layers' channels, "
                              f"got {raw['channels']!r}")
    if raw.get("head", "flatten") not in ("flatten", "keypoints"):
        raise CheckpointError(f"{source}: {where}.head must be 'flatten' or 'keypoints', got {raw.get('head')!r}")
    if not isinstance(raw.get("coord_channels", False), bool):
        raise CheckpointError(f"{source}: {where}.coord_channels must be true or false, got {raw['coord_channels']!r}")
    return dict(raw)


def _check_encoder_dict(data: Any, source: str, *, max_params: int, max_activation_bytes: int) -> None:
    """An encoder file's dict (or a student's ``encoder`` entry): its entries, types and sizes, before
    :func:`encoder_from_dict` builds anything."""
    from trakdis.modules import StateEncoder

    if not isinstance(data, Mapping):
        raise CheckpointError(f"{source}: the encoder must be a dict, got {type(data).__name__}")
    _check_keys(data, ENCODER_KEYS, source, "encoder file")
    missing = [k for k in ("encoder_kwargs", "state_dict") if k not in data]
    if missing:
        raise CheckpointError(f"encoder file {source} lacks {missing}")
    if not isinstance(data["state_dict"], Mapping):
        raise CheckpointError(f"{source}: the encoder's 'state_dict' must be a dict of tensors")
    kw = {**_EARLIER_ENCODER_LAYOUT, **_cnn_kwargs(source, data["encoder_kwargs"], "encoder_kwargs",
                                                    out_key="state_dim", max_params=max_params)}
    ensemble, members = data.get("ensemble"), 1
    if ensemble:
        if not isinstance(ensemble, Mapping) or set(ensemble) - {"members", "state_mirror"}:
            raise CheckpointError(f"{source}: 'ensemble' must be {{'members': n, 'state_mirror': ...}}, "
                                  f"got {ensemble!r}")
        members = ensemble.get("members")
        if not (limits.is_int(members) and 1 <= members <= limits.MAX_MEMBERS):
            raise CheckpointError(f"{source}: 'ensemble' needs 'members' >= 1 and <= {limits.MAX_MEMBERS} "
                                  f"(trakdis.utils.limits.MAX_MEMBERS), got {members!r}")
        mirror = ensemble.get("state_mirror")
        if mirror is not None and not (isinstance(mirror, (list, tuple)) and len(mirror) == 2 and all(
                isinstance(m, (list, tuple)) and len(m) == kw["state_dim"] for m in mirror)):
            raise CheckpointError(f"{source}: ensemble.state_mirror must be (permutation, signs) of the state's "
                                  f"{kw['state_dim']} dims, got {mirror!r}")
    state_dim = kw.pop("state_dim")
    _check_model_size(source, "encoder_kwargs", lambda: StateEncoder(state_dim, **kw), copies=members,
                      activation_bytes=members * _cnn_activation_bytes(kw), max_params=max_params,
                      max_activation_bytes=max_activation_bytes)


def _policy_fields(data: Mapping[str, Any], path: Path) -> None:
    """The plain entries of a policy file, typed and within range (:mod:`trakdis.utils.limits`)."""
    from trakdis.envs import TASKS

    if not isinstance(data["task"], str) or data["task"] not in TASKS:
        raise CheckpointError(f"{path}: 'task' must be one of {list(TASKS)}, got {data['task']!r}")
    horizon = data.get("horizon")
    if not (limits.is_int(horizon) and 1 <= horizon <= limits.MAX_HORIZON):
        raise CheckpointError(f"{path}: 'horizon' must be an int in [1, {limits.MAX_HORIZON}] "
                              f"(trakdis.utils.limits.MAX_HORIZON), got {horizon!r}")
    if not isinstance(data["observation_key"], str):
        raise CheckpointError(f"{path}: 'observation_key' must be a key name, got {data['observation_key']!r}")
    for name in ("target_return", "rtg_scale"):
        if name in data and not limits.is_number(data[name]):
            raise CheckpointError(f"{path}: {name!r} must be a finite number, got {data[name]!r}")
    if "rtg_scale" in data and not data["rtg_scale"] > 0:
        raise CheckpointError(f"{path}: 'rtg_scale' must be > 0, got {data['rtg_scale']!r}")
    if not isinstance(data["actor"], Mapping):
        raise CheckpointError(f"{path}: 'actor' must be a dict of tensors, got {type(data['actor']).__name__}")
    for name in ("normalizer", "encoder"):
        if data.get(name) is not None and not isinstance(data[name], Mapping):
            raise CheckpointError(f"{path}: {name!r} must be a dict or null, got {type(data[name]).__name__}")
    dims = data.get("proprio_dims") or ()
    if not (isinstance(dims, (list, tuple)) and len(dims) <= 4096 and all(limits.is_int(d) and d >= 0 for d in dims)):
        raise CheckpointError(f"{path}: 'proprio_dims' must be a list of state dims, got {dims!r}")
    if not isinstance(data.get("picker_odometry", False), bool):
        raise CheckpointError(f"{path}: 'picker_odometry' must be true or false, got {data['picker_odometry']!r}")
    limits.check_env_kwargs(data.get("env_kwargs"), str(path), error=CheckpointError)


# --------------------------------------------------------------------------- encoder files
# Keys an encoder file written before the keypoint encoder lacks: they mean the earlier layout.
_EARLIER_ENCODER_LAYOUT = {"head": "flatten", "stem_stride": 2, "coord_channels": False}


def save_encoder(path: str | Path, encoder: NormalizedEncoder | EncoderEnsemble, *, task: str,
                 extra: Mapping[str, Any] | None = None) -> Path:
    """Write an encoder file: a :class:`NormalizedEncoder`, or an :class:`~trakdis.modules.EncoderEnsemble`
    of them (its ``"ensemble"`` entry: the number of members and the state mirror, if any)."""
    ensemble = None
    if isinstance(encoder, EncoderEnsemble):
        ensemble = {"members": len(encoder.members), "state_mirror": encoder.state_mirror}
        first = encoder.members[0]
    else:
        first = encoder
    return save_checkpoint(path, {
        "kind": "encoder", "task": task, "render_version": render_version(task), "encoder_kwargs": dict(first.encoder.config),
        "state_dict": encoder.state_dict(), **_check_extra(extra, ENCODER_KEYS, "save_encoder"), "ensemble": ensemble,
    })


def check_render_version(data: Mapping[str, Any], task: str, source: str) -> None:
    """Refuse (:class:`~trakdis.utils.checkpoint.CheckpointError`) a model file whose image network
    was trained on another rendering of ``task`` than today's (:func:`trakdis.envs.render_version`):
    it would read images unlike its training images. Files written before the version was recorded
    count as version 2 (the 35 mm picker markers, before the unpinned fold's wider camera)."""
    found, current = data.get("render_version", 2), render_version(task)
    if not limits.is_int(found):
        raise CheckpointError(f"{source}: 'render_version' must be an int, got {found!r}")
    if found != current:
        raise CheckpointError(f"{source}: its image network was trained on {task} images of rendering version "
                              f"{found}; this trakdis renders {task} at version {current} (docs/tasks.md), so it "
                              f"would read other images than it learnt from: train it again")


def encoder_from_dict(data: Mapping[str, Any], *, source: str = "encoder file", max_params: int = limits.MAX_PARAMS,
                      max_activation_bytes: int = limits.MAX_ACTIVATION_BYTES) -> NormalizedEncoder | EncoderEnsemble:
    """The encoder of an encoder file's dict (read from ``source``), once its entries, types and sizes
    pass the checks (:mod:`trakdis.utils.limits`; a :class:`~trakdis.utils.checkpoint.CheckpointError`
    naming ``source`` otherwise)."""
    from trakdis.modules import StateEncoder

    _check_encoder_dict(data, source, max_params=max_params, max_activation_bytes=max_activation_bytes)
    try:
        return _encoder_from_dict(data, StateEncoder)
    except CheckpointError as err:
        raise CheckpointError(f"{source}: {err}") from err
    except (TypeError, KeyError, AttributeError, IndexError, ValueError) as err:
        raise CheckpointError(f"{source}: a malformed encoder entry ({type(err).__name__}: {err})") from err


def _encoder_from_dict(data: Mapping[str, Any], StateEncoder) -> NormalizedEncoder | EncoderEnsemble:
    def member() -> NormalizedEncoder:
        kw = {**_EARLIER_ENCODER_LAYOUT, **dict(data["encoder_kwargs"])}
        state_dim = kw.pop("state_dim")
        return NormalizedEncoder(StateEncoder(state_dim, **kw), torch.zeros(state_dim), torch.ones(state_dim))

    ensemble = data.get("ensemble")
    if ensemble:  # members and mirror checked by _check_encoder_dict
        mirror = ensemble.get("state_mirror")
        enc = EncoderEnsemble([member() for _ in range(ensemble["members"])],
                              state_mirror=None if mirror is None else tuple(mirror))
    else:
        enc = member()
    try:
        enc.load_state_dict(data["state_dict"])
    except (RuntimeError, TypeError, AttributeError) as err:
        raise CheckpointError(f"encoder weights do not match its encoder_kwargs {data['encoder_kwargs']} "
                              f"(ensemble {ensemble}): {err}") from err
    return enc.eval()


def load_encoder(path: str | Path, *, task: str | None = None, max_params: int = limits.MAX_PARAMS,
                 max_activation_bytes: int = limits.MAX_ACTIVATION_BYTES) -> tuple[NormalizedEncoder, dict[str, Any]]:
    """The encoder of an encoder file (or of a run directory holding ``encoder.pt``) and the file's
    dict; ``task``: refuse (``ValueError``) an encoder trained for another task. ``max_params`` /
    ``max_activation_bytes``: the limits of :mod:`trakdis.utils.limits` on the model it describes
    (raise them for a larger encoder you trust)."""
    path = Path(path)
    if path.is_dir():
        path = path / "encoder.pt"
    data = load_checkpoint(path, required=("kind",), max_bytes=_file_max_bytes(max_params),
                           limit_hint=_file_limit_hint(max_params))
    _check_names(data, path, ("kind", "task"))
    if data["kind"] != "encoder":
        raise CheckpointError(f"{path} is a {data['kind']!r} file, not an encoder (train one with recipes/train_encoder.py)")
    missing = [k for k in ("encoder_kwargs", "state_dict") if k not in data]
    if missing:
        raise CheckpointError(f"encoder file {path} lacks {missing}")
    _check_keys(data, ENCODER_KEYS, str(path), "encoder file")
    if task is not None and data.get("task") != task:
        raise ValueError(f"encoder {path} is for {data.get('task')}, not {task}")
    if data.get("task") is not None:
        check_render_version(data, data["task"], f"encoder {path}")
    return encoder_from_dict(data, source=str(path), max_params=max_params,
                             max_activation_bytes=max_activation_bytes), data


# --------------------------------------------------------------------------- policy files
def save_policy(path: str | Path, *, kind: str, task: str, horizon: int, dt_config, actor: nn.Module,
                observation_key: str, target_return: float, rtg_scale: float,
                normalizer: StateNormalizer | None = None,
                env_kwargs: Mapping[str, Any] | None = None, encoder_file: Mapping[str, Any] | None = None,
                extra: Mapping[str, Any] | None = None) -> Path:
    cfg = dt_config.to_dict() if hasattr(dt_config, "to_dict") else dataclasses.asdict(dt_config)
    return save_checkpoint(path, {
        "kind": kind, "task": task, "horizon": int(horizon), "dt_config": cfg,
        "observation_key": observation_key, "actor": actor.state_dict(),
        "target_return": float(target_return), "rtg_scale": float(rtg_scale),
        "env_kwargs": dict(env_kwargs or {}), "encoder": encoder_file,
        "normalizer": None if normalizer is None else normalizer.state_dict(),
        **_check_extra(extra, POLICY_KEYS, "save_policy"),
    })


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
    normalizer: StateNormalizer | None = None
    """standardisation of the observation the DT reads (None: raw)"""
    proprio_dims: tuple = ()
    """dims of the student's estimate taken from the true state (picker positions), if any"""
    picker_odometry: bool = False
    """the student's picker estimates fused with its own commands (``PickerOdometry`` in its env)"""

    @property
    def uses_pixels(self) -> bool:
        return self.encoder is not None

    def make_env(self, *, num_envs: int = 1, split: str = "eval", seed: int | None = None, state_noise: float = 0.0,
                 noise_seed: int | None = None,
                 parallel: bool = False, from_pixels: bool | None = None, image_size: int = 32,
                 target_return: float | None = None, video_size: int | None = None):
        """The acting env of this policy (pixels on for a student, or when ``from_pixels``)."""
        is_dt = self.kind not in ("expert", "bc_image")
        return make_acting_env(
            self.task,
            target_return=(self.target_return if target_return is None else target_return) if is_dt else None,
            rtg_scale=self.rtg_scale, encoder=self.encoder, state_noise=state_noise,
            noise_seed=noise_seed if noise_seed is not None else (None if seed is None else seed + 7919),
            num_envs=num_envs, parallel=parallel, seed=seed, split=split,
            from_pixels=bool(from_pixels) or self.uses_pixels, image_size=image_size,
            env_kwargs={**self.env_kwargs, "horizon": self.horizon}, video_size=video_size,
            picker_odometry=self.picker_odometry and self.encoder is not None,
            **({"encoder_key": self.observation_key} if self.kind in IMAGE_POLICY_KINDS else {}),
        )

    def make_policy(self, *, seed: int | None = None):
        """A TensorDict module writing ``"action"``: the DT acting wrapper, or the scripted expert."""
        if self.kind == "expert":
            from trakdis.envs import ExpertPolicy

            return ExpertPolicy(self.task, noise=self.expert_noise, seed=seed)
        if self.kind == "bc_image":  # stateless: the actor on the env's image features
            return self.actor.eval()
        from trakdis.modules import DTActingPolicy

        self.actor.eval()
        policy = DTActingPolicy(self.actor, observation_key=self.observation_key)
        pre = ProprioceptionOverride(self.proprio_dims) if self.proprio_dims else None
        if self.normalizer is None and pre is None:
            return policy
        return NormalizedPolicy(policy, self.normalizer, self.observation_key, pre=pre)

    def save(self, path: str | Path, dt_config, *, encoder_file: Mapping[str, Any] | None = None,
             extra: Mapping[str, Any] | None = None) -> Path:
        """Write this Decision Transformer policy (teacher or student) with :func:`save_policy`, from
        the handle's own fields; ``dt_config``: its actor's :class:`~trakdis.modules.DTConfig`."""
        return save_policy(path, kind=self.kind, task=self.task, horizon=self.horizon, dt_config=dt_config,
                           actor=self.actor, observation_key=self.observation_key, target_return=self.target_return,
                           rtg_scale=self.rtg_scale, normalizer=self.normalizer, env_kwargs=self.env_kwargs,
                           encoder_file=encoder_file, extra=extra)


def weight_copied_student(teacher: PolicyHandle, encoder: nn.Module, *, weight_copy: bool = True,
                          normalizer_keys: tuple[str, ...] = ("state_estimate",), proprio_dims: tuple = (),
                          picker_odometry: bool = False, device: str = "cpu") -> tuple[PolicyHandle, Any]:
    """The TraKDis student of a loaded ``teacher`` and its :class:`~trakdis.modules.DTConfig`.

    A DT of the teacher's sizes reading ``"state_estimate"`` (``encoder``'s estimate from the
    image, run in the acting env), starting as a copy of the teacher's weights (``weight_copy``;
    else fresh weights), acting with the teacher's return-to-go, env options and state statistics
    (a normaliser of ``normalizer_keys``); ``proprio_dims``: dims of the estimate taken from the
    true state when acting; ``picker_odometry``: the estimate's pickers fused with the student's own
    commands (``PickerOdometry``) when acting."""
    from trakdis.modules import DTConfig, copy_teacher_weights, make_dt_actor

    dt_cfg = DTConfig(**load_checkpoint(teacher.source)["dt_config"])
    student = make_dt_actor(dt_cfg, observation_key="state_estimate", device=device)
    if weight_copy:
        copy_teacher_weights(student, teacher.actor)
    norm = teacher.normalizer  # its out-of-view fill too (--mask-unseen-pickers): the student reads what the teacher read
    handle = PolicyHandle("student", teacher.task, teacher.horizon, actor=student, encoder=encoder,
                          observation_key="state_estimate", target_return=teacher.target_return,
                          rtg_scale=teacher.rtg_scale, env_kwargs=teacher.env_kwargs,
                          normalizer=None if norm is None else norm.with_keys(normalizer_keys),
                          proprio_dims=tuple(proprio_dims), picker_odometry=picker_odometry)
    return handle, dt_cfg


def check_unseen_picker_mask(teacher: PolicyHandle, encoder_file: Mapping[str, Any], *, encoder_source: str) -> bool:
    """Whether ``teacher`` acts on out-of-view-masked states (``online_dt.py --mask-unseen-pickers``:
    its normaliser carries an :class:`~trakdis.transforms.OutOfViewFill`); a ``ValueError`` naming
    both files and the flag unless the encoder (``encoder_file``: an encoder file's dict, read from
    ``encoder_source``; ``train_encoder.py --mask-unseen-pickers`` records ``mask_unseen_pickers``
    and ``out_of_view_fill``) was trained on labels masked the same way."""
    fill = None if teacher.normalizer is None else teacher.normalizer.fill
    encoder_masked = bool(encoder_file.get("mask_unseen_pickers", False))
    if (fill is not None) != encoder_masked:
        def how(masked):
            return "with --mask-unseen-pickers" if masked else "without --mask-unseen-pickers"

        raise ValueError(f"teacher {teacher.source} was trained {how(fill is not None)} (online_dt.py) but encoder "
                         f"{encoder_source} {how(encoder_masked)} (train_encoder.py): the student would read estimates "
                         f"of states the teacher never saw; train both with the same --mask-unseen-pickers")
    if fill is not None and encoder_file.get("out_of_view_fill") is not None:
        theirs = OutOfViewFill.from_state_dict(encoder_file["out_of_view_fill"])
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
    from trakdis.utils.logger import latest_run_file

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
    from trakdis.envs import task_spec

    res = _weight_copy_episodes(teacher, encoder, episodes=episodes, seed=seed, image_size=image_size,
                                num_envs=num_envs, parallel=parallel, keep_episodes=True, desc="student rollouts")
    steps = torch.cat([ep.select("pixels", "state", "state_estimate").to_tensordict() for ep in res.episodes])
    fill = None if teacher.normalizer is None else teacher.normalizer.fill
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
    from trakdis.envs import close_env
    from trakdis.evaluation import EpisodeStream, episode_score, race_survivors

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
    import copy

    handle, _ = weight_copied_student(teacher, copy.deepcopy(encoder).cpu().eval())
    return handle, handle.make_env(num_envs=num_envs, parallel=parallel, split="train", image_size=image_size)


def _weight_copy_episodes(teacher: PolicyHandle, encoder: nn.Module, *, episodes: int, seed: int, image_size: int,
                          num_envs: int, parallel: bool, keep_episodes: bool, desc: str):
    from trakdis.envs import close_env
    from trakdis.evaluation import run_episodes

    handle, env = _weight_copy_env(teacher, encoder, num_envs=num_envs, parallel=parallel, image_size=image_size)
    try:
        return run_episodes(env, handle.make_policy(), episodes, max_steps=teacher.horizon, keep_episodes=keep_episodes,
                            seed=seed, desc=desc)
    finally:
        close_env(env)


def load_policy(spec: str | Path, *, task: str | None = None, horizon: int | None = None,
                expert_noise: float = 0.0, device: str = "cpu", max_params: int = limits.MAX_PARAMS,
                max_activation_bytes: int = limits.MAX_ACTIVATION_BYTES) -> PolicyHandle:
    """``"expert"`` or the path of a policy file (or of a run directory holding ``policy.pt``).

    A file is untrusted input (docs/security.md): it must be a regular file, unpack to no more than
    its models need, hold only the entries trakdis writes (:data:`POLICY_KEYS`), each of its type and
    range (``env_kwargs``: :func:`~trakdis.utils.limits.check_env_kwargs`), and describe models of at
    most ``max_params`` parameters and ``max_activation_bytes`` of activations per acting window
    (estimated from its configs before anything is built; raise them for a larger policy you trust).
    Anything else is a :class:`~trakdis.utils.checkpoint.CheckpointError` naming the file and the entry."""
    if horizon is not None and not (limits.is_int(horizon) and 1 <= horizon <= limits.MAX_HORIZON):
        raise ValueError(f"horizon must be >= 1 (an int, at most {limits.MAX_HORIZON}; None: the policy's own), "
                         f"got {horizon!r}")
    if str(spec) == "expert":
        if task is None:
            raise ValueError("the expert policy needs --task")
        return PolicyHandle("expert", task, 100 if horizon is None else horizon, expert_noise=expert_noise, source="expert")
    path = Path(spec)
    if path.is_dir():
        path = path / "policy.pt"
    data = load_checkpoint(path, required=("kind", "task", "actor", "observation_key"),
                           max_bytes=_file_max_bytes(max_params), limit_hint=_file_limit_hint(max_params))
    _check_names(data, path, ("kind", "task", "observation_key"))
    if data["kind"] not in ("teacher", "student", *IMAGE_POLICY_KINDS):
        raise CheckpointError(f"{path}: kind {data['kind']!r} is not a policy (expected one of "
                              f"teacher, student, {', '.join(IMAGE_POLICY_KINDS)})")
    _check_keys(data, POLICY_KEYS, str(path), f"{data['kind']} policy file")
    _policy_fields(data, path)
    if task is not None and task != data["task"]:
        raise ValueError(f"{path} is a {data['task']} policy, but task {task!r} was asked for")
    sizes = dict(max_params=max_params, max_activation_bytes=max_activation_bytes)
    try:
        if data["kind"] in IMAGE_POLICY_KINDS:
            return _load_image_policy(path, data, horizon=horizon, device=device, **sizes)
        return _load_dt_policy(path, data, horizon=horizon, device=device, **sizes)
    except CheckpointError:
        raise
    except (TypeError, KeyError, AttributeError, IndexError, ValueError) as err:  # a field of an unexpected form
        raise CheckpointError(f"{path}: a malformed policy file ({type(err).__name__}: {err})") from err


def _load_dt_policy(path: Path, data: Mapping[str, Any], *, horizon: int | None, device: str, max_params: int,
                    max_activation_bytes: int) -> PolicyHandle:
    """A teacher's or student's :class:`PolicyHandle` from its checked file dict (:func:`load_policy`)."""
    from trakdis.modules import make_dt_actor

    if "dt_config" not in data:
        raise CheckpointError(f"{path}: a {data['kind']} policy file lacks 'dt_config'")
    cfg = _dt_config(str(path), data["dt_config"], max_params=max_params, max_activation_bytes=max_activation_bytes)
    encoder = None
    if data.get("encoder"):
        check_render_version(data["encoder"], data["task"], f"{path} (its encoder)")
        _check_encoder_dict(data["encoder"], f"{path} (its encoder)", max_params=max_params,
                            max_activation_bytes=max_activation_bytes)
    actor = make_dt_actor(cfg, observation_key=data["observation_key"], device=device)
    try:
        actor.load_state_dict(data["actor"])
    except RuntimeError as err:
        raise CheckpointError(f"{path}: actor weights do not match its dt_config: {err}") from err
    if data.get("encoder"):
        encoder = encoder_from_dict(data["encoder"], source=f"{path} (its encoder)", max_params=max_params,
                                    max_activation_bytes=max_activation_bytes)
    if data["kind"] == "student" and encoder is None:
        raise CheckpointError(f"{path}: a student policy file must contain its encoder")
    return PolicyHandle(
        data["kind"], data["task"], data["horizon"] if horizon is None else horizon, actor=actor.eval(), encoder=encoder,
        observation_key=data["observation_key"], target_return=data["target_return"],
        rtg_scale=data["rtg_scale"], env_kwargs=dict(data.get("env_kwargs") or {}), source=str(path),
        normalizer=StateNormalizer.from_state_dict(data["normalizer"]) if data.get("normalizer") else None,
        proprio_dims=tuple(data.get("proprio_dims") or ()), picker_odometry=bool(data.get("picker_odometry", False)),
    )


def load_teacher(spec: str | Path, *, task: str | None = None, horizon: int | None = None,
                 device: str = "cpu", **limits_kw: int) -> PolicyHandle:
    """:func:`load_policy` of a teacher's policy file (or run directory); a file of another kind, or
    a teacher for another ``task`` or ``horizon`` (each checked when given), is a
    :class:`~trakdis.utils.checkpoint.CheckpointError`."""
    teacher = load_policy(spec, device=device, **limits_kw)
    if teacher.kind != "teacher" or task not in (None, teacher.task) or horizon not in (None, teacher.horizon):
        expected = "".join([f" for {task}" if task else "", f" (horizon {horizon})" if horizon else ""])
        raise CheckpointError(f"{teacher.source}: a {teacher.kind} for {teacher.task} (horizon {teacher.horizon}); "
                              f"expected a teacher{expected}")
    return teacher


# --------------------------------------------------------------------------- image baselines
IMAGE_POLICY_KINDS = ("bc_image", "dt_image")
"""Policy kinds that read the image through their own CNN trunk (the paper's BC and DT-image)."""


def save_image_policy(path: str | Path, *, kind: str, task: str, horizon: int, trunk: nn.Module, actor: nn.Module,
                      head_config: Mapping[str, Any], observation_key: str = "image_features",
                      target_return: float = 0.0, rtg_scale: float = 1.0, env_kwargs: Mapping[str, Any] | None = None,
                      extra: Mapping[str, Any] | None = None) -> Path:
    """Write a ``bc_image`` / ``dt_image`` policy file: ``trunk_config`` + ``trunk`` (an
    :class:`~trakdis.modules.ImageTrunk`), the head ``actor`` (state dict) and its config
    (``bc_config`` or ``dt_config``), plus the acting return-to-go of a DT."""
    if kind not in IMAGE_POLICY_KINDS:
        raise ValueError(f"save_image_policy: kind must be one of {IMAGE_POLICY_KINDS}, got {kind!r}")
    config_key = "bc_config" if kind == "bc_image" else "dt_config"
    cfg = head_config.to_dict() if hasattr(head_config, "to_dict") else dict(head_config)
    return save_checkpoint(path, {
        "kind": kind, "task": task, "horizon": int(horizon), config_key: cfg, "render_version": render_version(task),
        "trunk_config": dict(trunk.config), "trunk": trunk.state_dict(), "observation_key": observation_key,
        "actor": actor.state_dict(), "target_return": float(target_return), "rtg_scale": float(rtg_scale),
        "env_kwargs": dict(env_kwargs or {}), **_check_extra(extra, POLICY_KEYS, "save_image_policy"),
    })


def _load_image_policy(path: Path, data: Mapping[str, Any], *, horizon: int | None, device: str, max_params: int,
                       max_activation_bytes: int) -> PolicyHandle:
    from trakdis.modules import BCConfig, ImageTrunk, make_bc_actor, make_dt_actor
    from trakdis.modules.baselines import BCHead

    config_key = "bc_config" if data["kind"] == "bc_image" else "dt_config"
    missing = [k for k in (config_key, "trunk_config", "trunk") if k not in data]
    if missing:
        raise CheckpointError(f"{path}: a {data['kind']} policy file lacks {missing}")
    check_render_version(data, data["task"], str(path))
    sizes = dict(max_params=max_params, max_activation_bytes=max_activation_bytes)
    trunk_kw = _cnn_kwargs(str(path), data["trunk_config"], "trunk_config", out_key="feature_dim", max_params=max_params)
    _check_model_size(str(path), "trunk_config", lambda: ImageTrunk.from_config(trunk_kw),
                      activation_bytes=_cnn_activation_bytes(trunk_kw), **sizes)
    if data["kind"] == "bc_image":
        bc = dict(data[config_key])
        _check_ints(str(path), config_key, bc, {"feature_dim": (1, max_params), "action_dim": (1, max_params),
                                                "hidden_dims": (1, max_params)}, max_params)
        bc["hidden_dims"] = tuple(bc.get("hidden_dims", ()))
        try:
            bc_cfg = BCConfig(**bc)
        except (TypeError, ValueError) as err:
            raise CheckpointError(f"{path}: {config_key} is not a valid BCConfig ({err})") from err
        _check_model_size(str(path), config_key, lambda: BCHead(bc_cfg), **sizes)
    else:
        dt_cfg = _dt_config(str(path), data[config_key], **sizes)
    try:
        trunk = ImageTrunk.from_config(trunk_kw).to(device)
        trunk.load_state_dict(data["trunk"])
    except (TypeError, ValueError, RuntimeError) as err:
        raise CheckpointError(f"{path}: the CNN trunk does not match its trunk_config {data['trunk_config']}: {err}") from err
    if data["kind"] == "bc_image":
        actor = make_bc_actor(bc_cfg, observation_key=data["observation_key"], device=device)
    else:
        actor = make_dt_actor(dt_cfg, observation_key=data["observation_key"], device=device)
    try:
        actor.load_state_dict(data["actor"])
    except RuntimeError as err:
        raise CheckpointError(f"{path}: actor weights do not match its {config_key}: {err}") from err
    return PolicyHandle(
        data["kind"], data["task"], data["horizon"] if horizon is None else horizon, actor=actor.eval(),
        encoder=trunk.eval(), observation_key=data["observation_key"], target_return=data.get("target_return", 0.0),
        rtg_scale=data.get("rtg_scale", 1.0), env_kwargs=dict(data.get("env_kwargs") or {}), source=str(path))
