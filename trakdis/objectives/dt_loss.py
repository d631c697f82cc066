"""Decision Transformer loss: masked negative log-likelihood minus an entropy bonus."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import ProbabilisticTensorDictModule, ProbabilisticTensorDictSequential, TensorDictModule
from tensordict.utils import NestedKey
from torchrl.modules import TanhNormal
from torchrl.modules.distributions.utils import rsample_and_log_prob
from torchrl.objectives import LossModule

__all__ = ["DTLoss", "masked_mean", "clamp_action", "tanh_normal_log_prob", "tanh_normal_rsample_log_prob"]

_LOG_2 = math.log(2.0)
_LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))


def masked_mean(x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Mean of ``x`` over entries where ``mask`` is True (all entries when ``mask`` is None)."""
    if mask is None:
        return x.mean()
    mask = mask.to(x.dtype)
    return (x * mask).sum() / mask.sum().clamp_min(1.0)


def clamp_action(action: torch.Tensor, eps: float) -> torch.Tensor:
    """Clamp targets into ``[-1 + eps, 1 - eps]``: a TanhNormal density is degenerate at exactly +-1."""
    return action.clamp(-1.0 + eps, 1.0 - eps) if eps > 0 else action


def _normal_log_prob(x, loc, scale, log_scale):
    # torch.distributions.Normal.log_prob, op for op (same rounding)
    return -((x - loc) ** 2) / (2 * scale**2) - log_scale - _LOG_SQRT_2PI


def _tanh_log_det(x):
    # log |d tanh(x) / dx| = log(1 - tanh(x)^2) = 2 (log 2 - x - softplus(-2x)): stable for large |x|
    # (torch.distributions.TanhTransform.log_abs_det_jacobian)
    return 2.0 * (_LOG_2 - x - F.softplus(-2.0 * x))


def tanh_normal_log_prob(loc, scale, value, log_scale=None) -> torch.Tensor:
    """``TanhNormal(loc, scale, low=-1, high=1).log_prob(value)`` in closed form (last dim = event).

    The same operations as TorchRL's ``TanhNormal`` (safe ``atanh`` clamped at the dtype's
    resolution, the Normal log-density, the stable tanh log-Jacobian), without building the
    distribution and its transforms.
    """
    eps = torch.finfo(value.dtype).resolution
    x = value.clamp(-(1.0 - eps), 1.0 - eps).atanh()
    log_scale = scale.log() if log_scale is None else log_scale
    return -_tanh_log_det(x).sum(-1) + _normal_log_prob(x, loc, scale, log_scale).sum(-1)


def tanh_normal_rsample_log_prob(loc, scale, n: int, log_scale=None) -> torch.Tensor:
    """Log-probabilities ``[n, *batch]`` of ``n`` reparameterised samples of ``TanhNormal(loc, scale)``.

    Draws the same standard normals as TorchRL's ``TanhNormal.rsample_and_log_prob((n,))`` (so
    the same samples under the same seed) and scores the pre-tanh values the same way.
    """
    eps = torch.empty((n, *loc.shape), dtype=loc.dtype, device=loc.device).normal_()
    x = loc + eps * scale
    log_scale = scale.log() if log_scale is None else log_scale
    return _normal_log_prob(x, loc, scale, log_scale).sum(-1) - _tanh_log_det(x).sum(-1)


def _tanh_normal_keys(actor) -> tuple[NestedKey, NestedKey] | None:
    """The ``(loc, scale)`` keys when ``actor``'s policy is TorchRL's ``TanhNormal`` over [-1, 1]."""
    if not isinstance(actor, ProbabilisticTensorDictSequential) or getattr(actor, "return_composite", False):
        return None
    prob = actor.module[-1]
    if not isinstance(prob, ProbabilisticTensorDictModule) or prob.distribution_class is not TanhNormal:
        return None
    kwargs = dict(prob.distribution_kwargs)
    try:
        if set(kwargs) - {"low", "high"} or float(kwargs.get("low", -1.0)) != -1.0 or float(kwargs.get("high", 1.0)) != 1.0:
            return None
    except (TypeError, ValueError, RuntimeError):  # e.g. per-dimension bounds
        return None
    keys = {(k[-1] if isinstance(k, tuple) else k): v for k, v in zip(prob.dist_keys, prob.in_keys)}
    if set(keys) != {"loc", "scale"}:
        return None
    return keys["loc"], keys["scale"]


def get_mask(tensordict: TensorDictBase, key: NestedKey, like: torch.Tensor, owner: str) -> torch.Tensor:
    mask = tensordict.get(key, None)
    if mask is None:
        raise KeyError(f"{owner}: the padding mask {key!r} is missing from the tensordict (keys: {list(tensordict.keys())})")
    if mask.shape != like.shape or mask.dtype != torch.bool:
        raise ValueError(f"{owner}: {key!r} must be bool of shape {tuple(like.shape)}, got {mask.dtype} {tuple(mask.shape)}")
    return mask


