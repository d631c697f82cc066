"""State standardisation (TorchRL's ObservationNorm built by state_normalizer, with NormalizedPolicy
acting on it) and the proprioception override (a TorchRL Transform)."""
import pytest
import torch
from points_env import PointsEnv
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import Compose, ObservationNorm, TransformedEnv, check_env_specs

from trakdis.modules import NormalizedPolicy
from trakdis.transforms import (OutOfViewFill, ProprioceptionOverride, StateNoise, fit_state_normalizer,
                                fixed_camera_matrix, normalizer_from_state_dict, normalizer_parts,
                                normalizer_state_dict, normalizer_with_keys, state_normalizer)


def _states():
    states = torch.randn(50, 3) * torch.tensor([1.0, 10.0, 0.0]) + torch.tensor([5.0, -2.0, 1.0])
    return states


def test_state_normalizer_is_observation_norm_and_normalized_policy():
    states = _states()
    norm = fit_state_normalizer(states, keys=("state", "state_estimate"))
    assert isinstance(norm, ObservationNorm) and bool(norm.standard_normal) and norm.in_keys == ["state", "state_estimate"]
    out = norm(TensorDict({"state": states, "state_estimate": states.clone(), "other": states.clone()}, [50]))
    assert torch.allclose(out["state"][:, :2].mean(0), torch.zeros(2), atol=1e-5)
    assert torch.allclose(out["state"][:, :2].std(0), torch.ones(2), atol=1e-4)
    assert torch.equal(out["state"], out["state_estimate"]) and torch.equal(out["other"], states)
    assert norm.scale[2] == 1e-3  # constant dimension: clamped, no division by zero
    # the formula, bit for bit: mean and std in float64, then float32; (x - loc) / scale, no eps added
    flat = states.double()
    loc, scale = flat.mean(0).float(), flat.std(0).clamp_min(1e-3).float()
    assert torch.equal(norm.loc, loc) and torch.equal(norm.scale, scale)
    assert torch.equal(out["state"], (states - loc) / scale)
    assert norm(TensorDict({"state": states.double()}, [50]))["state"].dtype == torch.float64  # promoted, as before
    again = normalizer_from_state_dict(normalizer_state_dict(norm))
    assert torch.equal(again.loc, norm.loc) and again.in_keys == norm.in_keys
    assert torch.equal(norm(TensorDict({"state_estimate": states}, [50]))["state_estimate"], out["state"])  # "state" absent: skipped
    seen = {}
    inner = TensorDictModule(lambda s: seen.setdefault("s", s.clone()).sum(-1, keepdim=True), ["state"], ["action"])
    td = TensorDict({"state": states[:4].clone(), "state_estimate": states[:4].clone()}, [4])
    NormalizedPolicy(inner, norm, "state")(td)
    assert torch.equal(seen["s"], (states[:4] - loc) / scale)  # the policy saw normalised states
    assert torch.equal(td["state"], states[:4]) and "action" in td.keys()  # the raw state is back
    assert torch.equal(td["state_estimate"], states[:4])  # the normaliser's other key untouched
    # a plain ObservationNorm (standard_normal) serves as well
    plain = ObservationNorm(loc, scale, in_keys=["state"], standard_normal=True)
    seen.clear()
    NormalizedPolicy(inner, plain, "state")(TensorDict({"state": states[:4].clone()}, [4]))
    assert torch.equal(seen["s"], (states[:4] - loc) / scale)
    with pytest.raises(ValueError):
        state_normalizer(torch.zeros(2), torch.zeros(2))
    with pytest.raises(ValueError, match="standard_normal"):
        normalizer_parts(ObservationNorm(loc, scale, in_keys=["state"]))


def test_proprioception_override():
    td = TensorDict({"state": torch.arange(6.0).expand(2, 6).clone(), "state_estimate": torch.zeros(2, 6)}, [2])
    ProprioceptionOverride(range(4, 6))(td)
    assert td["state_estimate"][0].tolist() == [0, 0, 0, 0, 4, 5]
    with pytest.raises(KeyError, match="state"):
        ProprioceptionOverride([1])(TensorDict({"state_estimate": torch.zeros(1, 2)}, [1]))
    only_state = TensorDict({"state": torch.ones(1, 2)}, [1])
    assert ProprioceptionOverride([1])(only_state) is only_state and "state_estimate" not in only_state.keys()


def test_compose_applies_the_steps_in_order():
    td = TensorDict({"state": torch.tensor([[1.0, 2.0, 3.0, 4.0]])}, [1])
    norm = state_normalizer(torch.ones(4), torch.full((4,), 2.0))
    override = ProprioceptionOverride((3,))
    td["state_estimate"] = torch.zeros(1, 4)
    out = Compose(override, state_normalizer(torch.ones(4), torch.full((4,), 2.0), keys=("state_estimate",)))(td.clone())
    assert out["state_estimate"].tolist() == [[-0.5, -0.5, -0.5, 1.5]]  # overridden first, then standardised
    assert torch.equal(Compose(norm)(td.clone())["state"], norm(td.clone())["state"])
    assert torch.equal(Compose()(td.clone())["state"], td["state"])  # no steps: the identity


