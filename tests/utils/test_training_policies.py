import pytest
import torch
from tensordict import TensorDict

from trakdis.modules import StateEncoder, make_dt_actor
from trakdis.objectives import MaskedOnlineDTLoss
from trakdis.utils.checkpoint import CheckpointError, save_checkpoint
from trakdis.utils.policies import NormalizedEncoder, load_encoder, load_policy, save_encoder, save_policy
from trakdis.utils.training import ModelConfig, Updater, episode_to_trajectory, mean_metrics


def tiny_actor(key="state"):
    cfg = ModelConfig(embed_dim=16, n_layer=1, n_head=1, context_len=4, dropout=0.0).dt_config(5, 2, horizon=10)
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


def test_episode_to_trajectory():
    T = 3
    ep = TensorDict({
        "state": torch.randn(T, 5), "action": torch.randn(T, 2), "step_count": torch.arange(T).unsqueeze(-1),
        "return_to_go": torch.zeros(T, 1),
        ("next", "state"): torch.randn(T, 5), ("next", "reward"): torch.tensor([[-1.0], [-2.0], [-3.0]]),
        ("next", "normalized_performance"): torch.rand(T, 1), ("next", "done"): torch.tensor([[False], [False], [True]]),
    }, batch_size=[T])
    traj = episode_to_trajectory(ep)
    assert traj["reward"].squeeze(-1).tolist() == [-1.0, -2.0, -3.0]
    assert traj["done"][-1].item() and "next" not in traj.keys()
    assert torch.equal(traj["state"], ep["state"])
    with pytest.raises(KeyError, match="action"):
        episode_to_trajectory(ep.exclude("action"))


def test_policy_and_encoder_files(tmp_path):
    cfg, actor = tiny_actor()
    save_policy(tmp_path / "policy.pt", kind="teacher", task="ClothFoldDiagonalPinned", horizon=10, dt_config=cfg,
                actor=actor, observation_key="state", target_return=-1.0, rtg_scale=1.0)
    h = load_policy(tmp_path)  # a run directory works too
    assert h.kind == "teacher" and h.task == "ClothFoldDiagonalPinned" and h.horizon == 10 and h.encoder is None
    for a, b in zip(actor.parameters(), h.actor.parameters()):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="ClothFold"):
        load_policy(tmp_path / "policy.pt", task="ClothFold")
    assert load_policy("expert", task="ClothFold").kind == "expert"
    with pytest.raises(ValueError, match="--task"):
        load_policy("expert")
    enc = NormalizedEncoder(StateEncoder(5, channels=(4, 4, 4, 4), hidden_dim=8), torch.arange(5.0), torch.full((5,), 2.0))
    save_encoder(tmp_path / "encoder.pt", enc, task="ClothFold")
    enc2, data = load_encoder(tmp_path / "encoder.pt")
    px = torch.randint(0, 255, (2, 32, 32, 3), dtype=torch.uint8)
    assert torch.allclose(enc.eval()(px), enc2(px))
    with pytest.raises(CheckpointError, match="teacher"):
        load_encoder(tmp_path / "policy.pt")
    save_checkpoint(tmp_path / "bad.pt", {"kind": "encoder", "task": "ClothFold", "dt_config": {}, "actor": {},
                                          "observation_key": "state"})
    with pytest.raises(CheckpointError, match="not a policy"):
        load_policy(tmp_path / "bad.pt")


def test_state_normalizer_and_normalized_policy():
    from tensordict.nn import TensorDictModule

    from trakdis.utils.policies import NormalizedPolicy, StateNormalizer

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
    from trakdis.utils.policies import ProprioceptionOverride

    td = TensorDict({"state": torch.arange(6.0).expand(2, 6).clone(), "state_estimate": torch.zeros(2, 6)}, [2])
    ProprioceptionOverride(range(4, 6))(td)
    assert td["state_estimate"][0].tolist() == [0, 0, 0, 0, 4, 5]
    with pytest.raises(KeyError, match="state"):
        ProprioceptionOverride([1])(TensorDict({"state_estimate": torch.zeros(1, 2)}, [1]))


def test_parallel_batched_env_matches_serial():
    from trakdis.utils.policies import close_env, make_batched_env

    rollouts = []
    for parallel in (False, True):
        env = make_batched_env("ClothFoldDiagonalUnpinned", num_envs=2, parallel=parallel, seed=3, env_kwargs={"horizon": 4})
        try:
            torch.manual_seed(0)
            rollouts.append(env.rollout(4, break_when_any_done=False))
        finally:
            close_env(env)
    serial, parallel = rollouts
    assert parallel.batch_size == serial.batch_size == torch.Size([2, 4])
    torch.testing.assert_close(parallel["state"], serial["state"])
    torch.testing.assert_close(parallel["next", "reward"], serial["next", "reward"])


def test_bad_state_noise_and_horizon_are_refused(tmp_path):
    from trakdis.utils.policies import make_acting_env

    for sigma in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="state_noise must be a finite std >= 0"):
            make_acting_env("ClothFold", state_noise=sigma)
    cfg, actor = tiny_actor()
    save_policy(tmp_path / "policy.pt", kind="teacher", task="ClothFold", horizon=10, dt_config=cfg,
                actor=actor, observation_key="state", target_return=-1.0, rtg_scale=1.0)
    for spec in (tmp_path, "expert"):
        with pytest.raises(ValueError, match="horizon must be >= 1"):
            load_policy(spec, task="ClothFold", horizon=0)
    assert load_policy(tmp_path).horizon == 10 and load_policy(tmp_path, horizon=3).horizon == 3
