"""State standardisation (StateNormalizer, with NormalizedPolicy acting on it) and the proprioception override."""
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from trakdis.modules import NormalizedPolicy
from trakdis.transforms import ProprioceptionOverride, StateNormalizer


def test_state_normalizer_and_normalized_policy():
    states = torch.randn(50, 3) * torch.tensor([1.0, 10.0, 0.0]) + torch.tensor([5.0, -2.0, 1.0])
    norm = StateNormalizer.fit(states, keys=("state", "state_estimate"))
    out = norm(TensorDict({"state": states, "state_estimate": states.clone(), "other": states.clone()}, [50]))
    assert torch.allclose(out["state"][:, :2].mean(0), torch.zeros(2), atol=1e-5)
    assert torch.allclose(out["state"][:, :2].std(0), torch.ones(2), atol=1e-4)
    assert torch.equal(out["state"], out["state_estimate"]) and torch.equal(out["other"], states)
    assert norm.scale[2] == 1e-3  # constant dimension: clamped, no division by zero
    again = StateNormalizer.from_state_dict(norm.state_dict())
    assert torch.equal(again.loc, norm.loc) and again.keys == norm.keys
    seen = {}
    inner = TensorDictModule(lambda s: seen.setdefault("s", s.clone()).sum(-1, keepdim=True), ["state"], ["action"])
    td = TensorDict({"state": states[:4].clone()}, [4])
    NormalizedPolicy(inner, norm, "state")(td)
    assert torch.allclose(seen["s"], norm.normalize(states[:4]))  # the policy saw normalised states
    assert torch.equal(td["state"], states[:4]) and "action" in td.keys()  # the raw state is back
    with pytest.raises(ValueError):
        StateNormalizer(torch.zeros(2), torch.zeros(2))


def test_proprioception_override():
    td = TensorDict({"state": torch.arange(6.0).expand(2, 6).clone(), "state_estimate": torch.zeros(2, 6)}, [2])
    ProprioceptionOverride(range(4, 6))(td)
    assert td["state_estimate"][0].tolist() == [0, 0, 0, 0, 4, 5]
    with pytest.raises(KeyError, match="state"):
        ProprioceptionOverride([1])(TensorDict({"state_estimate": torch.zeros(1, 2)}, [1]))


def test_chain_applies_the_steps_in_order():
    from trakdis.transforms import chain

    td = TensorDict({"state": torch.tensor([[1.0, 2.0, 3.0, 4.0]])}, [1])
    norm = StateNormalizer(torch.ones(4), torch.full((4,), 2.0))
    override = ProprioceptionOverride((3,))
    td["state_estimate"] = torch.zeros(1, 4)
    out = chain(override, StateNormalizer(torch.ones(4), torch.full((4,), 2.0), keys=("state_estimate",)))(td.clone())
    assert out["state_estimate"].tolist() == [[-0.5, -0.5, -0.5, 1.5]]  # overridden first, then standardised
    assert torch.equal(chain(norm)(td.clone())["state"], norm(td.clone())["state"])
    assert chain()(td) is td  # no steps: the identity
    assert chain(None, None)(td) is td  # an optional step that is off: skipped
    assert torch.equal(chain(None, norm, None)(td.clone())["state"], norm(td.clone())["state"])


def test_state_normalizer_with_out_of_view_fill(tmp_path):
    """--mask-unseen-pickers: the fill runs before standardising, travels in the state dict; state
    dicts without it (earlier policy files and checkpoints) load as before."""
    from trakdis.transforms import OutOfViewFill
    from trakdis.utils.checkpoint import load_checkpoint, save_checkpoint

    fill = OutOfViewFill.for_task("ClothFold")
    states = torch.rand(4, 5, 18) * 0.2 - 0.1
    states[1, :, 12:15] = torch.tensor([0.0, 0.0, 0.3])  # picker 0 high out of view
    states[2, :, 15:18] = torch.tensor([0.4, 0.0, 0.0])  # picker 1 beyond the frame's edge
    norm = StateNormalizer.fit(states, keys=("state", "state_estimate"), fill=fill)
    plain = StateNormalizer.fit(states, keys=("state", "state_estimate"))
    assert torch.equal(norm.loc, plain.loc) and torch.equal(norm.scale, plain.scale)  # fitted on the raw states
    raw = states.clone()
    assert torch.allclose(norm.normalize(states), (fill.mask(states) - norm.loc) / norm.scale)
    assert torch.equal(states, raw) and not torch.allclose(norm.normalize(states), plain.normalize(states))
    save_checkpoint(tmp_path / "n.pt", {"with": norm.state_dict(), "without": plain.state_dict()})
    saved = load_checkpoint(tmp_path / "n.pt")
    again = StateNormalizer.from_state_dict(saved["with"])
    assert again.fill == fill and again.keys == norm.keys and torch.equal(again.normalize(states), norm.normalize(states))
    assert "fill" not in saved["without"] and StateNormalizer.from_state_dict(saved["without"]).fill is None
    old = {k: v for k, v in saved["without"].items() if k != "keys"}  # the oldest layout: loc and scale only
    assert StateNormalizer.from_state_dict(old).fill is None
    assert norm.with_keys(("state_estimate",)).fill is fill
    with pytest.raises(TypeError, match="OutOfViewFill"):
        StateNormalizer(norm.loc, norm.scale, fill=fill.state_dict())
    with pytest.raises(ValueError, match="do not fit 15-dim states"):
        StateNormalizer(norm.loc[:15], norm.scale[:15], fill=fill)
