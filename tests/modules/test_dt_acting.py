import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from trakdis.modules import DTActingPolicy, DTModelConfig, make_dt_actor

S, A, K = 5, 3, 4


@pytest.fixture(scope="module")
def actor():
    torch.manual_seed(0)
    cfg = DTModelConfig(state_dim=S, action_dim=A, embed_dim=32, n_layer=2, n_head=4, context_len=K, max_timestep=64)
    return make_dt_actor(cfg, observation_key="state").eval()


def rollout(policy, steps, n, resets, seed=0):
    """Drive the policy with random inputs; env i is reset at the steps listed in resets[i]."""
    g = torch.Generator().manual_seed(seed)
    step_count = torch.zeros(n, 1, dtype=torch.long)
    log = []
    for t in range(steps):
        for i in range(n):
            if t in resets.get(i, ()):
                step_count[i] = 0
        td = TensorDict(
            state=torch.randn(n, S, generator=g),
            return_to_go=torch.randn(n, 1, generator=g),
            step_count=step_count.clone(),
            batch_size=[n],
        )
        policy(td)
        log.append(td)
        step_count += 1
    return torch.stack(log, dim=1)  # [n, steps]


def reference_actions(actor, traj, i, t):
    """Deterministic action at step t of env i from a left-padded training window."""
    sc = traj["step_count"][i, :, 0]
    start = t - int(sc[t])  # index of the env's last reset
    lo = max(start, t - K + 1)
    seg = traj[i, lo : t + 1]
    k = seg.shape[0]
    td = TensorDict(
        state=torch.zeros(1, K, S),
        action=torch.zeros(1, K, A),
        return_to_go=torch.zeros(1, K, 1),
        timestep=torch.zeros(1, K, dtype=torch.long),
        mask=torch.zeros(1, K, dtype=torch.bool),
        batch_size=[1, K],
    )
    td["state"][0, K - k :] = seg["state"]
    td["action"][0, K - k :] = seg["action"]
    td["return_to_go"][0, K - k :] = seg["return_to_go"]
    td["timestep"][0, K - k :] = seg["step_count"][:, 0]
    td["mask"][0, K - k :] = True
    with torch.no_grad():
        return torch.tanh(actor.get_dist(td).root_dist.loc[0, -1]), int(sc[t])


@pytest.mark.parametrize("mode", ["window", "kv_cache"])
def test_actions_equal_training_window_forward(actor, mode):
    policy = DTActingPolicy(actor, mode=mode)
    n, steps = 3, 11
    resets = {0: (0,), 1: (0, 3), 2: (0, 6, 7)}
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        traj = rollout(policy, steps, n, resets)
    checked = 0
    for i in range(n):
        for t in range(steps):
            ref, since_reset = reference_actions(actor, traj, i, t)
            if mode == "kv_cache" and since_reset >= K:
                continue  # the rolling cache is only exact before the window starts sliding
            torch.testing.assert_close(traj["action"][i, t], ref, rtol=0, atol=1e-5)
            checked += 1
    assert checked >= 20


def test_kv_cache_is_an_approximation_after_k_steps(actor):
    """Documented behaviour: after K steps the cached keys/values carry older context."""
    pol_w, pol_kv = DTActingPolicy(actor, mode="window"), DTActingPolicy(actor, mode="kv_cache")
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        tw = rollout(pol_w, 9, 2, {0: (0,), 1: (0,)})
        tk = rollout(pol_kv, 9, 2, {0: (0,), 1: (0,)})
    torch.testing.assert_close(tk["action"][:, :K], tw["action"][:, :K], rtol=0, atol=1e-5)
    assert (tk["action"][:, K:] - tw["action"][:, K:]).abs().max() > 1e-6


@pytest.mark.parametrize("mode", ["window", "kv_cache"])
def test_exploration_type_and_shapes(actor, mode):
    policy = DTActingPolicy(actor, mode=mode)
    td = TensorDict(state=torch.randn(2, S), return_to_go=torch.ones(2, 1), step_count=torch.zeros(2, 1, dtype=torch.long), batch_size=[2])
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        a1 = policy(td.clone())["action"]
        a2 = policy(td.clone())["action"]  # step_count 0 again: a fresh context, same action
    torch.testing.assert_close(a1, a2)
    with set_exploration_type(ExplorationType.RANDOM):
        torch.manual_seed(0)
        r1 = policy(td.clone())["action"]
        torch.manual_seed(1)
        r2 = policy(td.clone())["action"]
    assert r1.shape == (2, A) and not torch.allclose(r1, r2) and r1.abs().max() <= 1
    # unbatched env and batch of 1 give the same as row 0 of the batch
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        single = policy(td[0].clone())["action"]
        one = policy(td[:1].clone())["action"]
    assert single.shape == (A,) and one.shape == (1, A)
    torch.testing.assert_close(single, a1[0])
    torch.testing.assert_close(one[0], a1[0])
    # 2-D batch
    td4 = TensorDict(state=torch.randn(2, 3, S), return_to_go=torch.ones(2, 3, 1), step_count=torch.zeros(2, 3, 1, dtype=torch.long), batch_size=[2, 3])
    assert policy(td4)["action"].shape == (2, 3, A)


