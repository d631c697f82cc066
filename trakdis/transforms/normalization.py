"""State standardisation and the proprioception override: callables on TensorDicts (replay-buffer
sampling transforms, and the acting maps of :class:`~trakdis.modules.NormalizedPolicy`).

* :class:`StateNormalizer`: ``x -> (x - loc) / scale`` on some keys, fitted on a dataset's states
  (optionally after an :class:`~trakdis.transforms.OutOfViewFill`).
* :class:`ProprioceptionOverride`: the picker dims of an encoder's estimate taken from the true state.
* :func:`chain`: several such callables applied in order (a replay buffer takes one transform).
"""
from __future__ import annotations

from typing import Any, Callable, Mapping

import torch

from trakdis.transforms.visibility import OutOfViewFill

__all__ = ["ProprioceptionOverride", "StateNormalizer", "chain"]


class StateNormalizer:
    """``x -> (x - loc) / scale`` on the given keys of a TensorDict (returns it; values replaced, not
    modified in place). Decision Transformers are trained on standardised states (as in DT/ODT):
    the raw cloth coordinates differ by centimetres, far below the scale of the other token
    embeddings. Used as the replay buffer's sampling transform; :class:`NormalizedPolicy` applies the
    same map when acting, so the environment and the stored data stay in raw units.

    ``fill`` (an :class:`~trakdis.transforms.OutOfViewFill`, optional): applied to the raw state
    before standardising (``--mask-unseen-pickers``), wherever the normaliser runs (training
    windows, acting, distillation, evaluation); saved with the normaliser."""

    def __init__(self, loc, scale, keys=("state",), fill: OutOfViewFill | None = None):
        self.loc = torch.as_tensor(loc, dtype=torch.float32)
        self.scale = torch.as_tensor(scale, dtype=torch.float32)
        if self.loc.shape != self.scale.shape or self.loc.ndim != 1:
            raise ValueError(f"StateNormalizer: loc {tuple(self.loc.shape)} and scale {tuple(self.scale.shape)} must be equal 1-d shapes")
        if (self.scale <= 0).any():
            raise ValueError("StateNormalizer: scale must be > 0")
        self.keys = tuple(keys)
        if fill is not None and not isinstance(fill, OutOfViewFill):
            raise TypeError(f"StateNormalizer: fill must be an OutOfViewFill or None, got {type(fill).__name__}")
        if fill is not None and fill.starts and max(fill.starts) + 3 > self.loc.numel():
            raise ValueError(f"StateNormalizer: the fill's points at dims {list(fill.starts)} (xyz each) do not fit "
                             f"{self.loc.numel()}-dim states")
        self.fill = fill

    @classmethod
    def fit(cls, states: torch.Tensor, keys=("state",), min_scale: float = 1e-3,
            fill: OutOfViewFill | None = None) -> "StateNormalizer":
        """Mean and std over all leading dims of ``states`` ``[..., D]`` (std clamped to ``min_scale``),
        of the raw states (``fill`` is not applied to them: it is only carried)."""
        flat = states.reshape(-1, states.shape[-1]).double()
        return cls(flat.mean(0).float(), flat.std(0).clamp_min(min_scale).float(), keys, fill)

    def with_keys(self, keys) -> "StateNormalizer":
        """The same map (statistics and fill) on other keys."""
        return StateNormalizer(self.loc, self.scale, keys, self.fill)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        if self.fill is not None:
            x = self.fill.mask(x)
        return (x - self.loc.to(x.device)) / self.scale.to(x.device)

    def __call__(self, td):
        for key in self.keys:
            if key in td.keys():
                td.set(key, self.normalize(td.get(key)))
        return td

    def state_dict(self) -> dict:
        """Plain tensors and lists; ``"fill"`` only with a fill (earlier files have no such key)."""
        state = {"loc": self.loc.clone(), "scale": self.scale.clone(), "keys": list(self.keys)}
        if self.fill is not None:
            state["fill"] = self.fill.state_dict()
        return state

    @classmethod
    def from_state_dict(cls, state: Mapping[str, Any]) -> "StateNormalizer":
        fill = state.get("fill")
        return cls(state["loc"], state["scale"], state.get("keys", ("state",)),
                   None if fill is None else OutOfViewFill.from_state_dict(fill))


class ProprioceptionOverride:
    """Replace ``dims`` of ``dst`` (the encoder's estimate) by the same dims of ``src`` (the true
    state): the picker positions are known to the robot without vision. Callable on TensorDicts
    (windows or env steps); returns the TensorDict."""

    def __init__(self, dims, src: str = "state", dst: str = "state_estimate"):
        self.dims = torch.as_tensor(list(dims), dtype=torch.long)
        self.src, self.dst = src, dst

    def __call__(self, td):
        if self.dims.numel() and self.dst in td.keys():
            if self.src not in td.keys():
                raise KeyError(f"ProprioceptionOverride: {self.src!r} is needed to fill dims {self.dims.tolist()} of {self.dst!r}")
            est = td.get(self.dst).clone()
            est[..., self.dims] = td.get(self.src)[..., self.dims].to(est.dtype)
            td.set(self.dst, est)
        return td


def chain(*steps: Callable[[Any], Any] | None) -> Callable[[Any], Any]:
    """One callable applying ``steps`` (callables on a TensorDict, each returning it) in order,
    skipping ``None`` (an optional step that is off); none: the identity."""
    steps = tuple(step for step in steps if step is not None)

    def apply(td):
        for step in steps:
            td = step(td)
        return td

    return apply
