"""Behaviour cloning loss for a TanhNormal actor (the BC-image baseline)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from trakdis.objectives.dt_loss import _tanh_normal_keys, clamp_action, tanh_normal_log_prob

__all__ = ["BehaviourCloningLoss"]


class BehaviourCloningLoss(LossModule):
    r"""Behaviour cloning of expert actions: ``loss_bc = mean_b -log pi(a_expert | o_b)`` (``"nll"``)
    or ``mean ||tanh(loc) - a_expert||^2`` (``"mse"``, of the mean action).

    TorchRL's ``BCLoss`` computes the same NLL, but for a probabilistic actor it runs the network
    twice per batch (it calls the actor, which overwrites ``"action"`` with a sample, then
    ``get_dist``), a double CNN forward on images; and it scores the expert's actions as they are,
    while the expert's grasp commands are exactly +-1, where a ``TanhNormal`` density is degenerate
    (an NLL of ~1e4 at a small std). Here the network runs once (``get_dist_params``), targets are
    clamped to ``[-1 + action_eps, 1 - action_eps]`` (use the actor config's ``action_eps``) and the
    NLL is :func:`~trakdis.objectives.dt_loss.tanh_normal_log_prob`, the closed form ``MaskedOnlineDTLoss`` uses.

    Args:
        actor_network: a ``ProbabilisticActor`` with a ``TanhNormal`` over [-1, 1] (e.g.
            :func:`~trakdis.modules.make_bc_actor`, or with a trunk, :func:`~trakdis.modules.with_image_trunk`).

    Keyword Args:
        loss_function: ``"nll"`` (default) or ``"mse"``.
        action_eps: target clamp (0 disables).

    Keys (``set_keys``): ``action_target`` (``"action"``, ``[*B, action_dim]``). Returns
    ``loss_bc`` and the detached metric ``action_mse`` (squared error of the mean action).
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys.

        Attributes:
            action_target: the expert's action ``[*B, action_dim]``. Defaults to ``"action"``.
        """

        action_target: NestedKey = "action"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    actor_network: TensorDictModule
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams

    def __init__(self, actor_network: ProbabilisticTensorDictSequential, *,
                 loss_function: Literal["nll", "mse"] = "nll", action_eps: float = 1e-6) -> None:
        super().__init__()
        if loss_function not in ("nll", "mse"):
            raise ValueError(f"BehaviourCloningLoss: loss_function must be 'nll' or 'mse', got {loss_function!r}")
        keys = _tanh_normal_keys(actor_network)
        if keys is None:
            raise TypeError("BehaviourCloningLoss: the actor must be a ProbabilisticActor with a TanhNormal over "
                            "[-1, 1] and 'loc'/'scale' parameters (make_bc_actor)")
        self._loc_key, self._scale_key = keys
        self.convert_to_functional(actor_network, "actor_network", create_target_params=False)
        self.loss_function = loss_function
        self.action_eps = float(action_eps)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self):
        return sorted(set(self.actor_network.in_keys) | {self.tensor_keys.action_target}, key=str)

    @property
    def out_keys(self):
        return ["loss_bc", "action_mse"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        target = tensordict.get(self.tensor_keys.action_target, None)
        if target is None:
            raise KeyError(f"BehaviourCloningLoss: the expert action {self.tensor_keys.action_target!r} is missing "
                           f"(keys: {list(tensordict.keys())})")
        if target.requires_grad:
            raise RuntimeError(f"BehaviourCloningLoss: the target {self.tensor_keys.action_target!r} must not require grad")
        with self.actor_network_params.to_module(self.actor_network):
            params = self.actor_network.get_dist_params(tensordict.copy())
        loc, scale = params.get(self._loc_key), params.get(self._scale_key)
        if loc.shape != target.shape:
            raise ValueError(f"BehaviourCloningLoss: {self.tensor_keys.action_target!r} has shape {tuple(target.shape)}, "
                             f"the actor's 'loc' {tuple(loc.shape)}")
        target = clamp_action(target.to(loc.dtype), self.action_eps)
        sq_err = (torch.tanh(loc) - target).pow(2).mean()
        if self.loss_function == "nll":
            loss = -tanh_normal_log_prob(loc, scale, target).mean()
        else:
            loss = sq_err
        return TensorDict({"loss_bc": loss, "action_mse": sq_err.detach()}, batch_size=[])
