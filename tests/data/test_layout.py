"""The episode layout: rollout episodes in the dataset layout, the valid-step mask, real steps."""
import pytest
import torch
from tensordict import TensorDict

from trakdis.data import STEP_KEYS, episode_to_trajectory, real_steps, valid_mask


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
