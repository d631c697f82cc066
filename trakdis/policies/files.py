"""Policy and encoder files: what they hold, their checks, writing them and reading them back.

A *policy file* (``policy.pt``, written by ``online_dt.py`` and ``distill.py``) is a checkpoint
dict holding everything needed to act without the recipe's config:

``kind`` (``"teacher"`` / ``"student"``), ``task``, ``horizon``, ``dt_config`` (a
:class:`~trakdis.modules.DTModelConfig` dict), ``observation_key``, ``actor`` (state dict),
``target_return`` and ``rtg_scale`` (acting return-to-go), ``env_kwargs``, ``normalizer`` (a
state normaliser's :func:`~trakdis.transforms.normalizer_state_dict`, or None) and, for a student, ``encoder`` (an
encoder file's dict, see :func:`save_encoder`). The image baselines' files (kinds ``bc_image`` /
``dt_image``, :func:`save_image_policy`) hold their CNN trunk and head instead.

A file is untrusted input (docs/security.md): :func:`read_policy_file` and :func:`load_encoder`
check its entries, their types and ranges and the sizes of the models it describes before
anything is built. :func:`~trakdis.policies.load_policy` turns what :func:`read_policy_file`
reads into a :class:`~trakdis.policies.PolicyHandle`.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import torch
from torch import nn
from torchrl.envs.transforms import Compose, ObservationNorm

from trakdis.envs import TASKS, render_version
from trakdis.modules import (BCConfig, DTModelConfig, EncoderEnsemble, ImageTrunk, NormalizedEncoder, StateEncoder,
                             make_bc_actor, make_dt_actor)
from trakdis.modules.baselines import BCHead
from trakdis.modules.decision_transformer import StochasticDTActor
from trakdis.transforms.normalization import normalizer_from_state_dict, normalizer_state_dict
from trakdis.utils import limits
from trakdis.utils.checkpoint import FileFormatError, read_checkpoint, save_checkpoint

__all__ = [
    "POLICY_KEYS",
    "ENCODER_KEYS",
    "IMAGE_POLICY_KINDS",
    "save_policy",
    "save_image_policy",
    "read_policy_file",
    "save_encoder",
    "load_encoder",
    "encoder_from_dict",
    "check_render_version",
]


# --------------------------------------------------------------------------- what a file may hold
# The entries of policy and encoder files (the savers' and the recipes' extras): a file holding any
# other entry is refused, so that nothing unread (a large tensor, say) comes in with it.
POLICY_KEYS = frozenset({
    "format", "kind", "task", "horizon", "dt_config", "observation_key", "actor", "target_return", "rtg_scale",
    "env_kwargs", "encoder", "normalizer", "render_version", "bc_config", "trunk_config", "trunk",
    "proprio_dims", "picker_odometry", "hold_radius", "selected_round", "selection_scores", "teacher", "weight_copy",
    "distill", "estimate_noise", "state_noise", "expert_coef", "select_episodes", "dataset", "epochs", "updates"})
"""Entries a policy file may hold (``save_policy`` / ``save_image_policy`` and the recipes' extras; ``state_noise``:
``estimate_noise`` in the files distill.py wrote before the option was renamed)."""
ENCODER_KEYS = frozenset({
    "format", "kind", "task", "render_version", "encoder_kwargs", "state_dict", "ensemble", "val_mae", "val_error_cm",
    "epoch", "aug", "dataset", "student_rounds", "member_scores", "selected_member", "mask_unseen_pickers",
    "out_of_view_fill"})
"""Entries an encoder file (or a student policy's ``encoder`` entry) may hold."""


def _check_keys(data: Mapping[str, Any], allowed: frozenset, source: str, what: str) -> None:
    unknown = sorted(str(k) for k in data if k not in allowed)
    if unknown:
        raise FileFormatError(f"{source}: unknown entries {unknown} in a {what} (trakdis writes only "
                              f"{sorted(allowed - {'format'})}): refused rather than loaded unread")


def _check_names(data: Mapping[str, Any], path: Path, keys: Sequence[str]) -> None:
    """The entries ``keys`` of a file's dict, where present, strings (a tensor there would be compared as one)."""
    for key in keys:
        if data.get(key) is not None and not isinstance(data[key], str):
            raise FileFormatError(f"{path}: {key!r} must be a name, got {type(data[key]).__name__}")


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
            raise FileFormatError(f"{source}: {where}.{name} lists {len(value)} sizes, more than "
                                  f"{limits.MAX_LAYERS} (trakdis.utils.limits.MAX_LAYERS)")
        for v in values:
            if not (limits.is_int(v) and low <= v <= high):
                above = limits.is_int(v) and v > high and high == max_params
                raise FileFormatError(f"{source}: {where}.{name} must be {'ints' if values is value else 'an int'} in "
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
        raise FileFormatError(f"{source}: {where} does not describe a model ({type(err).__name__}: {err})") from err
    if params > max_params:
        raise FileFormatError(f"{source}: {where} describes a model of {params:,} parameters, more than the limit of "
                              f"{max_params:,}{_file_limit_hint(max_params)}")
    if activation_bytes > max_activation_bytes:
        raise FileFormatError(f"{source}: {where} needs about {activation_bytes / 2**20:,.0f} MiB of activations per "
                              f"acting window, more than the limit of {max_activation_bytes / 2**20:,.0f} MiB "
                              f"(trakdis.utils.limits.MAX_ACTIVATION_BYTES; load_policy(max_activation_bytes=...))")


def _dt_config(source: str, raw: Any, *, where: str = "dt_config", max_params: int, max_activation_bytes: int):
    """The :class:`~trakdis.modules.DTModelConfig` of a file's ``where`` entry, once its sizes are within the limits."""
    if not isinstance(raw, Mapping):
        raise FileFormatError(f"{source}: '{where}' must be a dict of DTModelConfig fields, got {type(raw).__name__}")
    unknown = sorted(str(k) for k in raw if k not in {f.name for f in dataclasses.fields(DTModelConfig)})
    if unknown:
        raise FileFormatError(f"{source}: {where} has unknown fields {unknown}")
    width = (1, max_params)
    _check_ints(source, where, raw, {"state_dim": width, "action_dim": width, "embed_dim": width, "n_head": width,
                                     "n_layer": (1, limits.MAX_LAYERS), "context_len": width, "max_timestep": width,
                                     "mlp_ratio": (1, 1024)}, max_params)
    for name in ("dropout", "attn_dropout", "log_std_min", "log_std_max", "init_log_std", "loc_bound"):
        if raw.get(name) is not None and not limits.is_number(raw[name]):
            raise FileFormatError(f"{source}: {where}.{name} must be a finite number, got {raw[name]!r}")
    for name in ("hidden_action_dims", "grasp_dims"):
        dims = raw.get(name)
        if dims is not None and not (isinstance(dims, (list, tuple)) and len(dims) <= raw.get("action_dim", 0)
                                     and all(limits.is_int(d) for d in dims)):
            raise FileFormatError(f"{source}: {where}.{name} must be a list of action dims, got {dims!r}")
    if not isinstance(raw.get("grasp_head", False), bool):
        raise FileFormatError(f"{source}: {where}.grasp_head must be true or false, got {raw['grasp_head']!r}")
    if not isinstance(raw.get("activation", "gelu"), str):
        raise FileFormatError(f"{source}: {where}.activation must be a name, got {raw['activation']!r}")
    try:
        cfg = DTModelConfig(**raw)
    except (TypeError, ValueError) as err:
        raise FileFormatError(f"{source}: {where} is not a valid DTModelConfig ({err})") from err
    if cfg.state_dim is None or cfg.action_dim is None:
        raise FileFormatError(f"{source}: {where} lacks state_dim or action_dim")
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
        raise FileFormatError(f"{source}: '{where}' must be a dict, got {type(raw).__name__}")
    allowed = _CNN_KEYS - ({"state_dim", "feature_dim"} - {out_key}) - ({"pad"} if out_key == "state_dim" else set())
    unknown = sorted(str(k) for k in raw if k not in allowed)
    if unknown or out_key not in raw:
        raise FileFormatError(f"{source}: {where} must hold {out_key} and may hold {sorted(allowed - {out_key})}; "
                              f"got unknown {unknown}" if unknown else f"{source}: {where} lacks {out_key!r}")
    width = (1, max_params)
    _check_ints(source, where, raw, {out_key: width, "image_size": (11, 4096), "channels": width,
                                     "hidden_dim": width, "stem_stride": (1, 2), "pad": (0, 64)}, max_params)
    if "channels" in raw and not (isinstance(raw["channels"], (list, tuple)) and len(raw["channels"]) == 4):
        raise FileFormatError(f"{source}: {where}.channels must list the 4 conv layers' channels, "
                              f"got {raw['channels']!r}")
    if raw.get("head", "flatten") not in ("flatten", "keypoints"):
        raise FileFormatError(f"{source}: {where}.head must be 'flatten' or 'keypoints', got {raw.get('head')!r}")
    if not isinstance(raw.get("coord_channels", False), bool):
        raise FileFormatError(f"{source}: {where}.coord_channels must be true or false, got {raw['coord_channels']!r}")
    return dict(raw)


def _check_encoder_dict(data: Any, source: str, *, max_params: int, max_activation_bytes: int) -> None:
    """An encoder file's dict (or a student's ``encoder`` entry): its entries, types and sizes, before
    :func:`encoder_from_dict` builds anything."""
    if not isinstance(data, Mapping):
        raise FileFormatError(f"{source}: the encoder must be a dict, got {type(data).__name__}")
    _check_keys(data, ENCODER_KEYS, source, "encoder file")
    missing = [k for k in ("encoder_kwargs", "state_dict") if k not in data]
    if missing:
        raise FileFormatError(f"encoder file {source} lacks {missing}")
    if not isinstance(data["state_dict"], Mapping):
        raise FileFormatError(f"{source}: the encoder's 'state_dict' must be a dict of tensors")
    kw = {**_EARLIER_ENCODER_LAYOUT, **_cnn_kwargs(source, data["encoder_kwargs"], "encoder_kwargs",
                                                    out_key="state_dim", max_params=max_params)}
    ensemble, members = data.get("ensemble"), 1
    if ensemble:
        if not isinstance(ensemble, Mapping) or set(ensemble) - {"members", "state_mirror"}:
            raise FileFormatError(f"{source}: 'ensemble' must be {{'members': n, 'state_mirror': ...}}, "
                                  f"got {ensemble!r}")
        members = ensemble.get("members")
        if not (limits.is_int(members) and 1 <= members <= limits.MAX_MEMBERS):
            raise FileFormatError(f"{source}: 'ensemble' needs 'members' >= 1 and <= {limits.MAX_MEMBERS} "
                                  f"(trakdis.utils.limits.MAX_MEMBERS), got {members!r}")
        mirror = ensemble.get("state_mirror")
        if mirror is not None and not (isinstance(mirror, (list, tuple)) and len(mirror) == 2 and all(
                isinstance(m, (list, tuple)) and len(m) == kw["state_dim"] for m in mirror)):
            raise FileFormatError(f"{source}: ensemble.state_mirror must be (permutation, signs) of the state's "
                                  f"{kw['state_dim']} dims, got {mirror!r}")
    state_dim = kw.pop("state_dim")
    _check_model_size(source, "encoder_kwargs", lambda: StateEncoder(state_dim, **kw), copies=members,
                      activation_bytes=members * _cnn_activation_bytes(kw), max_params=max_params,
                      max_activation_bytes=max_activation_bytes)


def _policy_fields(data: Mapping[str, Any], path: Path) -> None:
    """The plain entries of a policy file, typed and within range (:mod:`trakdis.utils.limits`)."""
    if not isinstance(data["task"], str) or data["task"] not in TASKS:
        raise FileFormatError(f"{path}: 'task' must be one of {list(TASKS)}, got {data['task']!r}")
    horizon = data.get("horizon")
    if not (limits.is_int(horizon) and 1 <= horizon <= limits.MAX_HORIZON):
        raise FileFormatError(f"{path}: 'horizon' must be an int in [1, {limits.MAX_HORIZON}] "
                              f"(trakdis.utils.limits.MAX_HORIZON), got {horizon!r}")
    if not isinstance(data["observation_key"], str):
        raise FileFormatError(f"{path}: 'observation_key' must be a key name, got {data['observation_key']!r}")
    for name in ("target_return", "rtg_scale"):
        if name in data and not limits.is_number(data[name]):
            raise FileFormatError(f"{path}: {name!r} must be a finite number, got {data[name]!r}")
    if "rtg_scale" in data and not data["rtg_scale"] > 0:
        raise FileFormatError(f"{path}: 'rtg_scale' must be > 0, got {data['rtg_scale']!r}")
    if not isinstance(data["actor"], Mapping):
        raise FileFormatError(f"{path}: 'actor' must be a dict of tensors, got {type(data['actor']).__name__}")
    for name in ("normalizer", "encoder"):
        if data.get(name) is not None and not isinstance(data[name], Mapping):
            raise FileFormatError(f"{path}: {name!r} must be a dict or null, got {type(data[name]).__name__}")
    dims = data.get("proprio_dims") or ()
    if not (isinstance(dims, (list, tuple)) and len(dims) <= 4096 and all(limits.is_int(d) and d >= 0 for d in dims)):
        raise FileFormatError(f"{path}: 'proprio_dims' must be a list of state dims, got {dims!r}")
    if not isinstance(data.get("picker_odometry", False), bool):
        raise FileFormatError(f"{path}: 'picker_odometry' must be true or false, got {data['picker_odometry']!r}")
    hold = data.get("hold_radius", 0.0)
    if not (limits.is_number(hold) and 0 <= hold < 1) or (hold and not data.get("picker_odometry", False)):
        raise FileFormatError(f"{path}: 'hold_radius' must be a distance in [0, 1) m, with picker_odometry true, "
                              f"got {hold!r}")
    limits.check_env_kwargs(data.get("env_kwargs"), str(path), error=FileFormatError)


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
    """Refuse (:class:`~trakdis.utils.checkpoint.FileFormatError`) a model file whose image network
    was trained on another rendering of ``task`` than today's (:func:`trakdis.envs.render_version`):
    it would read images unlike its training images. Files written before the version was recorded
    count as version 2 (the 35 mm picker markers, before the unpinned fold's wider camera)."""
    found, current = data.get("render_version", 2), render_version(task)
    if not limits.is_int(found):
        raise FileFormatError(f"{source}: 'render_version' must be an int, got {found!r}")
    if found != current:
        raise FileFormatError(f"{source}: its image network was trained on {task} images of rendering version "
                              f"{found}; this trakdis renders {task} at version {current} (docs/tasks.md), so it "
                              f"would read other images than it learnt from: train it again")


def encoder_from_dict(data: Mapping[str, Any], *, source: str = "encoder file", max_params: int = limits.MAX_PARAMS,
                      max_activation_bytes: int = limits.MAX_ACTIVATION_BYTES) -> NormalizedEncoder | EncoderEnsemble:
    """The encoder of an encoder file's dict (read from ``source``), once its entries, types and sizes
    pass the checks (:mod:`trakdis.utils.limits`; a :class:`~trakdis.utils.checkpoint.FileFormatError`
    naming ``source`` otherwise)."""
    _check_encoder_dict(data, source, max_params=max_params, max_activation_bytes=max_activation_bytes)
    try:
        return _encoder_from_dict(data)
    except FileFormatError as err:
        raise FileFormatError(f"{source}: {err}") from err
    except (TypeError, KeyError, AttributeError, IndexError, ValueError) as err:
        raise FileFormatError(f"{source}: a malformed encoder entry ({type(err).__name__}: {err})") from err


def _encoder_from_dict(data: Mapping[str, Any]) -> NormalizedEncoder | EncoderEnsemble:
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
        raise FileFormatError(f"encoder weights do not match its encoder_kwargs {data['encoder_kwargs']} "
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
    data = read_checkpoint(path, required=("kind",), max_bytes=_file_max_bytes(max_params),
                           limit_hint=_file_limit_hint(max_params))
    _check_names(data, path, ("kind", "task"))
    if data["kind"] != "encoder":
        raise FileFormatError(f"{path} is a {data['kind']!r} file, not an encoder (train one with recipes/train_encoder.py)")
    if task is not None and data.get("task") != task:
        raise ValueError(f"encoder {path} is for {data.get('task')}, not {task}")
    if data.get("task") is not None:
        check_render_version(data, data["task"], f"encoder {path}")
    return encoder_from_dict(data, source=str(path), max_params=max_params,
                             max_activation_bytes=max_activation_bytes), data


# --------------------------------------------------------------------------- policy files
def save_policy(path: str | Path, *, kind: str, task: str, horizon: int, dt_config, actor: nn.Module,
                observation_key: str, target_return: float, rtg_scale: float,
                normalizer: ObservationNorm | Compose | None = None,
                env_kwargs: Mapping[str, Any] | None = None, encoder_file: Mapping[str, Any] | None = None,
                extra: Mapping[str, Any] | None = None) -> Path:
    """Write a teacher's or student's policy file (the entries of this module's docstring; ``extra``: among
    :data:`POLICY_KEYS`)."""
    cfg = dt_config.to_dict() if hasattr(dt_config, "to_dict") else dataclasses.asdict(dt_config)
    return save_checkpoint(path, {
        "kind": kind, "task": task, "horizon": int(horizon), "dt_config": cfg,
        "observation_key": observation_key, "actor": actor.state_dict(),
        "target_return": float(target_return), "rtg_scale": float(rtg_scale),
        "env_kwargs": dict(env_kwargs or {}), "encoder": encoder_file,
        "normalizer": None if normalizer is None else normalizer_state_dict(normalizer),
        **_check_extra(extra, POLICY_KEYS, "save_policy"),
    })


def read_policy_file(path: str | Path, *, task: str | None = None, device: str = "cpu",
                     max_params: int = limits.MAX_PARAMS,
                     max_activation_bytes: int = limits.MAX_ACTIVATION_BYTES) -> dict[str, Any]:
    """The policy of a policy file (or of a run directory holding ``policy.pt``) as the fields of a
    :class:`~trakdis.policies.PolicyHandle` (``kind``, ``task``, ``horizon``, ``actor``, ``encoder``,
    ``observation_key``, ..., ``source``: the file), its models built on ``device``; ``task``: refuse
    (``ValueError``) a policy for another task.

    A file is untrusted input (docs/security.md): it must be a regular file, unpack to no more than
    its models need, hold only the entries trakdis writes (:data:`POLICY_KEYS`), each of its type and
    range (``env_kwargs``: :func:`~trakdis.utils.limits.check_env_kwargs`), and describe models of at
    most ``max_params`` parameters and ``max_activation_bytes`` of activations per acting window
    (estimated from its configs before anything is built; raise them for a larger policy you trust).
    Anything else is a :class:`~trakdis.utils.checkpoint.FileFormatError` naming the file and the entry."""
    path = Path(path)
    if path.is_dir():
        path = path / "policy.pt"
    data = read_checkpoint(path, required=("kind", "task", "actor", "observation_key"),
                           max_bytes=_file_max_bytes(max_params), limit_hint=_file_limit_hint(max_params))
    _check_names(data, path, ("kind", "task", "observation_key"))
    if data["kind"] not in ("teacher", "student", *IMAGE_POLICY_KINDS):
        raise FileFormatError(f"{path}: kind {data['kind']!r} is not a policy (expected one of "
                              f"teacher, student, {', '.join(IMAGE_POLICY_KINDS)})")
    _check_keys(data, POLICY_KEYS, str(path), f"{data['kind']} policy file")
    _policy_fields(data, path)
    if task is not None and task != data["task"]:
        raise ValueError(f"{path} is a {data['task']} policy, but task {task!r} was asked for")
    sizes = dict(max_params=max_params, max_activation_bytes=max_activation_bytes)
    try:
        if data["kind"] in IMAGE_POLICY_KINDS:
            return _image_policy_fields(path, data, device=device, **sizes)
        return _dt_policy_fields(path, data, device=device, **sizes)
    except FileFormatError:
        raise
    except (TypeError, KeyError, AttributeError, IndexError, ValueError) as err:  # a field of an unexpected form
        raise FileFormatError(f"{path}: a malformed policy file ({type(err).__name__}: {err})") from err


def _dt_policy_fields(path: Path, data: Mapping[str, Any], *, device: str, max_params: int,
                      max_activation_bytes: int) -> dict[str, Any]:
    """A teacher's or student's policy from its checked file dict (:func:`read_policy_file`)."""
    if "dt_config" not in data:
        raise FileFormatError(f"{path}: a {data['kind']} policy file lacks 'dt_config'")
    cfg = _dt_config(str(path), data["dt_config"], max_params=max_params, max_activation_bytes=max_activation_bytes)
    encoder = None
    if data.get("encoder"):  # checked (encoder_from_dict) and built before the actor: a bad one is refused first
        check_render_version(data["encoder"], data["task"], f"{path} (its encoder)")
        encoder = encoder_from_dict(data["encoder"], source=f"{path} (its encoder)", max_params=max_params,
                                    max_activation_bytes=max_activation_bytes)
    actor = make_dt_actor(cfg, observation_key=data["observation_key"], device=device)
    try:
        actor.load_state_dict(data["actor"])
    except RuntimeError as err:
        raise FileFormatError(f"{path}: actor weights do not match its dt_config: {err}") from err
    if data["kind"] == "student" and encoder is None:
        raise FileFormatError(f"{path}: a student policy file must contain its encoder")
    return dict(
        kind=data["kind"], task=data["task"], horizon=data["horizon"], actor=actor.eval(), encoder=encoder,
        observation_key=data["observation_key"], target_return=data["target_return"],
        rtg_scale=data["rtg_scale"], env_kwargs=dict(data.get("env_kwargs") or {}), source=str(path),
        normalizer=normalizer_from_state_dict(data["normalizer"]) if data.get("normalizer") else None,
        proprio_dims=tuple(data.get("proprio_dims") or ()), picker_odometry=bool(data.get("picker_odometry", False)),
        hold_radius=float(data.get("hold_radius", 0.0)),
    )


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


def _image_policy_fields(path: Path, data: Mapping[str, Any], *, device: str, max_params: int,
                         max_activation_bytes: int) -> dict[str, Any]:
    """An image baseline's policy from its checked file dict (:func:`read_policy_file`)."""
    config_key = "bc_config" if data["kind"] == "bc_image" else "dt_config"
    missing = [k for k in (config_key, "trunk_config", "trunk") if k not in data]
    if missing:
        raise FileFormatError(f"{path}: a {data['kind']} policy file lacks {missing}")
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
            raise FileFormatError(f"{path}: {config_key} is not a valid BCConfig ({err})") from err
        _check_model_size(str(path), config_key, lambda: BCHead(bc_cfg), **sizes)
    else:
        dt_cfg = _dt_config(str(path), data[config_key], **sizes)
    try:
        trunk = ImageTrunk.from_config(trunk_kw).to(device)
        trunk.load_state_dict(data["trunk"])
    except (TypeError, ValueError, RuntimeError) as err:
        raise FileFormatError(f"{path}: the CNN trunk does not match its trunk_config {data['trunk_config']}: {err}") from err
    if data["kind"] == "bc_image":
        actor = make_bc_actor(bc_cfg, observation_key=data["observation_key"], device=device)
    else:
        actor = make_dt_actor(dt_cfg, observation_key=data["observation_key"], device=device)
    try:
        actor.load_state_dict(data["actor"])
    except RuntimeError as err:
        raise FileFormatError(f"{path}: actor weights do not match its {config_key}: {err}") from err
    return dict(
        kind=data["kind"], task=data["task"], horizon=data["horizon"], actor=actor.eval(),
        encoder=trunk.eval(), observation_key=data["observation_key"], target_return=data.get("target_return", 0.0),
        rtg_scale=data.get("rtg_scale", 1.0), env_kwargs=dict(data.get("env_kwargs") or {}), source=str(path))
