"""Online Decision Transformer loss on padded windows: masked negative log-likelihood minus an entropy bonus."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import ProbabilisticTensorDictModule, ProbabilisticTensorDictSequential, dispatch
from tensordict.utils import NestedKey
from torchrl.modules import TanhNormal
from torchrl.objectives import OnlineDTLoss

from trakdis.modules.grasp_distribution import normal_log_prob, tanh_log_det

__all__ = ["MaskedOnlineDTLoss", "masked_mean", "clamp_action", "tanh_normal_log_prob", "tanh_normal_rsample_log_prob"]



def masked_mean(x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Mean of ``x`` over entries where ``mask`` is True (all entries when ``mask`` is None)."""
    if mask is None:
        return x.mean()
    mask = mask.to(x.dtype)
    return (x * mask).sum() / mask.sum().clamp_min(1.0)


def clamp_action(action: torch.Tensor, eps: float) -> torch.Tensor:
    """Clamp targets into ``[-1 + eps, 1 - eps]``: a TanhNormal density is degenerate at exactly +-1."""
    return action.clamp(-1.0 + eps, 1.0 - eps) if eps > 0 else action


def tanh_normal_log_prob(loc, scale, value, log_scale=None) -> torch.Tensor:
    """``TanhNormal(loc, scale, low=-1, high=1).log_prob(value)`` in closed form (last dim = event).

    The same operations as TorchRL's ``TanhNormal`` (safe ``atanh`` clamped at the dtype's
    resolution, the Normal log-density, the stable tanh log-Jacobian), without building the
    distribution and its transforms.
    """
    eps = torch.finfo(value.dtype).resolution
    x = value.clamp(-(1.0 - eps), 1.0 - eps).atanh()
    log_scale = scale.log() if log_scale is None else log_scale
    return -tanh_log_det(x).sum(-1) + normal_log_prob(x, loc, scale, log_scale).sum(-1)


def tanh_normal_rsample_log_prob(loc, scale, n: int, log_scale=None) -> torch.Tensor:
    """Log-probabilities ``[n, *batch]`` of ``n`` reparameterised samples of ``TanhNormal(loc, scale)``.

    Draws the same standard normals as TorchRL's ``TanhNormal.rsample_and_log_prob((n,))`` (so
    the same samples under the same seed) and scores the pre-tanh values the same way.
    """
    eps = torch.empty((n, *loc.shape), dtype=loc.dtype, device=loc.device).normal_()
    x = loc + eps * scale
    log_scale = scale.log() if log_scale is None else log_scale
    return normal_log_prob(x, loc, scale, log_scale).sum(-1) - tanh_log_det(x).sum(-1)


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


