"""Random Decision Transformer training windows for the tests (layout: docs/design.md).

``tests/`` is on ``sys.path`` because ``tests/conftest.py`` lives there (pytest's default import
mode), so test modules import this as ``from dt_windows import random_window``.
"""
from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDict


def random_window(
    batch: int,
    context: int,
    state_dim: int,
    action_dim: int,
    *,
    pad: Sequence[int] | None = None,
    seed: int = 0,
    generator: torch.Generator | None = None,
    state_keys: Sequence[str] = ("observation",),
    pixels: int | None = None,
) -> TensorDict:
    """A ``[batch, context]`` window: one ``randn`` state per key in ``state_keys``, optional uint8
    ``pixels`` of side ``pixels``, actions inside (-0.9, 0.9), ``return_to_go``, ``timestep`` and a
    ``mask`` whose row ``i`` is left-padded by ``pad[i]`` steps."""
    g = generator or torch.Generator().manual_seed(seed)
    mask = torch.ones(batch, context, dtype=torch.bool)
    for i, p in enumerate(pad or ()):
        mask[i, :p] = False
    data = {key: torch.randn(batch, context, state_dim, generator=g) for key in state_keys}
    if pixels is not None:
        data["pixels"] = torch.randint(0, 256, (batch, context, pixels, pixels, 3), dtype=torch.uint8, generator=g)
    data["action"] = torch.rand(batch, context, action_dim, generator=g) * 1.8 - 0.9
    data["return_to_go"] = torch.randn(batch, context, 1, generator=g)
    data["timestep"] = torch.arange(context).expand(batch, context).clone()
    data["mask"] = mask
    return TensorDict(data, batch_size=[batch, context])
