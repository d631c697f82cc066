"""Anti-aliased resizing of pixel observations."""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded, TensorSpec, Unbounded
from torchrl.envs.transforms import ObservationTransform
from torchrl.envs.transforms.transforms import _apply_to_composite

__all__ = ["ImageResize", "resize_images"]

_CHANNEL_SIZES = (1, 3, 4)


def _channels_last(shape: Sequence[int], channels_last: bool | None, key=None) -> bool:
    if channels_last is not None:
        return bool(channels_last)
    if len(shape) < 3:
        raise ValueError(f"ImageResize: {key!r} has shape {tuple(shape)}; expected [..., H, W, C] or [..., C, H, W]")
    if shape[-1] in _CHANNEL_SIZES:
        return True
    if shape[-3] in _CHANNEL_SIZES:
        return False
    raise ValueError(
        f"ImageResize: cannot tell the channel axis of {key!r} with shape {tuple(shape)} (neither the last "
        f"nor the third-to-last dim is 1, 3 or 4); pass channels_last=True/False"
    )


def resize_images(
    images: torch.Tensor,
    size: tuple[int, int],
    *,
    channels_last: bool | None = None,
    mode: str = "bilinear",
) -> torch.Tensor:
    """Resizes images of any batch shape with anti-aliasing.

    Args:
        images: ``[..., H, W, C]`` (channels last) or ``[..., C, H, W]``, uint8 or floating point.
        size: ``(height, width)`` of the result.
        channels_last: layout; ``None`` detects it (C in {1, 3, 4} on the last, else third-to-last dim).
        mode: ``"bilinear"``/``"bicubic"`` (with ``antialias=True``) or ``"area"`` (box average,
            OpenCV's ``INTER_AREA`` for integer factors).

    uint8 inputs are resized in float32, rounded and clamped back to uint8; floating inputs keep their dtype.
    """
    h, w = int(size[0]), int(size[1])
    cl = _channels_last(images.shape, channels_last)
    x = images.movedim(-1, -3) if cl else images
    if tuple(x.shape[-2:]) == (h, w):
        return images.clone()
    batch = x.shape[:-3]
    x = x.reshape(-1, *x.shape[-3:])
    dtype = x.dtype
    xf = x.float() if not dtype.is_floating_point else x
    if xf.numel() == 0:
        out = xf.new_zeros(*xf.shape[:-2], h, w)
    elif mode == "area":
        out = F.interpolate(xf, size=(h, w), mode="area")
    elif mode in ("bilinear", "bicubic"):
        out = F.interpolate(xf, size=(h, w), mode=mode, antialias=True, align_corners=False)
    else:
        raise ValueError(f"ImageResize: unknown mode {mode!r}; use 'bilinear', 'bicubic' or 'area'")
    if dtype == torch.uint8:
        out = out.round_().clamp_(0, 255).to(torch.uint8)
    elif not dtype.is_floating_point:
        out = out.round_().to(dtype)
    else:
        out = out.to(dtype)
    out = out.reshape(*batch, *out.shape[-3:])
    return out.movedim(-3, -1) if cl else out


class ImageResize(ObservationTransform):
    """Resizes pixel observations with anti-aliasing (TorchRL ``Transform``).

    Works on uint8 or float images, channels-last ``[*B, H, W, C]`` or channels-first
    ``[*B, C, H, W]``, with any batch shape (so also on replay-buffer windows ``[B, K, H, W, C]``);
    dtype and layout are kept, and the observation spec is updated to the new size.

    TorchRL's own ``Resize`` needs torchvision (not a dependency here) and channels-first images,
    hence this transform, which uses ``torch.nn.functional.interpolate(..., antialias=True)``.

    Args:
        in_keys: pixel keys to read (default ``["pixels"]``).
        out_keys: keys to write (default: ``in_keys``, i.e. in place).
        size: output size, an int (square) or ``(height, width)``. Default 32.
        channels_last: image layout; ``None`` (default) detects it from the shape.
        mode: ``"bilinear"`` (default), ``"bicubic"`` or ``"area"``.

    Examples:
        >>> env = TransformedEnv(base_env, ImageResize(in_keys=["pixels"], size=32))
    """

    def __init__(
        self,
        in_keys: Sequence[NestedKey] | None = None,
        out_keys: Sequence[NestedKey] | None = None,
        size: int | Sequence[int] = 32,
        channels_last: bool | None = None,
        mode: str = "bilinear",
    ):
        if in_keys is None:
            in_keys = ["pixels"]
        if out_keys is None:
            out_keys = list(in_keys)
        if len(out_keys) != len(in_keys):
            raise ValueError(f"ImageResize: in_keys {in_keys} and out_keys {out_keys} differ in length")
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        if isinstance(size, int):
            size = (size, size)
        size = tuple(int(s) for s in size)
        if len(size) != 2 or min(size) <= 0:
            raise ValueError(f"ImageResize: size must be a positive int or (height, width), got {size}")
        if mode not in ("bilinear", "bicubic", "area"):
            raise ValueError(f"ImageResize: unknown mode {mode!r}; use 'bilinear', 'bicubic' or 'area'")
        self.size = size
        self.channels_last = channels_last
        self.mode = mode

    def _apply_transform(self, obs: torch.Tensor) -> torch.Tensor:
        return resize_images(obs, self.size, channels_last=self.channels_last, mode=self.mode)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    @_apply_to_composite
    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        shape = list(observation_spec.shape)
        cl = _channels_last(shape, self.channels_last)
        if cl:
            shape[-3:-1] = self.size
        else:
            shape[-2:] = self.size
        kw = dict(shape=torch.Size(shape), dtype=observation_spec.dtype, device=observation_spec.device)
        if isinstance(observation_spec, Bounded):
            low, high = observation_spec.space.low, observation_spec.space.high
            if (low == low.flatten()[0]).all() and (high == high.flatten()[0]).all():
                return Bounded(low=low.flatten()[0].item(), high=high.flatten()[0].item(), **kw)
            # per-pixel bounds: a weighted average of values lies between the averages of their bounds
            return Bounded(low=self._apply_transform(low), high=self._apply_transform(high), **kw)
        if isinstance(observation_spec, Unbounded):
            return Unbounded(**kw)
        raise TypeError(
            f"ImageResize: unsupported spec {type(observation_spec).__name__} for pixel keys {self.in_keys}"
        )

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(in_keys={self.in_keys}, out_keys={self.out_keys}, size={self.size}, "
            f"channels_last={self.channels_last}, mode={self.mode!r})"
        )
