import pytest
import torch
from tensordict import TensorDict

from trakdis.data import TrajectoryReplayBuffer
from trakdis.transforms import EncoderTransform


def _trajs(returns, T=4, lengths=None):
    """Trajectories with given returns (reward spread evenly over the valid steps); state encodes (id, t)."""
    N = len(returns)
    lengths = torch.full((N,), T) if lengths is None else torch.as_tensor(lengths)
    t = torch.arange(T).float()
    ids = torch.arange(N).float()
    valid = (torch.arange(T)[None] < lengths[:, None]).float()
    reward = torch.as_tensor(returns, dtype=torch.float32)[:, None] / lengths[:, None] * valid
    state = torch.stack([ids[:, None].expand(N, T), t[None].expand(N, T)], -1)
    td = TensorDict(
        {"state": state, "action": state[..., :1] * 10 + state[..., 1:], "reward": reward.unsqueeze(-1)}, [N, T]
    )
    return td, lengths


class _FlatEncoder(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.lin = torch.nn.Linear(8 * 8 * 3, 3)

    def forward(self, pixels):
        return self.lin(pixels.flatten(1).float() / 255)


def _stored_ids(rb):
    st = rb.storage._storage
    return {int(st["state"][i, 0, 0]): bool(rb.online[i]) for i in range(len(rb))}


def test_offline_keeps_highest_returns_and_swap_order():
    rb = TrajectoryReplayBuffer(capacity=4, context_len=2, max_len=4)
    offline, _ = _trajs([-3.0, -1.0, -5.0, -2.0, -4.0, -0.5])  # ids 0..5
    rb.load_offline(offline)
    # the 4 highest returns: ids 5 (-0.5), 1 (-1), 3 (-2), 0 (-3); ids 2 and 4 are dropped
    assert set(_stored_ids(rb)) == {5, 1, 3, 0}
    assert rb.online_fraction == 0.0 and rb.num_offline == 4
    online, _ = _trajs([-10.0] * 6)
    online["state"][..., 0] += 100  # online ids 100..105
    expected_removed = [0, 3, 1, 5]  # lowest-return offline first
    for m in range(6):
        rb.add_trajectory(online[m])
        ids = _stored_ids(rb)
        assert rb.online_fraction == pytest.approx(min(m + 1, 4) / 4)
        assert rb.num_online == min(m + 1, 4) and len(rb) == 4
        if m < 4:
            assert set(ids) == set(expected_removed[m + 1 :]) | {100 + i for i in range(m + 1)}
        else:  # then the oldest online ones are replaced
            assert set(ids) == {100 + i for i in range(m - 3, m + 1)}
    assert rb.num_online_added == 6


def test_not_full_buffer_fills_empty_slots_first():
    rb = TrajectoryReplayBuffer(capacity=5, context_len=2, max_len=4)
    rb.load_offline(_trajs([-1.0, -3.0, -2.0])[0])
    online, _ = _trajs([-9.0] * 3)
    online["state"][..., 0] += 100
    rb.extend(online[:2])
    assert set(_stored_ids(rb)) == {0, 1, 2, 100, 101} and rb.online_fraction == pytest.approx(0.4)
    rb.extend(online[2:])
    assert set(_stored_ids(rb)) == {0, 2, 100, 101, 102}  # id 1 had the lowest return


def test_window_padding_mask_and_relabelled_rtg():
    # one trajectory of 3 steps (stored in max_len 6), K = 5: every window is left-padded
    td, lengths = _trajs([-6.0], T=6, lengths=[3])
    td["reward"][0, :3, 0] = torch.tensor([-1.0, -2.0, -3.0])
    rb = TrajectoryReplayBuffer(capacity=2, context_len=5, max_len=6, rtg_scale=0.5, seed=0, keys=("state", "action"))
    rb.load_offline(td, lengths)
    batch = rb.sample(64)
    assert batch.batch_size == (64, 5)
    assert batch["return_to_go"].shape == (64, 5, 1) and batch["timestep"].dtype == torch.int64
    rtg_of = {0: -3.0, 1: -2.5, 2: -1.5}
    starts = set()
    for b in range(64):
        m = batch["mask"][b]
        n = int(m.sum())
        assert 1 <= n <= 3 and not m[: 5 - n].any() and m[5 - n :].all()
        start = 3 - n
        starts.add(start)
        ts = batch["timestep"][b]
        assert ts[5 - n :].tolist() == list(range(start, 3)) and (ts[: 5 - n] == 0).all()
        assert batch["state"][b, 5 - n :, 1].tolist() == list(range(start, 3))
        assert (batch["state"][b, : 5 - n] == 0).all() and (batch["action"][b, : 5 - n] == 0).all()
        assert (batch["return_to_go"][b, : 5 - n] == 0).all()
        assert batch["return_to_go"][b, 5 - n :, 0].tolist() == [rtg_of[t] for t in range(start, 3)]
    assert starts == {0, 1, 2}


def test_full_windows_and_length_proportional_sampling():
    td, lengths = _trajs([-1.0, -1.0], T=20, lengths=[2, 18])
    rb = TrajectoryReplayBuffer(capacity=2, context_len=4, max_len=20, seed=1)
    rb.load_offline(td, lengths)
    batch = rb.sample(4000)
    traj_id = batch["state"][..., -1, 0]  # the last position is always a real step
    frac_long = (traj_id == 1).float().mean().item()
    assert abs(frac_long - 0.9) < 0.03
    full = batch["mask"].all(-1)
    assert full.any()
    # a full window is K consecutive steps of one trajectory
    t = batch["state"][full][..., 1]
    assert (t[:, 1:] - t[:, :-1] == 1).all()


@pytest.mark.parametrize("early", [False, True])
def test_step_coverage_and_early_windows(early):
    # one trajectory of 12 steps, K = 4; count how often each step is a real (masked-in) window step
    K, T = 4, 12
    td, lengths = _trajs([-1.0], T=T, lengths=[T])
    rb = TrajectoryReplayBuffer(capacity=1, context_len=K, max_len=T, seed=0, early_windows=early)
    rb.load_offline(td, lengths)
    assert rb.total_steps == T
    batch = rb.sample(20000)
    steps = batch["state"][..., 1][batch["mask"]].long()
    share = torch.bincount(steps, minlength=T).float() / batch["mask"].shape[0]
    last = batch["timestep"][:, -1]
    # windows stay contiguous, end at their last real step and are left-padded
    n = batch["mask"].sum(-1)
    assert (batch["timestep"][:, -1] - batch["timestep"].gather(1, (K - n).unsqueeze(1)).squeeze(1) == n - 1).all()
    if early:
        # every step lies in K of the T + K - 1 possible windows; every step ends some window
        torch.testing.assert_close(share, torch.full((T,), K / (T + K - 1)), atol=0.01, rtol=0)
        assert set(last.tolist()) == set(range(T))
    else:
        # ODT reference: windows start inside the trajectory, step 0 is in 1 of T windows
        assert abs(share[0].item() - 1 / T) < 0.01 and abs(share[6].item() - K / T) < 0.02
        assert set(last.tolist()) == set(range(K - 1, T))
    # the sampler's state (and its mode) round-trips
    rb2 = TrajectoryReplayBuffer(capacity=1, context_len=K, max_len=T, seed=0, early_windows=not early)
    rb2.sampler.load_state_dict(rb.sampler.state_dict())
    assert rb2.sampler.early_windows == early and rb2.sampler.num_windows == rb.sampler.num_windows


def test_collector_layout_transform_and_errors():
    T = 5
    traj = TensorDict(
        {
            "state": torch.randn(T, 3),
            "pixels": torch.randint(0, 255, (T, 8, 8, 3), dtype=torch.uint8),
            "action": torch.randn(T, 2),
            "next": {"reward": -torch.ones(T, 1), "state": torch.randn(T, 3)},
        },
        [T],
    )
    encoder = _FlatEncoder()
    rb = TrajectoryReplayBuffer(
        capacity=3, context_len=3, max_len=10, keys=("state", "pixels", "action"),
        transform=EncoderTransform(encoder, out_dim=3, dtype=torch.float32),
    )
    rb.add_trajectory(traj)
    assert rb.online_fraction == 1.0 and rb.total_steps == T
    batch = rb.sample(8)
    assert batch["pixels"].shape == (8, 3, 8, 8, 3) and batch["state_estimate"].shape == (8, 3, 3)
    last = batch["timestep"][:, -1]
    torch.testing.assert_close(batch["return_to_go"][:, -1, 0], -(T - last).float())
    with pytest.raises(KeyError, match="pixels"):
        TrajectoryReplayBuffer(capacity=2, context_len=2, max_len=10, keys=("pixels",)).add_trajectory(traj.exclude("pixels"))
    with pytest.raises(ValueError, match="max_len"):
        TrajectoryReplayBuffer(capacity=2, context_len=2, max_len=4).add_trajectory(traj)
    with pytest.raises(RuntimeError, match="not empty"):
        rb.load_offline(traj.unsqueeze(0))
    with pytest.raises(RuntimeError, match="no steps"):
        TrajectoryReplayBuffer(capacity=2, context_len=2, max_len=4).sample(2)


def test_state_dict_round_trip(tmp_path):
    td, lengths = _trajs([-1.0, -2.0, -3.0], T=8, lengths=[8, 5, 3])
    rb = TrajectoryReplayBuffer(capacity=3, context_len=4, max_len=8, seed=3)
    rb.load_offline(td, lengths)
    rb.add_trajectory(td[0])
    torch.save(rb.state_dict(), tmp_path / "rb.pt")
    rb2 = TrajectoryReplayBuffer(capacity=3, context_len=4, max_len=8, seed=99)
    rb2.load_state_dict(torch.load(tmp_path / "rb.pt", weights_only=False))
    assert len(rb2) == 3 and rb2.online_fraction == rb.online_fraction and rb2.total_steps == rb.total_steps
    a, b = rb.sample(16), rb2.sample(16)
    assert (a == b).all()
    # the ring cursor is restored: the next online trajectory replaces the same slot in both
    assert rb.add_trajectory(td[1]) == rb2.add_trajectory(td[1])
    with pytest.raises(ValueError, match="capacity"):
        TrajectoryReplayBuffer(capacity=4, context_len=4, max_len=8).load_state_dict(rb.state_dict())


def test_lowest_return_replacement_keeps_the_best(tmp_path):
    rb = TrajectoryReplayBuffer(capacity=3, context_len=2, max_len=4, replacement="lowest_return", seed=0)
    offline, _ = _trajs([-3.0, -1.0, -5.0, -2.0])  # ids 0..3; id 2 (-5) is dropped
    rb.load_offline(offline)
    assert set(_stored_ids(rb)) == {0, 1, 3}
    online, _ = _trajs([-10.0, -1.5, -0.5, -2.5])
    online["state"][..., 0] += 100
    # -10 is worse than every stored one: dropped; -1.5 replaces id 0 (-3); -0.5 replaces id 3 (-2)
    assert rb.add_trajectory(online[0]) == -1
    assert set(_stored_ids(rb)) == {0, 1, 3} and rb.num_online_added == 1
    assert rb.add_trajectory(online[1]) >= 0 and rb.add_trajectory(online[2]) >= 0
    assert _stored_ids(rb) == {1: False, 101: True, 102: True}
    assert sorted(rb.returns.tolist()) == pytest.approx([-1.5, -1.0, -0.5])
    # every sampled window comes from a kept trajectory
    assert set(rb.sample(256)["state"][..., 0].unique().long().tolist()) <= {0, 1, 101, 102}
    # the ranking survives a checkpoint: -2.5 is dropped in both, -0.7 and -0.6 replace -1.5 and -1.0
    rb2 = TrajectoryReplayBuffer(capacity=3, context_len=2, max_len=4, replacement="lowest_return", seed=0)
    torch.save(rb.state_dict(), tmp_path / "rb.pt")
    rb2.load_state_dict(torch.load(tmp_path / "rb.pt", weights_only=False))
    assert rb.add_trajectory(online[3]) == rb2.add_trajectory(online[3]) == -1
    better, _ = _trajs([-0.7, -0.6])
    assert (rb.extend(better) == rb2.extend(better)).all()
    assert sorted(rb2.returns.tolist()) == pytest.approx([-0.7, -0.6, -0.5]) == sorted(rb.returns.tolist())
    # within one batch, an item evicted by a later one of the same batch is reported as not kept
    rb3 = TrajectoryReplayBuffer(capacity=1, context_len=2, max_len=4, replacement="lowest_return")
    rb3.load_offline(_trajs([-5.0])[0])
    assert rb3.extend(_trajs([-2.0, -1.0])[0]).tolist() == [-1, 0]
    with pytest.raises(ValueError, match="replacement"):
        TrajectoryReplayBuffer(capacity=3, context_len=2, max_len=4, replacement="fifo")
    with pytest.raises(ValueError, match="replacement"):
        TrajectoryReplayBuffer(capacity=3, context_len=2, max_len=4).load_state_dict(rb.state_dict())


def test_stored_return_to_go_is_returned_unchanged():
    """relabel_return_to_go=False: windows carry the return-to-go stored with each step (the acting
    countdown), not the hindsight return from the rewards."""
    data, lengths = _trajs([-3.0, -1.0], T=4, lengths=[4, 3])
    acting = torch.tensor([[9.0, 8.0, 7.0, 6.0], [5.0, 4.0, 3.0, 0.0]]).unsqueeze(-1)
    data.set("return_to_go", acting)
    rb = TrajectoryReplayBuffer(capacity=2, context_len=2, max_len=4, rtg_scale=0.5, seed=0, relabel_return_to_go=False)
    assert "return_to_go" in rb.keys
    rb.load_offline(data, lengths)
    batch = rb.sample(64)
    m = batch["mask"]
    ids, t = batch["state"][..., 0].long(), batch["state"][..., 1].long()
    torch.testing.assert_close(batch["return_to_go"][m].squeeze(-1), acting[ids, t].squeeze(-1)[m])
    assert (batch["return_to_go"][~m] == 0).all()
    hindsight = TrajectoryReplayBuffer(capacity=2, context_len=2, max_len=4, rtg_scale=0.5, seed=0)
    hindsight.load_offline(data.exclude("return_to_go"), lengths)
    assert not torch.equal(hindsight.sample(64)["return_to_go"], batch["return_to_go"])


def test_add_episodes_adds_rollout_episodes_and_counts_the_kept():
    rb = TrajectoryReplayBuffer(capacity=2, context_len=2, max_len=3, replacement="lowest_return")
    rb.load_offline(*_trajs([-2.0, -1.0], T=3))

    def episode(ret):  # a rollout episode [T] as run_episodes keeps it (reward under "next")
        state = torch.full((3, 2), ret)
        return TensorDict({"state": state, "action": state[:, :1], "pixels": torch.zeros(3, 1),
                           "next": {"reward": torch.full((3, 1), ret / 3)}}, [3])

    assert rb.add_episodes([episode(-3.0), episode(-0.5)], keys=("state", "action")) == 1  # -3 is below both
    assert rb.num_online == 1 and sorted(rb.returns.tolist()) == pytest.approx([-1.0, -0.5])
    assert "pixels" not in rb.storage._storage.keys()  # only the given keys
    assert rb.add_episodes([], keys=("state", "action")) == 0
