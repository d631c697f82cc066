"""A frozen image encoder as a TorchRL transform: pixel keys -> estimated states."""

from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import dispatch
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


def _key_list(keys, name: str) -> list:
    # one NestedKey (a str or a tuple) is one key, as for every TorchRL transform
    keys = [keys] if isinstance(keys, (str, tuple)) else list(keys)
    if not keys:
        raise ValueError(f"EncoderTransform: {name} is empty")
    return keys


class EncoderTransform(ObservationTransform):
    """Runs a frozen encoder on pixel keys and writes estimated states (TorchRL ``Transform``).

    For each ``(in_key, out_key)`` pair (e.g. one per camera) the transform reads ``in_key`` (e.g.
    ``"pixels"`` ``[*B, H, W, 3]`` uint8, or whatever image layout the encoder accepts), flattens
    the batch dims, runs the one encoder under ``torch.no_grad()`` in eval mode, in chunks of at
    most ``max_batch`` images, on the encoder's device (inputs are moved there and results moved
    back to the input's device), and writes ``out_key`` ``[*B, D]``. It works on any batch shape,
    so the same instance serves a ``TransformedEnv`` (single, ``SerialEnv``/``ParallelEnv``; it
    pickles with its encoder), a collector, and a replay buffer (windows ``[B, K, H, W, 3]`` ->
    ``[B, K, D]``).

    The encoder is deliberately *not* registered as a submodule: ``TransformedEnv`` moves its
    transforms to the env's device (``transform.to(env.device)``), which would silently pull a GPU
    encoder onto the CPU of a CPU env. It therefore stays where you put it (``encoder.to(...)`` or
    ``device=``), and it is not part of the transform's ``state_dict`` (it is frozen; save it
    separately). It is pickled with the transform.

    Each output spec is ``Unbounded(shape=[*B, D])``; ``D`` and the dtype come from ``out_dim``/
    ``dtype`` or, when not given, from one dry run of the encoder on a zero image of the input
    spec. Lazy modules (``nn.LazyConv2d``, ``nn.LazyLinear``, ...) are initialised by that dry run
    (or by the first call, e.g. on replay-buffer samples); pass ``device=`` or move the encoder
    before the first call.

    Why not TorchRL's ``ModuleTransform`` (checked in 0.14): it needs the output specs written by
    hand, registers the module as a submodule (so ``env.to(...)`` moves it), and calls the module on
    the tensordict's own batch shape, while an image encoder takes ``[N, *image]``; this transform
    infers the specs, keeps the encoder where it is, and flattens/chunks any batch shape.
    (``VIPTransform``/``R3MTransform`` wrap fixed pretrained torchvision networks.)

    Args:
        encoder: the image encoder (``nn.Module``, ``[N, *image] -> [N, D]``); it is put in eval mode
            and its parameters are frozen (``requires_grad_(False)``); ``.train()`` on the transform
            keeps it in eval mode.
        in_keys: pixel keys to read (default ``["pixels"]``).
        out_keys: keys to write, one per in_key (default ``["state_estimate"]`` for a single
            in_key; required with several).

    Keyword Args:
        out_dim: size of the encoder output (inferred by a dry run when ``None``).
        dtype: output dtype (default: the encoder's output dtype, float32 in practice).
        max_batch: at most this many images per encoder call (bounds memory on long windows).
        freeze: set ``requires_grad_(False)`` on the encoder (default True).
        device: if given, the encoder is moved there once, at construction.

    Examples:
        >>> env = TransformedEnv(base_env, EncoderTransform(encoder, in_keys=["pixels_left", "pixels_right"],
        ...                                                 out_keys=["estimate_left", "estimate_right"]))
    """

    def __init__(
        self,
        encoder: nn.Module,
        in_keys: Sequence[NestedKey] | None = None,
        out_keys: Sequence[NestedKey] | None = None,
        *,
        out_dim: int | None = None,
        dtype: torch.dtype | None = None,
        max_batch: int = 4096,
        freeze: bool = True,
        device: torch.device | str | None = None,
    ):
        if not isinstance(encoder, nn.Module):
            raise TypeError(f"EncoderTransform: encoder must be an nn.Module, got {type(encoder).__name__}")
        in_keys = ["pixels"] if in_keys is None else _key_list(in_keys, "in_keys")
        if out_keys is None:
            if len(in_keys) != 1:
                raise ValueError(f"EncoderTransform: with several in_keys {in_keys}, pass one out_key each (out_keys=)")
            out_keys = ["state_estimate"]
        out_keys = _key_list(out_keys, "out_keys")
        if len(out_keys) != len(in_keys):
            raise ValueError(f"EncoderTransform: in_keys {in_keys} and out_keys {out_keys} differ in length")
        if len(set(out_keys)) != len(out_keys):
            raise ValueError(f"EncoderTransform: out_keys {out_keys} repeat a key")
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        if device is not None:
            encoder = encoder.to(device)
        object.__setattr__(self, "_encoder", encoder)  # not a submodule: see the class docstring
        if freeze:
            for param in encoder.parameters():
                # attribute, not requires_grad_(): a lazy module's uninitialised parameters allow only
                # this, and keep it once materialised
                param.requires_grad = False
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

    @torch.no_grad()
    def encode(self, pixels: torch.Tensor, event_ndim: int = 3, key: NestedKey = "pixels") -> torch.Tensor:
        """Encodes ``pixels`` ``[*B, *image_shape]`` (``image_shape`` has ``event_ndim`` dims) to ``[*B, D]``.

        ``key`` only names the input in error messages.
        """
        if pixels.ndim < event_ndim:
            raise ValueError(
                f"EncoderTransform: {key!r} has shape {tuple(pixels.shape)}, expected at least "
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
                    f"{getattr(out, 'shape', type(out))} for input {tuple(chunk.shape)} from {key!r}"
                )
            outs.append(out)
        out = torch.cat(outs, 0) if len(outs) > 1 else outs[0]
        if self.out_dim is not None and out.shape[-1] != self.out_dim:
            raise RuntimeError(
                f"EncoderTransform: the encoder returns {out.shape[-1]} features for {key!r}, expected out_dim={self.out_dim}"
            )
        if self.out_dtype is not None:
            out = out.to(self.out_dtype)
        out = out.to(pixels.device)
        return out.reshape(*batch, out.shape[-1])

    def _apply_transform(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.encode(pixels)

    def _encode_keys(self, tensordict: TensorDictBase) -> TensorDictBase:
        for in_key, out_key in zip(self.in_keys, self.out_keys):
            pixels = tensordict.get(in_key, None)
            if pixels is None:
                if self.missing_tolerance:
                    continue
                raise KeyError(f"EncoderTransform: {in_key!r} is missing (keys: {list(tensordict.keys(True, True))})")
            tensordict.set(out_key, self.encode(pixels, key=in_key))
        return tensordict

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._encode_keys(next_tensordict)

    @dispatch(source="in_keys", dest="out_keys")
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self._encode_keys(tensordict)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def _out_dim_and_dtype(self, pixel_spec: TensorSpec, key: NestedKey) -> tuple[int, torch.dtype]:
        if self.out_dim is not None and self.out_dtype is not None:
            return self.out_dim, self.out_dtype
        sample = pixel_spec.zero()
        sample = sample.reshape(-1, *sample.shape[-3:])[:1]
        out = self.encode(sample, key=key)  # also initialises lazy modules
        self.out_dim = int(out.shape[-1])
        self.out_dtype = out.dtype if self.out_dtype is None else self.out_dtype
        return self.out_dim, self.out_dtype

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        keys = list(observation_spec.keys(True, True))
        for in_key, out_key in zip(self.in_keys, self.out_keys):
            if in_key not in keys:
                raise KeyError(f"EncoderTransform: the pixel key {in_key!r} is not in the observation spec (keys: {keys})")
            pixel_spec = observation_spec[in_key]
            if len(pixel_spec.shape) < 3:
                raise ValueError(
                    f"EncoderTransform: the spec of {in_key!r} has shape {tuple(pixel_spec.shape)}, expected an image "
                    f"[*B, H, W, C] or [*B, C, H, W]"
                )
            dim, dtype = self._out_dim_and_dtype(pixel_spec, in_key)
            shape = torch.Size([*pixel_spec.shape[: len(pixel_spec.shape) - 3], dim])
            observation_spec[out_key] = Unbounded(shape=shape, dtype=dtype, device=pixel_spec.device)
        return observation_spec

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(encoder={type(self.encoder).__name__}, in_keys={self.in_keys}, "
            f"out_keys={self.out_keys}, out_dim={self.out_dim})"
        )
