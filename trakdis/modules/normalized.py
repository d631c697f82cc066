"""Wrappers that let a model trained on standardised values act on, or return, raw values.

* :class:`NormalizedPolicy`: a policy run on the standardised observation (a state normaliser:
  TorchRL's ``ObservationNorm``, see :func:`~trakdis.transforms.state_normalizer`; optionally after a
  :class:`~trakdis.transforms.ProprioceptionOverride`), the raw value put back afterwards.
* :class:`NormalizedEncoder`: ``encoder(pixels) * std + mean`` (the CNN regresses standardised states).
"""
from __future__ import annotations

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.envs.transforms import Transform

from trakdis.transforms.normalization import normalizer_with_keys

__all__ = ["NormalizedEncoder", "NormalizedPolicy"]


class NormalizedPolicy(TensorDictModuleBase):
    """Run ``policy`` on the normalised ``key`` (after the optional ``pre`` map, e.g. a
    :class:`ProprioceptionOverride`) and put the raw value back afterwards.

    ``normalizer``: a state normaliser (``ObservationNorm``, or ``Compose(OutOfViewFill, ObservationNorm)``;
    :func:`~trakdis.transforms.state_normalizer`), applied to ``key`` alone whatever its keys (a copy on
    ``[key]`` is kept). The raw value put back is the tensor read before, not
    ``ObservationNorm``'s inverse (``state * scale + loc``): that rounds, and the mask has none."""

    def __init__(self, policy: nn.Module, normalizer: Transform | None, key: str, pre=None):
        super().__init__()
        self.policy = policy
        self.normalizer = None if normalizer is None else normalizer_with_keys(normalizer, [key])
        self.key = key
        self.pre = pre
        self.in_keys = list(getattr(policy, "in_keys", [key]))
        self.out_keys = list(getattr(policy, "out_keys", ["action"]))

    def forward(self, tensordict):
        raw = tensordict.get(self.key)
        if self.pre is not None:
            self.pre(tensordict)
        if self.normalizer is not None:
            value = tensordict.get(self.key)
            tensordict.set(self.key, self.normalizer(TensorDict({self.key: value}, batch_size=[])).get(self.key))
        try:
            tensordict = self.policy(tensordict)
        finally:
            tensordict.set(self.key, raw)
        return tensordict


class NormalizedEncoder(nn.Module):
    """``encoder(pixels) * std + mean``: the CNN regresses standardised states, this returns raw ones.

    Not TorchRL's ``ObservationNorm(mean, std)`` (whose default map, ``obs * scale + loc``, is this one):
    that maps TensorDict entries, this maps the tensor inside an encoder (``EncoderTransform``,
    ``EncoderEnsemble`` members), and its buffers ``mean`` / ``std`` are the state-dict entries every
    encoder file holds."""

    def __init__(self, encoder: nn.Module, mean: torch.Tensor, std: torch.Tensor):
        super().__init__()
        self.encoder = encoder
        self.register_buffer("mean", torch.as_tensor(mean, dtype=torch.float32).clone())
        self.register_buffer("std", torch.as_tensor(std, dtype=torch.float32).clone())

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.encoder(pixels) * self.std + self.mean