class MaskedOnlineDTLoss(OnlineDTLoss):
    r"""TorchRL's :class:`~torchrl.objectives.OnlineDTLoss` on left-padded windows, with clamped targets
    and a fixed entropy weight that may be 0.

    ``loss_nll = masked_mean(-log pi(a_target))`` and ``loss_entropy = -lambda * H``, where
    ``H = masked_mean(-log pi(a~pi))`` is Online DT's Monte-Carlo entropy estimate (``TanhNormal`` has
    no closed form). With ``learn_temperature=True``, ``lambda = exp(log_alpha)`` is learned as in
    ``OnlineDTLoss``: ``loss_alpha = alpha * (H - target_entropy).detach()``, and ``loss_entropy`` uses
    ``alpha.detach()``. The temperature, its target entropy and its state (``log_alpha``,
    ``alpha_init``, ``target_entropy``) are ``OnlineDTLoss``'s; so is the masked reduction
    (:attr:`loss_mask_key`, kept equal to the ``mask`` key of :meth:`set_keys`).

    What this subclass adds to ``OnlineDTLoss`` (checked against torchrl 0.14):

    * a fixed weight ``lambda_entropy`` that may be 0 (``OnlineDTLoss`` takes ``log(alpha_init)``) and
      is used exactly (not as ``exp(log(lambda))``), with no ``loss_alpha`` output when it is fixed;
    * target actions clamped to ``[-1 + action_eps, 1 - action_eps]`` (to match the actor's
      ``loc_bound``, :attr:`~trakdis.modules.DTModelConfig.action_eps`), while the actor still reads the
      unclamped actions as inputs;
    * the padding mask is required (a missing or malformed mask is an error, not "no masking"), and
      the logged ``entropy`` is its masked mean;
    * for TorchRL's ``TanhNormal`` over [-1, 1] (:func:`~trakdis.modules.make_dt_actor`) the
      log-probabilities are computed in closed form, with the same operations and random draws as
      ``TanhNormal`` (same numbers) but without building distribution objects; other distributions
      go through ``actor.get_dist`` and ``OnlineDTLoss.get_entropy_bonus``, or the distribution's own
      ``entropy_estimate`` where it has one (the grasp head's
      :class:`~trakdis.modules.GraspConditionedTanhNormal`).

    With a full mask and the same temperature, ``loss_nll``/``loss_entropy`` equal ``OnlineDTLoss``'s
    ``loss_log_likelihood``/``loss_entropy`` (for targets inside the clamp range).

    Args:
        actor_network: a probabilistic actor whose ``get_dist(td)`` gives the per-step policy
            (e.g. :func:`~trakdis.modules.make_dt_actor`).

    Keyword Args:
        lambda_entropy: fixed entropy weight (paper: 0.1; >= 0); initial temperature when learned (> 0).
        learn_temperature: learn ``log_alpha`` toward ``target_entropy`` (Online DT).
        target_entropy: ``"auto"`` (``-action_dim``, from the actor's spec) or a float.
        samples_mc_entropy: samples per step for the entropy estimate.
        action_eps: targets are clamped to ``[-1 + eps, 1 - eps]`` (0 disables).

    Returns a TensorDict with ``loss_nll``, ``loss_entropy``, (``loss_alpha``) and detached
    ``entropy`` and ``alpha``.
    """

    @dataclass
    class _AcceptedKeys(OnlineDTLoss._AcceptedKeys):
        """Tensordict keys.

        Attributes:
            action_target: target action (also the DT's action input). Defaults to ``"action"``.
            action_pred: the actor's action (its spec gives ``target_entropy="auto"``). Defaults to ``"action"``.
            mask: bool ``[B, K]`` padding mask (True = real step). Defaults to ``"mask"``.
        """

        mask: NestedKey = "mask"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

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
        if lambda_entropy < 0 or (learn_temperature and lambda_entropy == 0):
            raise ValueError(f"lambda_entropy={lambda_entropy} must be >= 0 (> 0 when the temperature is learned)")
        super().__init__(
            actor_network,
            alpha_init=float(lambda_entropy) if lambda_entropy > 0 else 1.0,  # OnlineDTLoss takes its log
            fixed_alpha=not learn_temperature,
            target_entropy=target_entropy,
            samples_mc_entropy=int(samples_mc_entropy),
        )
        self.learn_temperature = learn_temperature
        if not learn_temperature:
            # the exact weight (exp(log(0.1)) is 1 ulp off in float32); log_alpha/alpha_init follow it
            self.register_buffer("lambda_entropy", torch.tensor(float(lambda_entropy), device=self.log_alpha.device))
            with torch.no_grad():
                self.alpha_init.fill_(float(lambda_entropy))
                self.log_alpha.copy_(self.lambda_entropy.log())  # -inf for 0
        self.action_eps = float(action_eps)
        self._tanh_normal_keys = _tanh_normal_keys(actor_network)
        self.loss_mask_key = self.tensor_keys.mask

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        # set_keys(): the mask key is also the reduction's mask; the input keys change
        self.loss_mask_key = self.tensor_keys.mask
        self._in_keys = None

    def _set_in_keys(self):
        keys = set(self.actor_network.in_keys) | {self.tensor_keys.action_target, self.tensor_keys.mask}
        self._in_keys = sorted(keys, key=str)

    @property
    def out_keys(self):
        keys = ["loss_nll", "loss_entropy", "entropy", "alpha"]
        return keys + ["loss_alpha"] if self.learn_temperature else keys

    @out_keys.setter
    def out_keys(self, values):
        self._out_keys = values

    @property
    def alpha(self) -> torch.Tensor:
        """Current entropy weight (detached)."""
        return super().alpha if self.learn_temperature else self.lambda_entropy.detach()

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # checkpoints of the former trakdis MaskedOnlineDTLoss (before it subclassed OnlineDTLoss) lack these
        for name in ("alpha_init", "log_alpha"):
            if prefix + name not in state_dict:
                state_dict[prefix + name] = getattr(self, name).detach().clone()
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def get_entropy_bonus(self, dist) -> torch.Tensor:
        # OnlineDTLoss's estimate needs a reparameterised sample, which a discrete grasp command has
        # not: a distribution with its own estimate (GraspConditionedTanhNormal) gives it
        if hasattr(dist, "entropy_estimate"):
            return dist.entropy_estimate(self.samples_mc_entropy)
        return super().get_entropy_bonus(dist)

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # Not OnlineDTLoss.forward: it reads the target and the actor's action input from one entry
        # (no room to clamp only the target) and always builds the distribution; the reduction,
        # temperature and entropy estimator below are its own.
        target = tensordict.get(self.tensor_keys.action_target, None)
        if target is None:
            raise KeyError(f"{type(self).__name__}: the target action {self.tensor_keys.action_target!r} is missing "
                           f"(keys: {list(tensordict.keys())})")
        if target.requires_grad:
            raise RuntimeError(f"{type(self).__name__}: the target action {self.tensor_keys.action_target!r} must not require grad")
        target = clamp_action(target, self.action_eps)
        tanh_keys = self._tanh_normal_keys
        with self.actor_network_params.to_module(self.actor_network):
            if tanh_keys is None:
                dist = self.actor_network.get_dist(tensordict.copy())
            else:  # default TanhNormal policy: closed form, same numbers, no distribution objects
                params = self.actor_network.get_dist_params(tensordict.copy())
        if tanh_keys is None:
            log_prob = dist.log_prob(target)
            entropy = self.get_entropy_bonus(dist)
        else:
            loc, scale = params.get(tanh_keys[0]), params.get(tanh_keys[1])
            log_scale = scale.log()
            log_prob = tanh_normal_log_prob(loc, scale, target, log_scale)
            entropy = -tanh_normal_rsample_log_prob(loc, scale, self.samples_mc_entropy, log_scale).mean(0)
        get_mask(tensordict, self.tensor_keys.mask, log_prob, type(self).__name__)  # required, [B, K] bool
        entropy = self._reduce_loss(entropy, tensordict, reduction="mean")  # masked mean (loss_mask_key)
        out = {
            "loss_nll": self._reduce_loss(-log_prob, tensordict, reduction="mean"),
            "loss_entropy": -self.alpha * entropy,
        }
        if self.learn_temperature:
            out["loss_alpha"] = self.log_alpha.exp() * (entropy - self.target_entropy).detach()
        out["entropy"] = entropy.detach()
        out["alpha"] = self.alpha
        return TensorDict(out, batch_size=[])