def test_reset_method_and_stored_actions(actor):
    policy = DTActingPolicy(actor, mode="window")
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        traj = rollout(policy, 5, 2, {0: (0,), 1: (0,)})
        # the context holds the policy's own actions
        stored = policy._act[:, [(policy._ptr - 1 - j) % K for j in range(K)][::-1]]
        torch.testing.assert_close(stored, traj["action"][:, -K:])
        policy.reset()
        again = rollout(policy, 5, 2, {0: (0,), 1: (0,)})
    torch.testing.assert_close(again["action"], traj["action"])


def test_errors(actor):
    with pytest.raises(ValueError, match="mode"):
        DTActingPolicy(actor, mode="full")
    policy = DTActingPolicy(actor)
    bad = TensorDict(state=torch.randn(2, S + 1), return_to_go=torch.ones(2, 1), step_count=torch.zeros(2, 1, dtype=torch.long), batch_size=[2])
    with pytest.raises(ValueError, match="'state' has shape"):
        policy(bad)
    late = TensorDict(state=torch.randn(2, S), return_to_go=torch.ones(2, 1), step_count=torch.full((2, 1), 64), batch_size=[2])
    with pytest.raises(ValueError, match="max_timestep"):
        DTActingPolicy(actor, mode="kv_cache")(late)


def test_input_dtypes_are_converted(actor):
    policy = DTActingPolicy(actor)
    td = TensorDict(state=torch.randn(2, S), return_to_go=torch.ones(2, 1), step_count=torch.zeros(2, 1, dtype=torch.long), batch_size=[2])
    td64 = TensorDict(
        state=td["state"].double(), return_to_go=td["return_to_go"].double(), step_count=td["step_count"].int(), batch_size=[2]
    )
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        torch.testing.assert_close(policy(td64)["action"], policy(td)["action"])


@pytest.mark.parametrize("mode", ["window", "kv_cache"])
def test_empty_batch_and_non_finite_inputs_are_refused(actor, mode):
    policy = DTActingPolicy(actor, mode=mode)

    def step(state, rtg=None, step_count=0):
        n = state.shape[0]
        return TensorDict(state=state, return_to_go=torch.ones(n, 1) if rtg is None else rtg,
                          step_count=torch.full((n, 1), step_count), batch_size=[n])

    with pytest.raises(ValueError, match=r"empty batch: 'state' has shape \(0, 5\)"):
        policy(step(torch.randn(0, S)))
    g = torch.Generator().manual_seed(0)
    first = step(torch.randn(2, S, generator=g))
    policy(first)
    nan = torch.randn(2, S, generator=g)
    nan[1, 2] = float("nan")
    with pytest.raises(ValueError, match=r"'state' holds NaN or inf values \(envs \[1\]"):
        policy(step(nan, step_count=1))
    with pytest.raises(ValueError, match="'return_to_go' holds NaN"):
        policy(step(torch.randn(2, S), rtg=torch.tensor([[1.0], [float("inf")]]), step_count=1))
    # the refused steps left the context as it was: the next finite step acts as if they never came
    fresh = DTActingPolicy(actor, mode=mode)
    fresh(first.clone())
    ok = step(torch.randn(2, S, generator=g), step_count=1)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        a = policy(ok.clone())["action"]
        b = fresh(ok.clone())["action"]
    assert torch.isfinite(a).all()
    torch.testing.assert_close(a, b)


@pytest.mark.parametrize("mode", ["window", "kv_cache"])
def test_hidden_action_dims_act_as_in_training(mode):
    # the acting context keeps the policy's own actions; the hidden dims of them are left out of the
    # tokens in acting (both modes) as in the training forward
    torch.manual_seed(0)
    cfg = DTModelConfig(state_dim=S, action_dim=A, embed_dim=32, n_layer=2, n_head=4, context_len=K, max_timestep=64,
                        hidden_action_dims=(2,))
    hidden_actor = make_dt_actor(cfg, observation_key="state").eval()
    policy = DTActingPolicy(hidden_actor, mode=mode)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        traj = rollout(policy, 6, 2, {0: (0,), 1: (0,)})
    for i in range(2):
        for t in range(min(6, K)):
            ref, _ = reference_actions(hidden_actor, traj, i, t)
            torch.testing.assert_close(traj["action"][i, t], ref, rtol=0, atol=1e-5)
