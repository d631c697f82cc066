"""State standardisation and the proprioception override, as TorchRL transforms (replay-buffer
sampling transforms, env transforms, and the acting maps of :class:`~trakdis.modules.NormalizedPolicy`).

A *state normaliser* is TorchRL's ``ObservationNorm(loc, scale, in_keys=keys, standard_normal=True)``:
``x -> (x - loc) / scale`` on some keys, fitted on a dataset's states. With ``--mask-unseen-pickers``
it is ``Compose(OutOfViewFill, ObservationNorm)``: the out-of-view pickers masked on the same keys
before standardising. Decision Transformers are trained on standardised states (as in DT/ODT): the
raw cloth coordinates differ by centimetres, far below the scale of the other token embeddings. The
normaliser is the replay buffer's sampling transform; :class:`~trakdis.modules.NormalizedPolicy`
applies the same map when acting, so the environment and the stored data stay in raw units. Keys it
does not find are skipped (``set_missing_tolerance(True)``).

* :func:`state_normalizer`, :func:`fit_state_normalizer`: build one (from statistics, or fitted).
* :func:`normalizer_state_dict`, :func:`normalizer_from_state_dict`: the dict policy files and resume
  checkpoints hold (``"loc"``, ``"scale"``, ``"keys"`` and, with a mask, ``"fill"``), and back.
* :func:`normalizer_parts`, :func:`normalizer_with_keys`: its ``ObservationNorm`` and mask; the same map
  on other keys.
* :class:`ProprioceptionOverride`: the picker dims of an encoder's estimate taken from the true state.

Several sampling transforms in a row are TorchRL's ``Compose``.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs.transforms import Compose, ObservationNorm, Transform

from trakdis.transforms.visibility import OutOfViewFill

__all__ = [
    "ProprioceptionOverride",
    "fit_state_normalizer",
    "normalizer_from_state_dict",
    "normalizer_parts",
    "normalizer_state_dict",
    "normalizer_with_keys",
    "state_normalizer",
]


def state_normalizer(loc, scale, keys: Sequence[NestedKey] = ("state",),
                     fill: OutOfViewFill | None = None) -> ObservationNorm | Compose:
    """``ObservationNorm(loc, scale, in_keys=keys, standard_normal=True)`` (float32 statistics; missing
    keys skipped), after ``fill``'s mask on the same ``keys`` when given (``Compose``; the fill's own
    keys are not used). ``loc`` and ``scale`` are 1-d of one shape, ``scale`` > 0: ``ObservationNorm``
    divides by a tensor ``scale`` as it is (its ``eps`` only clamps statistics it computes or is given
    as numbers), so a floor on the std (``fit_state_normalizer(min_scale=...)``) is applied before."""
    loc = torch.as_tensor(loc, dtype=torch.float32).clone()
    scale = torch.as_tensor(scale, dtype=torch.float32).clone()
    if loc.shape != scale.shape or loc.ndim != 1:
        raise ValueError(f"state normaliser: loc {tuple(loc.shape)} and scale {tuple(scale.shape)} must be equal 1-d shapes")
    if (scale <= 0).any():
        raise ValueError("state normaliser: scale must be > 0")
    keys = list(keys)
    if fill is not None and not isinstance(fill, OutOfViewFill):
        raise TypeError(f"state normaliser: fill must be an OutOfViewFill or None, got {type(fill).__name__}")
    if fill is not None and fill.starts and max(fill.starts) + 3 > loc.numel():
        raise ValueError(f"state normaliser: the fill's points at dims {list(fill.starts)} (xyz each) do not fit "
                         f"{loc.numel()}-dim states")
    norm = ObservationNorm(loc, scale, in_keys=keys, standard_normal=True)
    if fill is not None:
        norm = Compose(OutOfViewFill(fill.camera_matrix, fill.image_size, fill.starts, fill.fill, in_keys=keys), norm)
    norm.set_missing_tolerance(True)
    return norm


def fit_state_normalizer(states: torch.Tensor, keys: Sequence[NestedKey] = ("state",), min_scale: float = 1e-3,
                         fill: OutOfViewFill | None = None) -> ObservationNorm | Compose:
    """:func:`state_normalizer` of the mean and std over all leading dims of ``states`` ``[..., D]``
    (computed in float64, std clamped to ``min_scale``), of the raw states (``fill`` is not applied
    to them: it is only carried)."""
    flat = states.reshape(-1, states.shape[-1]).double()
    return state_normalizer(flat.mean(0).float(), flat.std(0).clamp_min(min_scale).float(), keys, fill)


def normalizer_parts(normalizer: ObservationNorm | Compose) -> tuple[ObservationNorm, OutOfViewFill | None]:
    """``(norm, fill)``: a state normaliser's ``ObservationNorm`` and its mask (None without one)."""
    if isinstance(normalizer, ObservationNorm):
        norm, fill = normalizer, None
    elif (isinstance(normalizer, Compose) and len(normalizer) == 2 and isinstance(normalizer[0], OutOfViewFill)
          and isinstance(normalizer[1], ObservationNorm)):
        norm, fill = normalizer[1], normalizer[0]
    else:
        raise TypeError(f"a state normaliser is an ObservationNorm, or Compose(OutOfViewFill, ObservationNorm); "
                        f"got {normalizer!r}")
    if not bool(norm.standard_normal):
        raise ValueError("a state normaliser's ObservationNorm has standard_normal=True ((x - loc) / scale)")
    return norm, fill


