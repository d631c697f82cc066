import pytest
import torch

from trakdis.utils.optim import Lamb, make_optimizer, make_warmup_scheduler


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
    from tensordict import TensorDict

    from trakdis.utils.training import Updater

    class Quadratic(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.ones(2))

        def forward(self, td):
            return TensorDict(loss_q=(self.w**2).sum())

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
