import functools

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.envs import SerialEnv, TransformedEnv, check_env_specs
from torchrl.envs.utils import RandomPolicy
from torchrl.objectives.value.functional import reward2go

from toy_pixel_env import make_toy_env
from trakdis.transforms import ReturnToGo, hindsight_return_to_go


def test_hindsight_hand_computed():
    reward = torch.tensor([[-1.0, -2.0, -3.0, -4.0], [-0.5, -0.25, 0.0, 0.0]]).unsqueeze(-1)
    mask = torch.tensor([[True, True, True, False], [True, True, False, False]])
    rtg = hindsight_return_to_go(reward, mask, rtg_scale=0.5)
    expected = torch.tensor([[-3.0, -2.5, -1.5, 0.0], [-0.375, -0.125, 0.0, 0.0]]).unsqueeze(-1)
    torch.testing.assert_close(rtg, expected)
    # unmasked, time on the last dim
    torch.testing.assert_close(
        hindsight_return_to_go(torch.tensor([1.0, 2.0, 3.0]), time_dim=-1), torch.tensor([6.0, 5.0, 3.0])
    )


def test_hindsight_agrees_with_torchrl_reward2go_on_full_episodes():
    torch.manual_seed(0)
    reward = -torch.rand(3, 100, 1)
    done = torch.zeros(3, 100, 1, dtype=torch.bool)
    done[:, -1] = True
    torch.testing.assert_close(hindsight_return_to_go(reward, rtg_scale=2.0), 2.0 * reward2go(reward, done, 1.0), rtol=1e-5, atol=1e-5)


def test_hindsight_errors():
    with pytest.raises(ValueError, match="mask shape"):
        hindsight_return_to_go(torch.zeros(2, 5, 1), torch.ones(2, 4, dtype=torch.bool))
    with pytest.raises(TypeError, match="floating"):
        hindsight_return_to_go(torch.zeros(2, 5, 1, dtype=torch.long))


def check_countdown(batch, target, scale):
    """rtg restarts at scale*target at each episode start and drops by scale*reward per step."""
    rtg, nrtg = batch["return_to_go"], batch["next", "return_to_go"]
    reward, done = batch["next", "reward"], batch["next", "done"]
    n_env, T = rtg.shape[:2]
    starts = 0
    for i in range(n_env):
        for t in range(T):
            if t == 0 or done[i, t - 1]:
                if t > 0:
                    starts += 1
                assert rtg[i, t].item() == pytest.approx(scale * target, abs=1e-5), (i, t)
            else:
                assert rtg[i, t].item() == pytest.approx(nrtg[i, t - 1].item(), abs=1e-5)
            assert nrtg[i, t].item() == pytest.approx(rtg[i, t].item() - scale * reward[i, t].item(), abs=1e-5)
    return starts


def test_countdown_single_env():
    env = TransformedEnv(make_toy_env(size=8), ReturnToGo(target_return=-1.0, rtg_scale=0.1))
    check_env_specs(env, seed=0)
    assert env.observation_spec["return_to_go"].shape == (1,)
    td = env.rollout(10, break_when_any_done=False)
    assert td["return_to_go"][0].item() == pytest.approx(-0.1)
    assert check_countdown(td.unsqueeze(0), -1.0, 0.1) >= 1  # the toy episodes last <= 8 steps


def test_countdown_partial_resets_in_batched_envs():
    env = TransformedEnv(SerialEnv(3, functools.partial(make_toy_env, size=8)), ReturnToGo(-2.0, rtg_scale=0.5))
    env.set_seed(1)
    check_env_specs(env, seed=1)
    col = Collector(env, RandomPolicy(env.action_spec), frames_per_batch=60, total_frames=60)
    batch = next(iter(col))
    col.shutdown()
    assert batch["next", "done"].any(1).all()
    # episode lengths differ across envs, so resets are partial
    assert not (batch["next", "done"][0] == batch["next", "done"][1]).all() or not (
        batch["next", "done"][1] == batch["next", "done"][2]
    ).all()
    assert check_countdown(batch, -2.0, 0.5) >= 3
