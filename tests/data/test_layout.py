"""The episode layout: rollout episodes in the dataset layout, the valid-step mask, real steps."""
import pytest
import torch
from tensordict import TensorDict

from trakdis.data import (STEP_KEYS, encode_trajectories, episode_to_trajectory, real_steps, split_episodes_train_val,
                          valid_mask)


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


def test_real_steps_drops_padding_and_keeps_episode_order():
    steps = TensorDict({"x": torch.arange(12.0).reshape(3, 4)}, batch_size=[3, 4])
    lengths = torch.tensor([4, 2, 3])
    assert real_steps(steps, lengths)["x"].tolist() == [0, 1, 2, 3, 4, 5, 8, 9, 10]
    assert real_steps(steps, lengths, torch.tensor([2, 1]))["x"].tolist() == [4, 5, 8, 9, 10]


def test_valid_mask_and_the_step_keys_of_a_dataset():
    assert valid_mask(torch.tensor([2, 0, 3]), 3).tolist() == [[True, True, False], [False, False, False],
                                                              [True, True, True]]
    names = [name for name, _ in STEP_KEYS]
    assert len(set(names)) == len(names) and {"state", "action", "reward", "done"} <= set(names)


def test_split_episodes_train_val_is_a_seeded_partition():
    train, val = split_episodes_train_val(10, 0.2, seed=3)
    assert len(val) == 2 and sorted(train.tolist() + val.tolist()) == list(range(10))
    again = split_episodes_train_val(10, 0.2, seed=3)
    assert torch.equal(train, again[0]) and torch.equal(val, again[1])
    assert not torch.equal(torch.cat(split_episodes_train_val(10, 0.2, seed=4)), torch.cat((train, val)))
    assert len(split_episodes_train_val(4, 0.1, seed=0)[1]) == 1  # at least one validation episode
    for n, fraction in ((1, 0.5), (5, 0.0)):  # a single episode, or no validation asked for
        train, val = split_episodes_train_val(n, fraction, seed=0)
        assert len(val) == 0 and sorted(train.tolist()) == list(range(n))
    with pytest.raises(ValueError, match="val_fraction"):
        split_episodes_train_val(4, 1.0, seed=0)


def test_encode_trajectories_replaces_images_by_the_encoders_output():
    data = TensorDict({"pixels": torch.randint(0, 255, (5, 3, 3, 2, 2), dtype=torch.uint8),
                       "action": torch.randn(5, 3, 2), "state": torch.randn(5, 3, 4)}, batch_size=[5, 3])
    calls = []

    def encoder(images):
        calls.append(images.shape[0])
        assert not torch.is_grad_enabled()
        return images.float().flatten(-3)[..., :4]

    out = encode_trajectories(data, encoder, keys=("action",), batch_size=2)
    assert calls == [2, 2, 1] and set(out.keys()) == {"action", "state_estimate"} and out.batch_size == (5, 3)
    assert torch.equal(out["state_estimate"], data["pixels"].float().flatten(-3)[..., :4])
    assert torch.equal(out["action"], data["action"])
    assert set(encode_trajectories(data, encoder, keys=("state",), out_key="z").keys()) == {"state", "z"}
