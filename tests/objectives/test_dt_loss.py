import pytest
import torch
from dt_windows import random_window
from torchrl.objectives import OnlineDTLoss

from trakdis.modules import DTModelConfig, make_dt_actor
from trakdis.objectives import MaskedOnlineDTLoss

S, A, B, K = 5, 3, 4, 6


@pytest.fixture
def actor():
    torch.manual_seed(0)
    cfg = DTModelConfig(state_dim=S, action_dim=A, embed_dim=32, n_layer=2, n_head=4, context_len=K, dropout=0.0, attn_dropout=0.0)
    return make_dt_actor(cfg)


def window(pad=(0, 0, 0, 0), seed=0):
    return random_window(B, K, S, A, pad=pad, seed=seed)


def test_matches_torchrl_online_dt_loss_fixed_temperature(actor):
    td = window()
    ours = MaskedOnlineDTLoss(actor, lambda_entropy=0.1)
    ref = OnlineDTLoss(actor, alpha_init=0.1, fixed_alpha=True)
    torch.manual_seed(3)
    out = ours(td.clone())
    torch.manual_seed(3)
    out_ref = ref(td.clone())
    torch.testing.assert_close(out["loss_nll"], out_ref["loss_log_likelihood"])
    torch.testing.assert_close(out["loss_entropy"], out_ref["loss_entropy"])
    torch.testing.assert_close(out["entropy"], out_ref["entropy"])
    torch.testing.assert_close(out["alpha"], out_ref["alpha"])
    assert set(out.keys()) == {"loss_nll", "loss_entropy", "entropy", "alpha"}
    assert not out["entropy"].requires_grad and out["loss_nll"].requires_grad


def test_padding_is_masked_like_torchrl_per_step_losses(actor):
    td = window(pad=(0, 2, 5, 3))
    ref = OnlineDTLoss(actor, alpha_init=0.1, fixed_alpha=True, reduction="none", scalar_output_mode="exclude")
    torch.manual_seed(4)
    out = MaskedOnlineDTLoss(actor, lambda_entropy=0.1)(td.clone())
    torch.manual_seed(4)
    out_ref = ref(td.clone())
    m = td["mask"]
    torch.testing.assert_close(out["loss_nll"], out_ref["loss_log_likelihood"][m].mean())
    torch.testing.assert_close(out["loss_entropy"], out_ref["loss_entropy"][m].mean())
    # padded content never changes the loss
    td2 = td.clone()
    td2["observation"][~m] = float("nan")
    td2["action"][~m] = 5.0
    td2["return_to_go"][~m] = -1e4
    torch.manual_seed(4)
    out2 = MaskedOnlineDTLoss(actor, lambda_entropy=0.1)(td2)
    torch.testing.assert_close(out2["loss_nll"], out["loss_nll"], rtol=0, atol=1e-5)
    torch.testing.assert_close(out2["loss_entropy"], out["loss_entropy"], rtol=0, atol=1e-5)


def test_learned_temperature(actor):
    td = window()
    loss = MaskedOnlineDTLoss(actor, lambda_entropy=0.2, learn_temperature=True)
    assert loss.target_entropy.item() == -A
    ref = OnlineDTLoss(actor, alpha_init=0.2)
    torch.manual_seed(5)
    out = loss(td.clone())
    torch.manual_seed(5)
    out_ref = ref(td.clone())
    torch.testing.assert_close(out["loss_alpha"], out_ref["loss_alpha"])
    torch.testing.assert_close(out["loss_entropy"], out_ref["loss_entropy"])
    # the temperature learns only from loss_alpha; the actor not from loss_alpha
    out["loss_alpha"].backward(retain_graph=True)
    assert loss.log_alpha.grad is not None and loss.log_alpha.grad.abs() > 0
    assert all(p.grad is None for p in loss.actor_network_params.values(True, True))
    loss.zero_grad()
    (out["loss_nll"] + out["loss_entropy"]).backward()
    assert loss.log_alpha.grad is None or loss.log_alpha.grad.abs() == 0
    grads = [p.grad for p in loss.actor_network_params.values(True, True)]
    assert all(g is not None for g in grads) and sum(g.abs().sum() for g in grads) > 0
    assert set(loss.parameters()) == set(loss.actor_network_params.values(True, True)) | {loss.log_alpha}
    assert MaskedOnlineDTLoss(actor, target_entropy=-1.5).target_entropy.item() == -1.5


