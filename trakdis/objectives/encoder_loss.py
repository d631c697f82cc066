"""Supervised state-encoder loss with label-consistent augmentation."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.objectives import LossModule

from trakdis.modules.encoder import EncoderEnsemble, to_float_chw
from trakdis.transforms.augment import random_flip, random_shift

__all__ = ["EncoderLoss"]


class EncoderLoss(LossModule):
    r"""MSE regression of ``encoder(pixels)`` on the true reduced state, with augmentation.

    While the module is in training mode and ``augment=True`` each image is, independently:

    * randomly shifted by up to ``pad`` pixels (DrQ: replicate-pad then random crop). Labels are
      kept: the shift is used as a small-camera-jitter invariance (a regulariser, as in DrQ), not
      as a geometric transform of the scene; the implied label error is bounded by ``pad``
      pixels' worth of world distance, so keep ``pad`` small (default 2 of 32 pixels).
    * mirrored left-right with probability ``flip_prob`` if ``state_mirror=(perm, sign)`` is given;
      its labels become ``state[..., perm] * sign`` (``trakdis.envs.task_spec(task).state_mirror``:
      mirrored coordinates and swapped corner/picker identities). Without ``state_mirror`` no
      flip is done (flipping without relabelling would teach wrong labels).

    In eval mode (``loss.eval()``) no augmentation is applied, for validation.

    Args:
        encoder: a module mapping float CHW images ``[N, 3, H, W]`` to ``[N, state_dim]``
            (e.g. :class:`~trakdis.modules.StateEncoder`).

    Keyword Args:
        state_mirror: ``(perm, sign)`` or None.
        augment: enable augmentation (in training mode).
        flip_prob: probability of the mirror flip.
        pad: random-shift padding in pixels; 0 (default) disables the shift. A shift moves the scene
            in the image while the state labels stay, so it trains the encoder to ignore where things
            are (measured: docs/recipes/train_encoder.md); the flip transforms its labels, the shift cannot.
        in_key, target_key: set the ``pixels`` / ``state`` keys (also via ``set_keys``).

    With an :class:`~trakdis.modules.EncoderEnsemble` each member is trained on its own squared error
    (``loss_encoder``: their mean; the members' mirrored views are for acting, not trained), and
    ``mae`` is that of the members' mean estimate.

    Returns ``loss_encoder`` (MSE) and metric ``mae`` (detached), both averaged over batch and dims.
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys.

        Attributes:
            pixels: images, uint8 ``[*B, H, W, 3]`` or float ``[*B, 3, H, W]``. Defaults to ``"pixels"``.
            state: target reduced state ``[*B, state_dim]``. Defaults to ``"state"``.
        """

        pixels: NestedKey = "pixels"
        state: NestedKey = "state"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    def __init__(
        self,
        encoder: nn.Module,
        *,
        state_mirror: tuple[Sequence[int], Sequence[float]] | None = None,
        augment: bool = True,
        flip_prob: float = 0.5,
        pad: int = 0,
        in_key: NestedKey = "pixels",
        target_key: NestedKey = "state",
    ) -> None:
        super().__init__()
        if not 0.0 <= flip_prob <= 1.0:
            raise ValueError(f"flip_prob={flip_prob} must be in [0, 1]")
        if pad < 0:
            raise ValueError(f"pad={pad} must be >= 0")
        self.encoder = encoder
        if state_mirror is not None:
            perm, sign = state_mirror
            self.register_buffer("mirror_perm", torch.as_tensor(perm, dtype=torch.long))
            self.register_buffer("mirror_sign", torch.as_tensor(sign, dtype=torch.float32))
            if self.mirror_perm.shape != self.mirror_sign.shape or self.mirror_perm.dim() != 1:
                raise ValueError(f"state_mirror: perm and sign must be 1-D of equal length, got {tuple(self.mirror_perm.shape)} and {tuple(self.mirror_sign.shape)}")
            if sorted(self.mirror_perm.tolist()) != list(range(len(self.mirror_perm))):
                raise ValueError(f"state_mirror: perm {self.mirror_perm.tolist()} is not a permutation")
        else:
            self.mirror_perm = self.mirror_sign = None
        self.augment = augment
        self.flip_prob = float(flip_prob)
        self.pad = int(pad)
        self.set_keys(pixels=in_key, state=target_key)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self):
        return [self.tensor_keys.pixels, self.tensor_keys.state]

    @property
    def out_keys(self):
        return ["loss_encoder", "mae"]

    def augment_batch(self, images: torch.Tensor, state: torch.Tensor, *, generator: torch.Generator | None = None):
        """Apply the configured augmentation to float CHW ``images [N, 3, H, W]`` and ``state [N, D]``."""
        images = random_shift(images, self.pad, generator=generator)
        if self.mirror_perm is not None and self.flip_prob > 0:
            images, state = random_flip(images, state, self.mirror_perm, self.mirror_sign, self.flip_prob, generator=generator)
        return images, state

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        pixels = tensordict.get(self.tensor_keys.pixels)
        state = tensordict.get(self.tensor_keys.state)
        images = to_float_chw(pixels, name=str(self.tensor_keys.pixels))
        lead = images.shape[:-3]
        if tuple(state.shape[:-1]) != tuple(lead):
            raise ValueError(
                f"EncoderLoss: {self.tensor_keys.state!r} has shape {tuple(state.shape)} but "
                f"{self.tensor_keys.pixels!r} has batch shape {tuple(lead)}"
            )
        if self.mirror_perm is not None and state.shape[-1] != self.mirror_perm.numel():
            raise ValueError(f"EncoderLoss: state_mirror has {self.mirror_perm.numel()} entries but {self.tensor_keys.state!r} has width {state.shape[-1]}")
        images = images.reshape(-1, *images.shape[-3:])
        state = state.reshape(-1, state.shape[-1]).detach().to(images.dtype)
        if self.augment and self.training:
            images, state = self.augment_batch(images, state)
        if isinstance(self.encoder, EncoderEnsemble):  # each member learns from its own error (a deep ensemble)
            errs = [member(images) - state for member in self.encoder.members]
            loss = torch.stack([e.pow(2).mean() for e in errs]).mean()
            err = torch.stack(errs).mean(0)
        else:
            err = self.encoder(images) - state
            loss = err.pow(2).mean()
        return TensorDict({"loss_encoder": loss, "mae": err.detach().abs().mean()}, batch_size=[])
