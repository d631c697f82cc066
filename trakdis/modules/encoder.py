"""CNN state encoder: RGB image -> reduced state (TraKDis' F_c)."""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

__all__ = ["StateEncoder", "to_float_chw"]


def to_float_chw(pixels: torch.Tensor, *, name: str = "pixels") -> torch.Tensor:
    """Convert uint8 ``[*B, H, W, 3]`` (HWC, 0..255) or float ``[*B, 3, H, W]`` (CHW, 0..1) to float CHW.

    Raises a ``ValueError`` naming the shape and dtype for anything else (e.g. uint8 CHW or float HWC).
    """
    if pixels.dtype == torch.uint8:
        if pixels.dim() < 3 or pixels.shape[-1] != 3:
            raise ValueError(
                f"{name}: uint8 images must be HWC [*B, H, W, 3], got shape {tuple(pixels.shape)} dtype {pixels.dtype}"
            )
        return pixels.movedim(-1, -3).float().div_(255.0)
    if pixels.dtype.is_floating_point:
        if pixels.dim() < 3 or pixels.shape[-3] != 3:
            raise ValueError(
                f"{name}: float images must be CHW [*B, 3, H, W] with values in [0, 1], "
                f"got shape {tuple(pixels.shape)} dtype {pixels.dtype}"
            )
        return pixels
    raise ValueError(f"{name}: expected uint8 HWC or float CHW images, got dtype {pixels.dtype} shape {tuple(pixels.shape)}")


class StateEncoder(nn.Module):
    """4-layer CNN mapping an RGB image to the reduced state.

    Conv(3->c0, 3x3, stride 2) then three Conv(3x3, stride 1), ReLU after each (DrQ/SAC-AE style),
    flatten, Linear -> LayerNorm -> ReLU -> Linear(state_dim).

    Args:
        state_dim: output width.
        image_size: input height and width (square images; default 32 as in the paper).
        channels: output channels of the four conv layers.
        hidden_dim: width of the MLP head.

    Input: uint8 ``[*B, H, W, 3]`` (env ``"pixels"``) or float ``[*B, 3, H, W]`` in [0, 1];
    output ``[*B, state_dim]``.
    """

    def __init__(self, state_dim: int, *, image_size: int = 32, channels: Sequence[int] = (32, 32, 32, 32), hidden_dim: int = 256):
        super().__init__()
        if len(channels) != 4:
            raise ValueError(f"StateEncoder has 4 conv layers; got channels={tuple(channels)}")
        if image_size < 11:
            raise ValueError(f"image_size={image_size} is too small for 4 conv layers (>= 11)")
        self.state_dim = state_dim
        self.image_size = image_size
        layers, c_in = [], 3
        for i, c_out in enumerate(channels):
            layers += [nn.Conv2d(c_in, c_out, kernel_size=3, stride=2 if i == 0 else 1), nn.ReLU()]
            c_in = c_out
        self.convs = nn.Sequential(*layers)
        side = (image_size - 3) // 2 + 1 - 3 * 2
        self.head = nn.Sequential(
            nn.Flatten(),
            nn.Linear(c_in * side * side, hidden_dim),
            nn.LayerNorm(hidden_dim),
            nn.ReLU(),
            nn.Linear(hidden_dim, state_dim),
        )

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        x = to_float_chw(pixels)
        if tuple(x.shape[-2:]) != (self.image_size, self.image_size):
            raise ValueError(
                f"StateEncoder(image_size={self.image_size}) got images of size {tuple(x.shape[-2:])} "
                f"(input shape {tuple(pixels.shape)}, dtype {pixels.dtype}); resize them first"
            )
        lead = x.shape[:-3]
        x = x.reshape(-1, *x.shape[-3:])
        return self.head(self.convs(x)).reshape(*lead, self.state_dim)