def test_training_reduces_nll(actor):
    td = window()
    loss = MaskedOnlineDTLoss(actor, lambda_entropy=0.0)
    opt = torch.optim.Adam(loss.parameters(), lr=3e-3)
    first = None
    for _ in range(30):
        out = loss(td)
        opt.zero_grad()
        (out["loss_nll"] + out["loss_entropy"]).backward()
        opt.step()
        first = out["loss_nll"].item() if first is None else first
    assert out["loss_nll"].item() < first - 1.0


def test_set_keys_and_errors(actor):
    td = window()
    loss = MaskedOnlineDTLoss(actor)
    td["target"] = torch.rand(B, K, A) * 1.8 - 0.9
    td["valid"] = td["mask"].clone()
    td["valid"][:, :3] = False
    loss.set_keys(action_target="target", mask="valid")
    assert "target" in loss.in_keys and "valid" in loss.in_keys
    out = loss(td.clone())
    with torch.no_grad():
        dist = actor.get_dist(td.clone())
    expected = -dist.log_prob(td["target"])[:, 3:].mean()
    torch.testing.assert_close(out["loss_nll"], expected)
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss.set_keys(observation="x")
    with pytest.raises(KeyError, match="'valid'"):
        loss(td.exclude("valid"))
    td_grad = window()
    td_grad["action"].requires_grad_()
    with pytest.raises(RuntimeError, match="must not require grad"):
        MaskedOnlineDTLoss(actor)(td_grad)
    with pytest.raises(ValueError, match="lambda_entropy"):
        MaskedOnlineDTLoss(actor, lambda_entropy=0.0, learn_temperature=True)


def test_targets_at_the_bounds_stay_finite(actor):
    td = window()
    td["action"][..., -1] = torch.where(torch.rand(B, K) > 0.5, 1.0, -1.0)  # e.g. pick open/close
    out = MaskedOnlineDTLoss(actor)(td)
    assert torch.isfinite(out["loss_nll"])


def test_closed_form_tanh_normal_equals_the_distribution_path(actor):
    from torchrl.modules import TanhNormal

    from trakdis.objectives.dt_loss import tanh_normal_log_prob, tanh_normal_rsample_log_prob

    td = window(pad=(0, 2, 5, 3))
    fast = MaskedOnlineDTLoss(actor, lambda_entropy=0.1)
    generic = MaskedOnlineDTLoss(actor, lambda_entropy=0.1)
    assert fast._tanh_normal_keys == ("loc", "scale")
    generic._tanh_normal_keys = None  # force TanhNormal objects (the path for other distributions)
    outs, grads = [], []
    for loss in (fast, generic):
        torch.manual_seed(7)
        out = loss(td.clone())
        outs.append(out)
        grads.append(torch.autograd.grad(out["loss_nll"] + out["loss_entropy"], list(loss.actor_network_params.values(True, True))))
    for key in ("loss_nll", "loss_entropy", "entropy"):
        torch.testing.assert_close(outs[0][key], outs[1][key], rtol=0, atol=0)
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b)
    # the functions themselves, including saturated targets and extreme locations
    loc = torch.tensor([[0.0, 5.0, -30.0], [0.3, -2.0, 12.0]])
    scale = torch.tensor([[1.0, 0.01, 3.0], [0.0067, 0.0067, 0.0067]])  # e^-5: the smallest std
    value = torch.tensor([[0.5, 1.0, -1.0], [-0.999, 0.2, 0.9999999]])
    dist = TanhNormal(loc, scale, low=-1.0, high=1.0)
    torch.testing.assert_close(tanh_normal_log_prob(loc, scale, value), dist.log_prob(value), rtol=0, atol=0)
    torch.manual_seed(2)
    _, lp = dist.rsample_and_log_prob((3,))
    torch.manual_seed(2)
    torch.testing.assert_close(tanh_normal_rsample_log_prob(loc, scale, 3), lp, rtol=0, atol=0)


