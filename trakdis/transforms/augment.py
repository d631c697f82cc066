"""Image augmentations (random shift, horizontal flip) with consistent label transforms: the state
encoder's training augmentation (:class:`~trakdis.objectives.EncoderLoss`) and the image trunk's random shift.

All functions take float CHW images ``[N, C, H, W]`` (see :func:`trakdis.modules.to_float_chw`).
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

__all__ = ["random_shift", "horizontal_flip", "mirror_state", "random_flip"]


def random_shift(images: torch.Tensor, pad: int, *, generator: torch.Generator | None = None) -> torch.Tensor:
    """DrQ random shift: replicate-pad by ``pad`` pixels, then crop back a random ``H x W`` window.

    Each image gets its own integer shift in ``[-pad, pad]`` along both axes.
    """
    if pad <= 0:
        return images
    n, c, h, w = images.shape
    padded = F.pad(images, (pad, pad, pad, pad), mode="replicate")
    off = torch.randint(0, 2 * pad + 1, (n, 2), generator=generator, device="cpu").to(images.device)
    rows = off[:, 0, None] + torch.arange(h, device=images.device)  # [N, H]
    cols = off[:, 1, None] + torch.arange(w, device=images.device)  # [N, W]
    batch = torch.arange(n, device=images.device)[:, None, None]
    out = padded[batch, :, rows[:, :, None], cols[:, None, :]]  # [N, H, W, C]
    return out.permute(0, 3, 1, 2).contiguous()


def horizontal_flip(images: torch.Tensor, flip: torch.Tensor | None = None) -> torch.Tensor:
    """Mirror images left-right (along W); only rows where ``flip`` (bool ``[N]``) is True if given."""
    flipped = images.flip(-1)
    if flip is None:
        return flipped
    return torch.where(flip.view(-1, 1, 1, 1), flipped, images)


def mirror_state(state: torch.Tensor, perm: Sequence[int] | torch.Tensor, sign: Sequence[float] | torch.Tensor,
                 flip: torch.Tensor | None = None) -> torch.Tensor:
    """Reduced state of the mirrored scene: ``state[..., perm] * sign`` (rows where ``flip`` if given).

    ``(perm, sign)`` is ``trakdis.envs.task_spec(task).state_mirror``: the permutation swaps
    corner/picker identities and ``sign`` negates the coordinate that the image flip mirrors.
    """
    perm = torch.as_tensor(perm, dtype=torch.long, device=state.device)
    sign = torch.as_tensor(sign, dtype=state.dtype, device=state.device)
    if perm.shape != (state.shape[-1],) or sign.shape != (state.shape[-1],):
        raise ValueError(
            f"state_mirror perm/sign must both have length state_dim={state.shape[-1]}, "
            f"got {tuple(perm.shape)} and {tuple(sign.shape)}"
        )
    mirrored = state[..., perm] * sign
    if flip is None:
        return mirrored
    return torch.where(flip.view(-1, *([1] * (state.dim() - 1))), mirrored, state)


def random_flip(images: torch.Tensor, state: torch.Tensor, perm, sign, prob: float = 0.5,
                *, generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Flip each (image, state) pair with probability ``prob``, keeping labels consistent."""
    flip = (torch.rand(images.shape[0], generator=generator) < prob).to(images.device)
    return horizontal_flip(images, flip), mirror_state(state, perm, sign, flip)
