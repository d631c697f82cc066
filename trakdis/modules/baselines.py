"""The image baselines of the paper's Table I: BC-image and DT-image.

Both are a CNN trunk on the raw 32x32 image (:class:`ImageTrunk`, a
:class:`~trakdis.modules.StateEncoder` whose output is a learned feature vector instead of the
reduced state, trained end to end) followed by a head that reads ``"image_features"``:

* **BC-image** (behaviour cloning): :func:`make_bc_actor`, an MLP head (TorchRL ``MLP``) with the
  Online DT Gaussian parameterisation (bounded log-std, softly bounded pre-tanh mean) in a TorchRL
  ``ProbabilisticActor`` with ``TanhNormal``, trained with
  :class:`~trakdis.objectives.BehaviourCloningLoss` (NLL of the expert's action).
* **DT-image**: :func:`~trakdis.modules.make_dt_actor` with ``observation_key="image_features"``,
  trained with :class:`~trakdis.objectives.MaskedOnlineDTLoss` on windows of images.

:func:`with_image_trunk` puts the trunk in front of a head actor, so that the training actor reads
``"pixels"`` (``[*B, H, W, 3]`` uint8, any leading dims, e.g. ``[B, K]`` windows) and gradients
reach the CNN. When acting, the trunk runs in the environment as a TorchRL transform
(:class:`~trakdis.transforms.EncoderTransform`, as the student's encoder does) and the head actor
alone reads the features: the DT head then keeps its context with
:class:`~trakdis.modules.DTActingPolicy`, unchanged. The CNN treats every frame on its own, so
this split computes exactly what the training actor computes.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal

from trakdis.modules.encoder import StateEncoder, to_float_chw
from trakdis.transforms.augment import random_shift

__all__ = ["BCConfig", "BCHead", "ImageTrunk", "ImageTrunkConfig", "make_bc_actor", "with_image_trunk"]

FEATURE_KEY = "image_features"


class ImageTrunk(nn.Module):
    """CNN trunk of the image baselines: image -> ``feature_dim`` learned features.

    A :class:`~trakdis.modules.StateEncoder` (same layers, same options) with ``state_dim =
    feature_dim``, and the encoder's random-shift augmentation (DrQ, up to ``pad`` pixels, as in
    :class:`~trakdis.objectives.EncoderLoss`) applied **in training mode only**, per image, so that
    every loss that trains the trunk augments the same way and acting (eval mode, or inside
    :class:`~trakdis.transforms.EncoderTransform`, which keeps its encoder in eval mode) never does.

    No horizontal flip: a mirrored image would need a mirrored action label, which the task specs
    do not define (``task_spec(task).state_mirror`` covers states only), and the diagonal folds'
    scripted expert is not mirror-symmetric (it always carries corner c00 to cNN; in the mirrored
    scene that is another corner pair), so mirrored demonstrations would teach wrong actions.

    Input: uint8 ``[*B, H, W, 3]`` or float ``[*B, 3, H, W]`` in [0, 1]; output ``[*B, feature_dim]``.
    """

    def __init__(self, feature_dim: int = 64, *, pad: int = 2, image_size: int = 32,
                 channels: Sequence[int] = (32, 32, 32, 32), hidden_dim: int = 256, head: str = "flatten",
                 stem_stride: int = 2, coord_channels: bool = False):
        super().__init__()
        if feature_dim < 1:
            raise ValueError(f"ImageTrunk: feature_dim must be >= 1, got {feature_dim}")
        if pad < 0:
            raise ValueError(f"ImageTrunk: pad must be >= 0, got {pad}")
        self.encoder = StateEncoder(feature_dim, image_size=image_size, channels=channels, hidden_dim=hidden_dim,
                                    head=head, stem_stride=stem_stride, coord_channels=coord_channels)
        self.pad = int(pad)
        self.feature_dim = int(feature_dim)
        cfg = dict(self.encoder.config)
        cfg["feature_dim"] = cfg.pop("state_dim")
        self.config = {**cfg, "pad": self.pad}

    @classmethod
    def from_config(cls, config: dict) -> "ImageTrunk":
        """Rebuild from :attr:`config` (as saved in a policy file)."""
        kw = dict(config)
        return cls(kw.pop("feature_dim"), **kw)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        x = to_float_chw(pixels)
        if self.training and self.pad > 0:
            lead = x.shape[:-3]
            x = random_shift(x.reshape(-1, *x.shape[-3:]), self.pad).reshape(*lead, *x.shape[-3:])
        return self.encoder(x)


@dataclass
class ImageTrunkConfig:
    """CNN trunk of an image baseline (the recipes' ``--trunk.*`` options; :class:`ImageTrunk`)."""

    feature_dim: int = 64
    """width of the learned image features"""
    channels: tuple[int, ...] = (32, 32, 32, 32)
    """channels of the 4 conv layers"""
    hidden_dim: int = 256
    """width of the CNN's MLP head"""
    stem_stride: int = 2
    """stride of the first conv layer"""
    pad: int = 2
    """random-shift augmentation (pixels) while training; 0: none"""

    def make(self, image_size: int = 32) -> ImageTrunk:
        return ImageTrunk(self.feature_dim, pad=self.pad, image_size=image_size, channels=self.channels,
                          hidden_dim=self.hidden_dim, stem_stride=self.stem_stride)


@dataclass
class BCConfig:
    """Sizes of the BC-image head (features -> Gaussian action parameters).

    ``log_std_min``/``log_std_max``/``init_log_std``/``loc_bound`` mean what they mean in
    :class:`~trakdis.modules.DTModelConfig` (the same defaults as the recipes' teacher), so BC and the
    DTs share one action distribution and one target clamp (:attr:`action_eps`).
    """

    feature_dim: int
    action_dim: int
    hidden_dims: tuple[int, ...] = (256, 256)
    log_std_min: float = -2.5
    log_std_max: float = 2.0
    init_log_std: float = 0.0
    loc_bound: float = 5.0

    def __post_init__(self) -> None:
        for name in ("feature_dim", "action_dim"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"BCConfig.{name}={getattr(self, name)} must be >= 1")
        if any(int(h) < 1 for h in self.hidden_dims):
            raise ValueError(f"BCConfig.hidden_dims={tuple(self.hidden_dims)}: every width must be >= 1")
        if not self.log_std_min < self.init_log_std < self.log_std_max:
            raise ValueError(f"BCConfig: init_log_std={self.init_log_std} must lie strictly inside "
                             f"({self.log_std_min}, {self.log_std_max})")
        if self.loc_bound < 0:
            raise ValueError(f"BCConfig.loc_bound={self.loc_bound} must be >= 0 (0: unbounded)")
        self.hidden_dims = tuple(int(h) for h in self.hidden_dims)

    @property
    def action_eps(self) -> float:
        """Target-action clamp matching :attr:`loc_bound` (see ``DTModelConfig.action_eps``)."""
        return 1.0 - math.tanh(self.loc_bound) if self.loc_bound > 0 else 1e-6

    def to_dict(self) -> dict:
        return {"feature_dim": self.feature_dim, "action_dim": self.action_dim, "hidden_dims": list(self.hidden_dims),
                "log_std_min": self.log_std_min, "log_std_max": self.log_std_max, "init_log_std": self.init_log_std,
                "loc_bound": self.loc_bound}


class BCHead(nn.Module):
    """``features [*B, F] -> (loc, scale) [*B, A]``: a TorchRL ``MLP`` and the Online DT parameterisation
    (``log_std`` squashed into ``[log_std_min, log_std_max]``, starting at ``init_log_std`` for every
    input; ``loc`` softly bounded by ``loc_bound``), as :class:`~trakdis.modules.StochasticDTActor`'s head."""

    def __init__(self, config: BCConfig):
        super().__init__()
        self.config = config
        a = config.action_dim
        self.net = MLP(in_features=config.feature_dim, out_features=2 * a, num_cells=list(config.hidden_dims),
                       activation_class=nn.ReLU)
        last = [m for m in self.net.modules() if isinstance(m, nn.Linear)][-1]
        frac = (config.init_log_std - config.log_std_min) / (config.log_std_max - config.log_std_min)
        with torch.no_grad():
            last.weight[a:].zero_()
            last.bias[a:].fill_(math.atanh(2.0 * frac - 1.0))
            last.bias[:a].zero_()

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        c = self.config
        if features.shape[-1] != c.feature_dim:
            raise ValueError(f"BCHead: {FEATURE_KEY!r} has shape {tuple(features.shape)}, expected [..., {c.feature_dim}]")
        loc, log_std = self.net(features).chunk(2, dim=-1)
        log_std = c.log_std_min + 0.5 * (c.log_std_max - c.log_std_min) * (torch.tanh(log_std) + 1.0)
        if c.loc_bound > 0:
            loc = c.loc_bound * torch.tanh(loc / c.loc_bound)
        return loc, log_std.exp()


def _tanh_normal_actor(module: nn.Module, action_dim: int, device=None) -> ProbabilisticActor:
    spec = Bounded(low=-1.0, high=1.0, shape=(action_dim,), device=device)
    return ProbabilisticActor(module, in_keys=["loc", "scale"], out_keys=["action"], spec=spec,
                              distribution_class=TanhNormal, distribution_kwargs={"low": -1.0, "high": 1.0},
                              return_log_prob=False)


def make_bc_actor(config: BCConfig, observation_key=FEATURE_KEY, *, device=None) -> ProbabilisticActor:
    """A TorchRL ``ProbabilisticActor`` (``TanhNormal`` over [-1, 1], as :func:`make_dt_actor`) around
    a :class:`BCHead` reading ``observation_key`` ``[*B, feature_dim]``.

    Probabilistic rather than a deterministic actor with an MSE loss: the expert's grasp commands
    are saturated at +-1, which the NLL keeps fitting past the saturation (the squared error of
    ``tanh`` stops pulling near +-1; docs/recipes/distill.md measured NLL > MSE for the student);
    evaluation uses the mean action ``tanh(loc)``, the same as for every DT policy here.
    """
    head = BCHead(config)
    if device is not None:
        head = head.to(device)
    module = TensorDictModule(head, in_keys=[observation_key], out_keys=["loc", "scale"])
    return _tanh_normal_actor(module, config.action_dim, device)


def with_image_trunk(actor: ProbabilisticActor, trunk: nn.Module, pixels_key="pixels") -> ProbabilisticActor:
    """The training actor of an image baseline: ``trunk`` writes the head's observation key from
    ``pixels_key``, then the head ``actor`` (from :func:`make_bc_actor` or :func:`make_dt_actor`)
    runs. Shares the modules of both (no copy); ``get_dist`` / ``get_dist_params`` (the losses) run
    the trunk too, so gradients reach it."""
    if not isinstance(actor, ProbabilisticActor) or len(actor.module) != 2:
        raise TypeError(f"with_image_trunk: expected an actor from make_bc_actor/make_dt_actor, got {type(actor).__name__}")
    head, prob = actor.module[0], actor.module[-1]
    trunk_module = TensorDictModule(trunk, in_keys=[pixels_key], out_keys=[head.in_keys[0]])
    spec = actor.spec["action"]
    return ProbabilisticActor(TensorDictSequential(trunk_module, head), in_keys=list(prob.in_keys),
                              out_keys=list(prob.out_keys), spec=spec, distribution_class=prob.distribution_class,
                              distribution_kwargs=dict(prob.distribution_kwargs), return_log_prob=False)