class DTLoss(LossModule):
    r"""Decision Transformer / Online DT loss with padding masks.

    ``loss_nll = masked_mean(-log pi(a_target))`` and an entropy bonus
    ``loss_entropy = -lambda * H`` where ``H = masked_mean(-log pi(a~pi))`` is the Monte-Carlo entropy
    estimate of Online DT / TorchRL's ``OnlineDTLoss`` (``TanhNormal`` has no closed form). With
    ``learn_temperature=True``, ``lambda = exp(log_alpha)`` is learned as in Online DT:
    ``loss_alpha = alpha * (H - target_entropy).detach()`` and ``loss_entropy`` uses ``alpha.detach()``.

    With a full mask and the same temperature, ``loss_nll``/``loss_entropy`` equal TorchRL's
    ``OnlineDTLoss`` ``loss_log_likelihood``/``loss_entropy`` (for targets inside the clamp range);
    unlike it, padded steps are excluded from every average.

    Args:
        actor_network: a probabilistic actor whose ``get_dist(td)`` gives the per-step policy
            (e.g. :func:`~trakdis.modules.make_dt_actor`).

    Keyword Args:
        lambda_entropy: fixed entropy weight (paper: 0.1); initial temperature when learned.
        learn_temperature: learn ``log_alpha`` toward ``target_entropy`` (Online DT).
        target_entropy: ``"auto"`` (``-action_dim``, from the actor's spec) or a float.
        samples_mc_entropy: samples per step for the entropy estimate.
        action_eps: targets are clamped to ``[-1 + eps, 1 - eps]`` (0 disables).

    Returns a TensorDict with ``loss_nll``, ``loss_entropy``, (``loss_alpha``) and detached
    ``entropy`` and ``alpha``.
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys.

        Attributes:
            action_target: target action (also the DT's action input). Defaults to ``"action"``.
            mask: bool ``[B, K]`` padding mask (True = real step). Defaults to ``"mask"``.
        """

        action_target: NestedKey = "action"
        mask: NestedKey = "mask"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    actor_network: TensorDictModule
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        *,
        lambda_entropy: float = 0.1,
        learn_temperature: bool = False,
        target_entropy: str | float = "auto",
        samples_mc_entropy: int = 1,
        action_eps: float = 1e-6,
    ) -> None:
        super().__init__()
        if lambda_entropy < 0 or (learn_temperature and lambda_entropy == 0):
            raise ValueError(f"lambda_entropy={lambda_entropy} must be >= 0 (> 0 when the temperature is learned)")
        self.convert_to_functional(actor_network, "actor_network", create_target_params=False)
        device = next(iter(self.actor_network_params.values(True, True))).device
        self.learn_temperature = learn_temperature
        if learn_temperature:
            self.log_alpha = torch.nn.Parameter(torch.tensor(math.log(lambda_entropy), device=device))
        else:
            self.register_buffer("lambda_entropy", torch.tensor(float(lambda_entropy), device=device))
        if target_entropy == "auto":
            spec = getattr(actor_network, "spec", None)
            if spec is None or "action" not in spec.keys():
                raise RuntimeError("DTLoss: cannot infer the action dimension from the actor's spec; pass target_entropy=")
            target_entropy = -float(spec["action"].shape[-1])
        self.register_buffer("target_entropy", torch.tensor(float(target_entropy), device=device))
        self.samples_mc_entropy = int(samples_mc_entropy)
        self.action_eps = float(action_eps)
        self._tanh_normal_keys = _tanh_normal_keys(actor_network)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self):
        keys = set(self.actor_network.in_keys) | {self.tensor_keys.action_target, self.tensor_keys.mask}
        return sorted(keys, key=str)

    @property
    def out_keys(self):
        keys = ["loss_nll", "loss_entropy", "entropy", "alpha"]
        return keys + ["loss_alpha"] if self.learn_temperature else keys

    @property
    def alpha(self) -> torch.Tensor:
        """Current entropy weight (detached)."""
        return (self.log_alpha.exp() if self.learn_temperature else self.lambda_entropy).detach()

    def entropy(self, dist: torch.distributions.Distribution) -> torch.Tensor:
        """Per-step Monte-Carlo entropy ``-mean_s log pi(a_s)``, ``a_s ~ pi`` reparameterised."""
        _, log_p = rsample_and_log_prob(dist, (self.samples_mc_entropy,))
        return -log_p.mean(0)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        target = tensordict.get(self.tensor_keys.action_target)
        if target.requires_grad:
            raise RuntimeError(f"DTLoss: the target action {self.tensor_keys.action_target!r} must not require grad")
        target = clamp_action(target, self.action_eps)
        tanh_keys = self._tanh_normal_keys
        with self.actor_network_params.to_module(self.actor_network):
            if tanh_keys is None:
                dist = self.actor_network.get_dist(tensordict.copy())
            else:  # default TanhNormal policy: closed form, same numbers, no distribution objects
                params = self.actor_network.get_dist_params(tensordict.copy())
        if tanh_keys is None:
            log_prob = dist.log_prob(target)
            entropy = self.entropy(dist)
        else:
            loc, scale = params.get(tanh_keys[0]), params.get(tanh_keys[1])
            log_scale = scale.log()
            log_prob = tanh_normal_log_prob(loc, scale, target, log_scale)
            entropy = -tanh_normal_rsample_log_prob(loc, scale, self.samples_mc_entropy, log_scale).mean(0)
        mask = get_mask(tensordict, self.tensor_keys.mask, log_prob, "DTLoss")
        weight = mask.to(log_prob.dtype)
        denom = weight.sum().clamp_min(1.0)  # masked_mean, with the mask converted once
        entropy = (entropy * weight).sum() / denom
        out = {"loss_nll": -((log_prob * weight).sum() / denom), "loss_entropy": -self.alpha * entropy}
        if self.learn_temperature:
            out["loss_alpha"] = self.log_alpha.exp() * (entropy - self.target_entropy).detach()
        out["entropy"] = entropy.detach()
        out["alpha"] = self.alpha
        return TensorDict(out, batch_size=[])
