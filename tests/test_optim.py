"""Optimisation: LAMB and Adam(W), the LR schedules, and the Updater (steps, non-finite losses, state)."""
import pytest
import torch
from tensordict import TensorDict

from trakdis.modules import DTModelConfig, make_dt_actor
from trakdis.objectives import MaskedOnlineDTLoss
from quadratic_loss import Quadratic
from trakdis.optim import Lamb, Updater, make_optimizer, make_warmup_scheduler, mean_metrics


@pytest.mark.parametrize("name", ["lamb", "adamw", "adam"])
def test_optimizers_fit_linear_regression(name):
    torch.manual_seed(0)
    x = torch.randn(256, 4)
    y = x @ torch.tensor([1.0, -2.0, 0.5, 3.0]) + 0.1
    model = torch.nn.Linear(4, 1)
    opt = make_optimizer(name, model.parameters(), lr=0.05, weight_decay=1e-4)
    first = None
    for _ in range(300):
        loss = ((model(x).squeeze(-1) - y) ** 2).mean()
        first = first if first is not None else loss.item()
        opt.zero_grad(); loss.backward(); opt.step()
    assert loss.item() < 0.01 * first


def test_lamb_state_roundtrip_and_errors():
    p = torch.nn.Parameter(torch.ones(3))
    opt = Lamb([p], lr=0.1)
    p.grad = torch.ones(3)
    opt.step()
    sd = opt.state_dict()
    opt2 = Lamb([torch.nn.Parameter(p.detach().clone())], lr=0.1)
    opt2.load_state_dict(sd)
    assert opt2.state_dict()["state"][0]["step"] == 1
    # trust ratio: a step moves the weight by lr * ||w|| / ||update|| * update = lr * w for uniform values
    assert torch.allclose(p.detach(), torch.full((3,), 0.9), atol=1e-5)
    with pytest.raises(ValueError, match="nope"):
        make_optimizer("nope", [p], lr=0.1)
    with pytest.raises(ValueError):
        Lamb([p], lr=0.0)


def test_warmup():
    p = torch.nn.Parameter(torch.ones(1))
    opt = torch.optim.SGD([p], lr=1.0)
    sched = make_warmup_scheduler(opt, 4)
    lrs = []
    for _ in range(6):
        lrs.append(opt.param_groups[0]["lr"]); opt.step(); sched.step()
    assert lrs == [0.25, 0.5, 0.75, 1.0, 1.0, 1.0]


def test_warmup_then_cosine_decay_then_constant():
    import pytest

    p = torch.nn.Parameter(torch.ones(1))
    opt = torch.optim.SGD([p], lr=1.0)
    sched = make_warmup_scheduler(opt, 2, decay_steps=6, min_fraction=0.1)
    lrs = []
    for _ in range(9):
        lrs.append(opt.param_groups[0]["lr"]); opt.step(); sched.step()
    assert lrs[:2] == [0.5, 1.0]
    assert all(a > b for a, b in zip(lrs[1:5], lrs[2:6]))  # strictly decreasing down to update 6
    assert lrs[5] == pytest.approx(0.1) and lrs[6:] == pytest.approx([0.1] * 3)
    with pytest.raises(ValueError, match="min_fraction"):
        make_warmup_scheduler(opt, 2, decay_steps=6, min_fraction=0.0)


def test_updater_switches_to_a_constant_lr():
    up = Updater(Quadratic(), optimizer="adam", lr=1e-2, warmup_steps=1, decay_steps=4, min_lr_fraction=0.5)
    lrs = [up.step(TensorDict())["lr"] for _ in range(6)]
    assert lrs[3:] == [5e-3] * 3
    up.set_constant_lr(1e-4)
    assert [up.step(TensorDict())["lr"] for _ in range(3)] == [1e-4] * 3
    state = up.state_dict()
    up2 = Updater(Quadratic(), optimizer="adam", lr=1e-2, warmup_steps=1, decay_steps=4, min_lr_fraction=0.5)
    up2.load_state_dict(state)
    up2.set_constant_lr(1e-4)
    assert up2.step(TensorDict())["lr"] == 1e-4


def tiny_actor(key="state"):
    cfg = DTModelConfig(embed_dim=16, n_layer=1, n_head=1, context_len=4, dropout=0.0).for_task(5, 2, horizon=10)
    return cfg, make_dt_actor(cfg, observation_key=key)


def window(B=8, K=4):
    g = torch.Generator().manual_seed(0)
    return TensorDict({
        "state": torch.randn(B, K, 5, generator=g),
        "action": torch.rand(B, K, 2, generator=g) * 1.8 - 0.9,
        "return_to_go": torch.randn(B, K, 1, generator=g),
        "timestep": torch.arange(K).expand(B, K).clone(),
        "mask": torch.ones(B, K, dtype=torch.bool),
    }, batch_size=[B, K])


def test_updater_reduces_dt_loss_and_roundtrips():
    torch.manual_seed(0)
    cfg, actor = tiny_actor()
    up = Updater(MaskedOnlineDTLoss(actor, lambda_entropy=0.0), lr=3e-3, warmup_steps=1)
    batch = window()
    first = up.step(batch)
    for _ in range(60):
        last = up.step(batch)
    assert last["loss_nll"] < first["loss_nll"] - 0.5
    assert {"loss_nll", "loss_entropy", "lr", "grad_norm"} <= set(last)
    _, actor2 = tiny_actor()
    up2 = Updater(MaskedOnlineDTLoss(actor2, lambda_entropy=0.0), lr=3e-3, warmup_steps=1)
    up2.load_state_dict(up.state_dict())
    assert up2.updates == 61
    assert torch.equal(next(iter(actor2.parameters())), next(iter(actor.parameters())))
    assert mean_metrics([{"a": 1.0}, {"a": 3.0, "b": 1.0}]) == {"train/a": 2.0, "train/b": 1.0}


def test_updater_rejects_non_finite():
    _, actor = tiny_actor()
    up = Updater(MaskedOnlineDTLoss(actor), lr=1e-3)
    batch = window()
    batch["state"][0, 0, 0] = float("nan")
    with pytest.raises(FloatingPointError, match="non-finite loss"):
        up.step(batch)
