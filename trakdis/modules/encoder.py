"""CNN state encoder: RGB image -> reduced state (TraKDis' F_c)."""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from trakdis.transforms.augment import mirror_state

__all__ = ["EncoderEnsemble", "SpatialSoftArgmax", "StateEncoder", "coordinate_channels", "to_float_chw"]


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


class SpatialSoftArgmax(nn.Module):
    """Expected image coordinates of each feature map (Levine et al. 2016, "deep spatial autoencoders").

    ``[N, C, H, W] -> [N, 2 C]``: for each channel, a softmax over its ``H x W`` positions (with a
    learned temperature) weights the pixel-centre coordinates in ``[-1, 1]``, giving ``(x, y)``. The
    result is sub-pixel and moves with the thing the map responds to, which a flatten + linear head
    on stride-2 features has to learn per position.
    """

    def __init__(self, height: int, width: int):
        super().__init__()
        ys = torch.linspace(-1.0, 1.0, height)
        xs = torch.linspace(-1.0, 1.0, width)
        grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
        self.register_buffer("grid", torch.stack([grid_x.reshape(-1), grid_y.reshape(-1)], dim=-1), persistent=False)
        self.log_temperature = nn.Parameter(torch.zeros(()))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        n, c = features.shape[:2]
        weights = torch.softmax(features.reshape(n, c, -1) / self.log_temperature.exp(), dim=-1)
        return (weights @ self.grid).reshape(n, 2 * c)


def coordinate_channels(x: torch.Tensor) -> torch.Tensor:
    """``[N, C, H, W] -> [N, C + 2, H, W]`` with the pixel's x and y in ``[-1, 1]`` (CoordConv, Liu et al. 2018)."""
    n, _, h, w = x.shape
    ys = torch.linspace(-1.0, 1.0, h, dtype=x.dtype, device=x.device).view(1, 1, h, 1).expand(n, 1, h, w)
    xs = torch.linspace(-1.0, 1.0, w, dtype=x.dtype, device=x.device).view(1, 1, 1, w).expand(n, 1, h, w)
    return torch.cat([x, xs, ys], dim=1)


