"""A frozen image encoder as a TorchRL transform: pixels -> estimated state."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Composite, TensorSpec, Unbounded
from torchrl.envs.transforms import ObservationTransform

__all__ = ["EncoderTransform"]


def _module_device(module: nn.Module) -> torch.device | None:
    for t in module.parameters():
        return t.device
    for t in module.buffers():
        return t.device
    return None


class EncoderTransform(ObservationTransform):
    """Runs a frozen encoder on a pixel key and writes the estimated state (TorchRL ``Transform``).

    The transform reads ``in_key`` (e.g. ``"pixels"`` ``[*B, H, W, 3]`` uint8, or whatever image
    layout the encoder accepts), flattens the batch dims, runs the encoder under ``torch.no_grad()``
    in eval mode, in chunks of at most ``max_batch`` images, on the encoder's device (inputs are moved
    there and results moved back to the input's device), and writes ``out_key`` ``[*B, D]``.
    It works on any batch shape, so the same instance serves a ``TransformedEnv`` (single,
    ``SerialEnv``/``ParallelEnv``; it pickles with its encoder), a collector, and a replay buffer
    (windows ``[B, K, H, W, 3]`` -> ``[B, K, D]``).

    The encoder is deliberately *not* registered as a submodule: ``TransformedEnv`` moves its
    transforms to the env's device (``transform.to(env.device)``), which would silently pull a GPU
    encoder onto the CPU of a CPU env. It therefore stays where you put it (``encoder.to(...)`` or
    ``device=``), and it is not part of the transform's ``state_dict`` (it is frozen; save it
    separately). It is pickled with the transform.

    The output spec is ``Unbounded(shape=[*B, D])``; ``D`` and the dtype come from ``out_dim``/
    ``dtype`` or, when not given, from one dry run of the encoder on a zero image of the input spec.

    Args:
        encoder: the image encoder (``nn.Module``); it is put in eval mode and its parameters are
            frozen (``requires_grad_(False)``); ``.train()`` on the transform keeps it in eval mode.
        in_key: pixel key to read (default ``"pixels"``).
        out_key: key to write (default ``"state_estimate"``).
        out_dim: size of the encoder output (inferred by a dry run when ``None``).
        dtype: output dtype (default: the encoder's output dtype, float32 in practice).
        max_batch: at most this many images per encoder call (bounds memory on long windows).
        freeze: set ``requires_grad_(False)`` on the encoder (default True).
        device: if given, the encoder is moved there once, at construction.
    """

    def __init__(
        self,
        encoder: nn.Module,
        in_key: NestedKey = "pixels",
        out_key: NestedKey = "state_estimate",
        out_dim: int | None = None,
        dtype: torch.dtype | None = None,
        max_batch: int = 4096,
        freeze: bool = True,
        device: torch.device | str | None = None,
    ):
        if not isinstance(encoder, nn.Module):
            raise TypeError(f"EncoderTransform: encoder must be an nn.Module, got {type(encoder).__name__}")
        super().__init__(in_keys=[in_key], out_keys=[out_key])
        if device is not None:
            encoder = encoder.to(device)
        object.__setattr__(self, "_encoder", encoder)  # not a submodule: see the class docstring
        if freeze:
            encoder.requires_grad_(False)
        encoder.eval()
        self.out_dim = None if out_dim is None else int(out_dim)
        self.out_dtype = dtype
        if max_batch < 1:
            raise ValueError(f"EncoderTransform: max_batch must be >= 1, got {max_batch}")
        self.max_batch = int(max_batch)

    def train(self, mode: bool = True):
        super().train(mode)
        self.encoder.eval()  # frozen: never switch dropout/batch-norm to training behaviour
        return self

    @property
    def encoder(self) -> nn.Module:
        return self._encoder

    @property
    def in_key(self) -> NestedKey:
        return self.in_keys[0]

    @property
    def out_key(self) -> NestedKey:
        return self.out_keys[0]

    @torch.no_grad()
    def encode(self, pixels: torch.Tensor, event_ndim: int = 3) -> torch.Tensor:
        """Encodes ``pixels`` ``[*B, *image_shape]`` (``image_shape`` has ``event_ndim`` dims) to ``[*B, D]``."""
        if pixels.ndim < event_ndim:
            raise ValueError(
                f"EncoderTransform: {self.in_key!r} has shape {tuple(pixels.shape)}, expected at least "
                f"{event_ndim} image dims"
            )
        batch = pixels.shape[: pixels.ndim - event_ndim]
        flat = pixels.reshape(-1, *pixels.shape[pixels.ndim - event_ndim :])
        device = _module_device(self.encoder)
        outs = []
        for start in range(0, max(flat.shape[0], 1), self.max_batch):
            chunk = flat[start : start + self.max_batch]
            if device is not None and chunk.device != device:
                chunk = chunk.to(device, non_blocking=True)
            out = self.encoder(chunk)
            if not isinstance(out, torch.Tensor) or out.ndim != 2 or out.shape[0] != chunk.shape[0]:
                raise RuntimeError(
                    f"EncoderTransform: the encoder must map [N, *image] to [N, D]; got "
                    f"{getattr(out, 'shape', type(out))} for input {tuple(chunk.shape)} from {self.in_key!r}"
                )
            outs.append(out)
        out = torch.cat(outs, 0) if len(outs) > 1 else outs[0]
        if self.out_dtype is not None:
            out = out.to(self.out_dtype)
        out = out.to(pixels.device)
        return out.reshape(*batch, out.shape[-1])

    def _apply_transform(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.encode(pixels)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def _out_dim_and_dtype(self, pixel_spec: TensorSpec) -> tuple[int, torch.dtype]:
        if self.out_dim is not None and self.out_dtype is not None:
            return self.out_dim, self.out_dtype
        sample = pixel_spec.zero()
        sample = sample.reshape(-1, *sample.shape[-3:])[:1]
        out = self.encode(sample)
        self.out_dim = int(out.shape[-1]) if self.out_dim is None else self.out_dim
        if self.out_dim != out.shape[-1]:
            raise ValueError(f"EncoderTransform: out_dim={self.out_dim} but the encoder returns {out.shape[-1]} features")
        self.out_dtype = out.dtype if self.out_dtype is None else self.out_dtype
        return self.out_dim, self.out_dtype

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        if self.in_key not in observation_spec.keys(True, True):
            raise KeyError(
                f"EncoderTransform: the pixel key {self.in_key!r} is not in the observation spec "
                f"(keys: {list(observation_spec.keys(True, True))})"
            )
        pixel_spec = observation_spec[self.in_key]
        dim, dtype = self._out_dim_and_dtype(pixel_spec)
        shape = torch.Size([*pixel_spec.shape[: len(pixel_spec.shape) - 3], dim])
        observation_spec[self.out_key] = Unbounded(shape=shape, dtype=dtype, device=pixel_spec.device)
        return observation_spec

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(encoder={type(self.encoder).__name__}, in_key={self.in_key!r}, "
            f"out_key={self.out_key!r}, out_dim={self.out_dim})"
        )
