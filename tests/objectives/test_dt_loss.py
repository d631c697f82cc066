import pytest
import torch
from dt_windows import random_window
from torchrl.objectives import OnlineDTLoss

from trakdis.modules import DTConfig, make_dt_actor
from trakdis.objectives import DTLoss

S, A, B, K = 5, 3, 4, 6


@pytest.fixture
def actor():
    torch.manual_seed(0)
    cfg = DTConfig(state_dim=S, action_dim=A, embed_dim=32, n_layer=2, n_head=4, context_len=K, dropout=0.0, attn_dropout=0.0)
    return make_dt_actor(cfg)


def window(pad=(0, 0, 0, 0), seed=0):
    return random_window(B, K, S, A, pad=pad, seed=seed)


def test_matches_torchrl_online_dt_loss_fixed_temperature(actor):
    td = window()
    ours = DTLoss(actor, lambda_entropy=0.1)
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
    out = DTLoss(actor, lambda_entropy=0.1)(td.clone())
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
    out2 = DTLoss(actor, lambda_entropy=0.1)(td2)
    torch.testing.assert_close(out2["loss_nll"], out["loss_nll"], rtol=0, atol=1e-5)
    torch.testing.assert_close(out2["loss_entropy"], out["loss_entropy"], rtol=0, atol=1e-5)


def test_learned_temperature(actor):
    td = window()
    loss = DTLoss(actor, lambda_entropy=0.2, learn_temperature=True)
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
    assert DTLoss(actor, target_entropy=-1.5).target_entropy.item() == -1.5


def test_training_reduces_nll(actor):
    td = window()
    loss = DTLoss(actor, lambda_entropy=0.0)
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
    loss = DTLoss(actor)
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
        DTLoss(actor)(td_grad)
    with pytest.raises(ValueError, match="lambda_entropy"):
        DTLoss(actor, lambda_entropy=0.0, learn_temperature=True)


def test_targets_at_the_bounds_stay_finite(actor):
    td = window()
    td["action"][..., -1] = torch.where(torch.rand(B, K) > 0.5, 1.0, -1.0)  # e.g. pick open/close
    out = DTLoss(actor)(td)
    assert torch.isfinite(out["loss_nll"])