class StateEncoder(nn.Module):
    """4-layer CNN mapping an RGB image to the reduced state (TraKDis' F_c).

    Default (DrQ/SAC-AE layout): Conv(3x3, stride 2) then three Conv(3x3, stride 1), ReLU after
    each, flatten, Linear -> LayerNorm -> ReLU -> Linear(state_dim).

    ``head="keypoints", stem_stride=1, coord_channels=True``: the image and two coordinate
    channels (CoordConv) go through four 3x3 convolutions that keep the full resolution; a spatial
    soft-argmax turns each of the last layer's maps into an ``(x, y)`` keypoint, which, with the
    maps' mean activations, feed the same MLP. Built to localise small things (corners, pickers a
    few pixels wide) to a fraction of a pixel; on the 40-episode ClothFold data it was not more
    precise than the default and 6x slower to train (docs/recipes/train_encoder.md).

    Args:
        state_dim: output width.
        image_size: input height and width (square images; default 32 as in the paper).
        channels: output channels of the four conv layers (the last one = number of keypoints).
        hidden_dim: width of the MLP head.
        head: ``"keypoints"`` (spatial soft-argmax) or ``"flatten"``.
        stem_stride: stride of the first conv layer (1 or 2).
        coord_channels: append pixel-coordinate channels to the input.

    Input: uint8 ``[*B, H, W, 3]`` (env ``"pixels"``) or float ``[*B, 3, H, W]`` in [0, 1];
    output ``[*B, state_dim]``.
    """

    def __init__(self, state_dim: int, *, image_size: int = 32, channels: Sequence[int] = (32, 32, 32, 32),
                 hidden_dim: int = 256, head: str = "flatten", stem_stride: int = 2, coord_channels: bool = False):
        super().__init__()
        if len(channels) != 4:
            raise ValueError(f"StateEncoder has 4 conv layers; got channels={tuple(channels)}")
        if head not in ("keypoints", "flatten"):
            raise ValueError(f"StateEncoder: head must be 'keypoints' or 'flatten', got {head!r}")
        if stem_stride not in (1, 2):
            raise ValueError(f"StateEncoder: stem_stride must be 1 or 2, got {stem_stride!r}")
        if image_size < 11:
            raise ValueError(f"image_size={image_size} is too small for 4 conv layers (>= 11)")
        self.state_dim = state_dim
        self.image_size = image_size
        self.config = {"state_dim": state_dim, "image_size": image_size, "channels": [int(c) for c in channels],
                       "hidden_dim": hidden_dim, "head": head, "stem_stride": stem_stride,
                       "coord_channels": bool(coord_channels)}
        self.coord_channels = bool(coord_channels)
        # "keypoints" keeps the resolution (padding 1); "flatten" is the earlier unpadded layout.
        padding = 1 if head == "keypoints" else 0
        layers, c_in = [], 3 + 2 * self.coord_channels
        side = image_size
        for i, c_out in enumerate(channels):
            stride = stem_stride if i == 0 else 1
            layers += [nn.Conv2d(c_in, c_out, kernel_size=3, stride=stride, padding=padding), nn.ReLU()]
            side = (side + 2 * padding - 3) // stride + 1
            c_in = c_out
        if head == "keypoints":
            layers.pop()  # the last maps are softmax logits: a ReLU would flatten them to uniform weights
        self.convs = nn.Sequential(*layers)
        if head == "keypoints":
            self.keypoints = SpatialSoftArgmax(side, side)
            features = 3 * c_in  # (x, y) and mean activation per map
        else:
            self.keypoints = None
            features = c_in * side * side
        self.head = nn.Sequential(
            nn.Linear(features, hidden_dim),
            nn.LayerNorm(hidden_dim),
            nn.ReLU(),
            nn.Linear(hidden_dim, state_dim),
        )

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """The head's input for float CHW images ``[N, 3, H, W]``."""
        if self.coord_channels:
            x = coordinate_channels(x)
        maps = self.convs(x)
        if self.keypoints is None:
            return maps.flatten(1)
        return torch.cat([self.keypoints(maps), maps.mean(dim=(-2, -1))], dim=-1)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        x = to_float_chw(pixels)
        if tuple(x.shape[-2:]) != (self.image_size, self.image_size):
            raise ValueError(
                f"StateEncoder(image_size={self.image_size}) got images of size {tuple(x.shape[-2:])} "
                f"(input shape {tuple(pixels.shape)}, dtype {pixels.dtype}); resize them first"
            )
        lead = x.shape[:-3]
        x = x.reshape(-1, *x.shape[-3:])
        return self.head(self.features(x)).reshape(*lead, self.state_dim)


class EncoderEnsemble(nn.Module):
    """The mean of several encoders' estimates, each also read off the mirrored image if ``state_mirror``.

    ``members``: encoders mapping the same images to states in the same units (e.g.
    :class:`~trakdis.modules.NormalizedEncoder`, raw state units). With ``state_mirror=(perm, sign)``
    (``trakdis.envs.task_spec(task).state_mirror``) every member also reads the left-right flipped
    image, and its estimate is mirrored back (``state[..., perm] * sign``) before the average: the
    flip test-time augmentation, exact where the flip augmentation is (the mirrored scene renders
    as the flipped image). A member's errors that are not mirror-symmetric average out.

    Input: uint8 ``[*B, H, W, 3]`` or float ``[*B, 3, H, W]`` images; output ``[*B, state_dim]``.
    """

    def __init__(self, members: Sequence[nn.Module], *, state_mirror: tuple[Sequence[int], Sequence[float]] | None = None):
        super().__init__()
        if len(members) < 1:
            raise ValueError("EncoderEnsemble needs at least one member")
        self.members = nn.ModuleList(members)
        self.state_mirror = None if state_mirror is None else (
            [int(i) for i in state_mirror[0]], [float(v) for v in state_mirror[1]])

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        estimates = [member(pixels) for member in self.members]
        if self.state_mirror is not None:
            # HWC uint8 images flip along dim -2, CHW float images along dim -1 (to_float_chw's layouts)
            flipped = pixels.flip(-2 if pixels.dtype == torch.uint8 else -1)
            estimates += [mirror_state(member(flipped), *self.state_mirror) for member in self.members]
        return torch.stack(estimates).mean(0)