def test_other_distributions_use_the_generic_path():
    from tensordict.nn import TensorDictModule
    from torchrl.data import Bounded
    from torchrl.modules import ProbabilisticActor, TanhNormal

    from trakdis.modules.decision_transformer import StochasticDTActor

    torch.manual_seed(0)
    cfg = DTModelConfig(state_dim=S, action_dim=A, embed_dim=32, n_layer=2, n_head=4, context_len=K, dropout=0.0, attn_dropout=0.0)
    module = TensorDictModule(StochasticDTActor(cfg), in_keys=["observation", "action", "return_to_go", "timestep", "mask"], out_keys=["loc", "scale"])
    actor = ProbabilisticActor(
        module, in_keys=["loc", "scale"], out_keys=["action"], spec=Bounded(-2.0, 2.0, shape=(A,)),
        distribution_class=TanhNormal, distribution_kwargs={"low": -2.0, "high": 2.0},
    )
    loss = MaskedOnlineDTLoss(actor, lambda_entropy=0.1, action_eps=0.0)
    assert loss._tanh_normal_keys is None
    td = window()
    torch.manual_seed(3)
    out = loss(td.clone())
    torch.manual_seed(3)
    ref = OnlineDTLoss(actor, alpha_init=0.1, fixed_alpha=True)(td.clone())
    torch.testing.assert_close(out["loss_nll"], ref["loss_log_likelihood"])
    torch.testing.assert_close(out["loss_entropy"], ref["loss_entropy"])


@pytest.mark.parametrize("loc_bound", [0.0, 5.0])
def test_own_saturated_mean_actions_as_targets(loc_bound):
    # Online fine-tuning writes the policy's own mean actions back as targets. A grasp command the
    # policy is sure of has a large pre-tanh mean and the smallest std; unbounded, its action
    # rounds to +-1.0 in float32, is clamped to atanh(1 - 1e-6) = 7.25 and costs a huge NLL.
    cfg = DTModelConfig(state_dim=4, action_dim=2, embed_dim=16, n_layer=1, n_head=2, context_len=3, dropout=0.0,
                        attn_dropout=0.0, loc_bound=loc_bound)
    actor = make_dt_actor(cfg)
    dt = actor.module[0].module
    with torch.no_grad():
        dt.head_loc.weight.zero_()
        dt.head_loc.bias.fill_(12.0)  # a saturated, confident grasp command
        dt.head_log_std.weight.zero_()
        dt.head_log_std.bias.fill_(-20.0)  # log-std at its lower bound (-5)
    td = random_window(8, 3, 4, 2)
    with torch.no_grad():
        out = actor(td.clone())
    if loc_bound:
        assert out["loc"].max() < loc_bound
    td["action"] = out["loc"].tanh()  # the mean action, as stored by a rollout
    loss = MaskedOnlineDTLoss(actor, lambda_entropy=0.0, action_eps=cfg.action_eps)
    nll = float(loss(td)["loss_nll"])
    if loc_bound:
        assert nll < 0  # the own mean action is the mode: a high likelihood, not a penalty
    else:
        assert nll > 1e3


def test_is_torchrl_online_dt_loss_with_zero_or_exact_fixed_weight(actor):
    loss = MaskedOnlineDTLoss(actor, lambda_entropy=0.0)
    assert isinstance(loss, OnlineDTLoss) and loss.loss_mask_key == "mask"
    out = loss(window(pad=(0, 2, 5, 3)))
    assert out["alpha"].item() == 0.0 and out["loss_entropy"].item() == 0.0 and "loss_alpha" not in out.keys()
    assert torch.isfinite(out["entropy"])
    # the fixed weight is used exactly (OnlineDTLoss's exp(log(0.1)) is 1 ulp off in float32)
    assert MaskedOnlineDTLoss(actor, lambda_entropy=0.1).alpha.item() == torch.tensor(0.1).item()
    loss.set_keys(mask="valid")
    assert loss.loss_mask_key == "valid" and "valid" in loss.in_keys


def test_loads_checkpoints_of_the_former_dt_loss(actor):
    for kw in (dict(lambda_entropy=0.1), dict(lambda_entropy=0.2, learn_temperature=True)):
        loss = MaskedOnlineDTLoss(actor, **kw)
        state = loss.state_dict()
        old = {k: v for k, v in state.items() if k not in ("alpha_init",) and not (k == "log_alpha" and not loss.learn_temperature)}
        fresh = MaskedOnlineDTLoss(actor, **kw)
        fresh.load_state_dict(old)  # strict: the keys OnlineDTLoss adds are filled in
        torch.testing.assert_close(fresh.alpha, loss.alpha)