def test_state_normalizer_with_out_of_view_fill(tmp_path):
    """--mask-unseen-pickers: the fill runs before standardising (Compose), travels in the state
    dict; state dicts without it (earlier policy files and checkpoints) load as before."""
    from trakdis.utils.checkpoint import read_checkpoint, save_checkpoint

    fill = OutOfViewFill.for_task("ClothFold")
    states = torch.rand(4, 5, 18) * 0.2 - 0.1
    states[1, :, 12:15] = torch.tensor([0.0, 0.0, 0.3])  # picker 0 high out of view
    states[2, :, 15:18] = torch.tensor([0.4, 0.0, 0.0])  # picker 1 beyond the frame's edge
    norm = fit_state_normalizer(states, keys=("state", "state_estimate"), fill=fill)
    plain = fit_state_normalizer(states, keys=("state", "state_estimate"))
    assert isinstance(norm, Compose) and isinstance(norm[0], OutOfViewFill) and isinstance(norm[1], ObservationNorm)
    (n, f), (p, none) = normalizer_parts(norm), normalizer_parts(plain)
    assert none is None and f.in_keys == ["state", "state_estimate"]  # the mask runs on the normaliser's keys
    assert torch.equal(n.loc, p.loc) and torch.equal(n.scale, p.scale)  # fitted on the raw states

    def run(t, x):
        return t(TensorDict({"state": x}, x.shape[:-1]))["state"]

    raw = states.clone()
    assert torch.equal(run(norm, states), (fill.mask(states) - n.loc) / n.scale)
    assert torch.equal(states, raw) and not torch.allclose(run(norm, states), run(plain, states))
    save_checkpoint(tmp_path / "n.pt", {"with": normalizer_state_dict(norm), "without": normalizer_state_dict(plain)})
    saved = read_checkpoint(tmp_path / "n.pt")
    assert set(saved["with"]) == {"loc", "scale", "keys", "fill"} and saved["with"]["keys"] == ["state", "state_estimate"]
    again = normalizer_from_state_dict(saved["with"])
    g = normalizer_parts(again)[1]
    assert g.starts == fill.starts and torch.equal(g.camera_matrix, fill.camera_matrix) and torch.equal(g.fill, fill.fill)
    assert torch.equal(run(again, states), run(norm, states))
    assert "fill" not in saved["without"] and normalizer_parts(normalizer_from_state_dict(saved["without"]))[1] is None
    old = {k: v for k, v in saved["without"].items() if k != "keys"}  # the oldest layout: loc and scale only
    assert normalizer_parts(normalizer_from_state_dict(old))[0].in_keys == ["state"]
    moved = normalizer_with_keys(norm, ("state_estimate",))
    assert normalizer_parts(moved)[1].in_keys == ["state_estimate"] and normalizer_parts(moved)[0].in_keys == ["state_estimate"]
    with pytest.raises(TypeError, match="OutOfViewFill"):
        state_normalizer(n.loc, n.scale, fill=fill.to_dict())
    with pytest.raises(ValueError, match="do not fit 15-dim states"):
        state_normalizer(n.loc[:15], n.scale[:15], fill=fill)


def test_in_an_env_and_a_replay_buffer():
    """ProprioceptionOverride and the normaliser (with its mask) as TorchRL transforms: in a
    TransformedEnv (steps and resets, specs checked) and as a replay buffer's sampling transform."""
    fill = OutOfViewFill(fixed_camera_matrix("ClothFold", 32), 32, [0, 3])
    loc, scale = torch.full((6,), 0.01), torch.full((6,), 0.1)
    torch.manual_seed(0)
    raw = PointsEnv().rollout(5)
    env = TransformedEnv(PointsEnv(), Compose(ProprioceptionOverride([0, 1, 2]),
                                              state_normalizer(loc, scale, keys=["state", "state_estimate"], fill=fill)))
    check_env_specs(env)
    torch.manual_seed(0)
    out = env.rollout(5)
    for key in ((), ("next",)):
        state, est = raw[key + ("state",)], raw[key + ("state_estimate",)].clone()
        est[..., :3] = state[..., :3]  # the pickers' proprioception
        assert torch.equal(out[key + ("state",)], (fill.mask(state) - loc) / scale)
        assert torch.equal(out[key + ("state_estimate",)], (fill.mask(est) - loc) / scale)
    assert (out["state"][..., 5] == (0.4 - 0.01) / 0.1).all()  # the point above the frame: the sentinel
    buffer = ReplayBuffer(storage=LazyTensorStorage(10), batch_size=5,
                          transform=Compose(StateNoise(0.0, in_keys=["state_estimate"]), ProprioceptionOverride([0, 1, 2]),
                                            state_normalizer(loc, scale, keys=["state", "state_estimate"], fill=fill)))
    buffer.extend(raw.select("state", "state_estimate").set("step", torch.arange(5)))
    assert torch.equal(buffer.storage.get(torch.arange(5))["state"], raw["state"])  # stored raw
    sample = buffer.sample()
    assert torch.equal(sample["state"], out["state"][sample["step"]])  # standardised when sampled, as in the env
    assert torch.equal(sample["state_estimate"], out["state_estimate"][sample["step"]])