def normalizer_state_dict(normalizer: ObservationNorm | Compose) -> dict:
    """Plain tensors and lists: ``"loc"``, ``"scale"``, ``"keys"``; ``"fill"`` (the mask's
    :meth:`~trakdis.transforms.OutOfViewFill.to_dict`) only with a mask (earlier files have no such key)."""
    norm, fill = normalizer_parts(normalizer)
    state = {"loc": norm.loc.detach().cpu().clone(), "scale": norm.scale.detach().cpu().clone(),
             "keys": list(norm.in_keys)}
    if fill is not None:
        state["fill"] = fill.to_dict()
    return state


def normalizer_from_state_dict(state: Mapping[str, Any]) -> ObservationNorm | Compose:
    """The normaliser of a :func:`normalizer_state_dict` dict; the oldest files hold ``"loc"`` and
    ``"scale"`` only (keys ``["state"]``, no mask)."""
    fill = state.get("fill")
    return state_normalizer(state["loc"], state["scale"], state.get("keys", ("state",)),
                            None if fill is None else OutOfViewFill.from_dict(fill))


def normalizer_with_keys(normalizer: ObservationNorm | Compose, keys: Sequence[NestedKey]) -> ObservationNorm | Compose:
    """A new normaliser: the same statistics and mask on ``keys``."""
    return normalizer_from_state_dict({**normalizer_state_dict(normalizer), "keys": list(keys)})


class ProprioceptionOverride(Transform):
    """Replace ``dims`` of ``dst`` (the encoder's estimate) by the same dims of ``src`` (the true
    state): the picker positions are known to the robot without vision (TorchRL ``Transform``:
    ``in_keys`` ``[src, dst]``, ``out_keys`` ``[dst]``). On env steps and resets, replay-buffer
    samples and stored TensorDicts: a TensorDict without ``dst`` is left as it is; one with ``dst``
    but not ``src`` is a ``KeyError``."""

    def __init__(self, dims, src: NestedKey = "state", dst: NestedKey = "state_estimate"):
        super().__init__(in_keys=[src, dst], out_keys=[dst])
        self.dims = torch.as_tensor(list(dims), dtype=torch.long)
        self.src, self.dst = src, dst

    def _override(self, td: TensorDictBase) -> TensorDictBase:
        if self.dims.numel() and self.dst in td.keys(include_nested=True):
            if self.src not in td.keys(include_nested=True):
                raise KeyError(f"ProprioceptionOverride: {self.src!r} is needed to fill dims {self.dims.tolist()} of {self.dst!r}")
            est = td.get(self.dst).clone()
            est[..., self.dims] = td.get(self.src)[..., self.dims].to(est.dtype)
            td.set(self.dst, est)
        return td

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self._override(tensordict)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._override(next_tensordict)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._override(tensordict_reset)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(dims={self.dims.tolist()}, src={self.src!r}, dst={self.dst!r})"
