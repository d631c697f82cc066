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
