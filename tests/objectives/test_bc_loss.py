"""BehaviourCloningLoss: the NLL of TorchRL's TanhNormal (clamped targets), its MSE variant and errors."""
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.modules import ProbabilisticActor
from torchrl.modules.distributions import NormalParamExtractor
from torch.distributions import Normal

from trakdis.modules import BCConfig, make_bc_actor
from trakdis.objectives import BehaviourCloningLoss
from trakdis.objectives.dt_loss import clamp_action


def batch(n=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    action = torch.rand(n, 3, generator=g) * 2 - 1
    action[:, -1] = 1.0  # saturated, as the expert's grasp commands
    return TensorDict({"image_features": torch.randn(n, 6, generator=g), "action": action}, [n])


def test_nll_equals_torchrl_tanh_normal_log_prob_of_clamped_targets():
    torch.manual_seed(0)
    cfg = BCConfig(6, 3, hidden_dims=(8,))
    actor = make_bc_actor(cfg)
    loss = BehaviourCloningLoss(actor, action_eps=cfg.action_eps)
    td = batch()
    out = loss(td)
    assert set(out.keys()) == {"loss_bc", "action_mse"} and set(loss.out_keys) == {"loss_bc", "action_mse"}
    dist = actor.get_dist(td.clone())
    expected = -dist.log_prob(clamp_action(td["action"], cfg.action_eps)).mean()
    torch.testing.assert_close(out["loss_bc"], expected, rtol=1e-4, atol=1e-4)
    params = actor.get_dist_params(td.clone())
    torch.testing.assert_close(out["action_mse"], (torch.tanh(params["loc"]) - clamp_action(td["action"], cfg.action_eps)).pow(2).mean())
    assert td["action"][:, -1].eq(1.0).all()  # the input is not modified
    mse = BehaviourCloningLoss(actor, loss_function="mse", action_eps=cfg.action_eps)(td)
    torch.testing.assert_close(mse["loss_bc"], out["action_mse"])
    out["loss_bc"].backward()
    assert all(p.grad is not None for p in actor.parameters())


def test_set_keys_and_errors():
    actor = make_bc_actor(BCConfig(6, 3, hidden_dims=(8,)))
    loss = BehaviourCloningLoss(actor)
    td = batch().rename_key_("action", "expert_action")
    with pytest.raises(KeyError, match="'action' is missing"):
        loss(td)
    loss.set_keys(action_target="expert_action")
    assert torch.isfinite(loss(td)["loss_bc"])
    bad = TensorDict({"image_features": torch.randn(5, 6), "expert_action": torch.zeros(5, 2)}, [5])
    with pytest.raises(ValueError, match="expert_action.*shape"):
        loss(bad)
    td["expert_action"].requires_grad_(True)
    with pytest.raises(RuntimeError, match="must not require grad"):
        loss(td)
    with pytest.raises(ValueError, match="loss_function"):
        BehaviourCloningLoss(actor, loss_function="l1")
    normal = ProbabilisticActor(TensorDictModule(torch.nn.Sequential(torch.nn.Linear(6, 6), NormalParamExtractor()),
                                                 in_keys=["image_features"], out_keys=["loc", "scale"]),
                                in_keys=["loc", "scale"], distribution_class=Normal)
    with pytest.raises(TypeError, match="TanhNormal"):
        BehaviourCloningLoss(normal)
