"""Wrappers that let a model trained on standardised values act on, or return, raw values.

* :class:`NormalizedPolicy`: a policy run on the standardised observation (a
  :class:`~trakdis.transforms.StateNormalizer`, optionally after a
  :class:`~trakdis.transforms.ProprioceptionOverride`), the raw value put back afterwards.
* :class:`NormalizedEncoder`: ``encoder(pixels) * std + mean`` (the CNN regresses standardised states).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from tensordict.nn import TensorDictModuleBase
from torch import nn

if TYPE_CHECKING:
    from trakdis.transforms.normalization import StateNormalizer

__all__ = ["NormalizedEncoder", "NormalizedPolicy"]


class NormalizedPolicy(TensorDictModuleBase):
    """Run ``policy`` on the normalised ``key`` (after the optional ``pre`` map, e.g. a
    :class:`ProprioceptionOverride`) and put the raw value back afterwards."""

    def __init__(self, policy: nn.Module, normalizer: StateNormalizer | None, key: str, pre=None):
        super().__init__()
        self.policy = policy
        self.normalizer = normalizer
        self.key = key
        self.pre = pre
        self.in_keys = list(getattr(policy, "in_keys", [key]))
        self.out_keys = list(getattr(policy, "out_keys", ["action"]))

    def forward(self, tensordict):
        raw = tensordict.get(self.key)
        if self.pre is not None:
            self.pre(tensordict)
        value = tensordict.get(self.key)
        tensordict.set(self.key, value if self.normalizer is None else self.normalizer.normalize(value))
        try:
            tensordict = self.policy(tensordict)
        finally:
            tensordict.set(self.key, raw)
        return tensordict


class NormalizedEncoder(nn.Module):
    """``encoder(pixels) * std + mean``: the CNN regresses standardised states, this returns raw ones."""

    def __init__(self, encoder: nn.Module, mean: torch.Tensor, std: torch.Tensor):
        super().__init__()
        self.encoder = encoder
        self.register_buffer("mean", torch.as_tensor(mean, dtype=torch.float32).clone())
        self.register_buffer("std", torch.as_tensor(std, dtype=torch.float32).clone())

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.encoder(pixels) * self.std + self.mean
