"""``GymEnv("trakdis/<Task>-v0")`` and ``make_env(...)``: the same keys, specs and values.

TorchRL's own ``GymEnv`` renames the Dict observation's ``"state"`` to ``"observation"``, reads no
info entries and counts no steps; ``with_contract_keys`` adds exactly what ``make_env`` adds.
"""

import pytest
import torch
from torchrl.envs import GymEnv, check_env_specs

from trakdis.envs import make_env, with_contract_keys

SPECS = ("full_observation_spec", "full_action_spec", "full_reward_spec", "full_done_spec", "full_state_spec")


def _assert_same_specs(a, b):
    for name in SPECS:
        sa, sb = getattr(a, name), getattr(b, name)
        assert set(sa.keys(True, True)) == set(sb.keys(True, True)), name
        for key in sa.keys(True, True):
            assert sa[key] == sb[key], (name, key, sa[key], sb[key])


@pytest.mark.parametrize("task,from_pixels", [("ClothFold", True), ("ClothFoldDiagonalPinned", False)])
def test_gym_id_env_with_contract_keys_equals_make_env(task, from_pixels):
    kwargs = dict(from_pixels=True, pixels_only=False) if from_pixels else {}
    plain = GymEnv(f"trakdis/{task}-v0", **kwargs)
    assert "observation" in plain.observation_spec.keys() and "state" not in plain.observation_spec.keys()
    ours = make_env(task, from_pixels=from_pixels)
    env = with_contract_keys(plain)
    _assert_same_specs(env, ours)
    check_env_specs(env, seed=0)
    # same seed -> same episode: states, pixels (rendered by TorchRL's pixel wrapper), rewards, infos
    env.set_seed(1)
    ours.set_seed(1)
    actions = torch.rand(4, *ours.action_spec.shape, generator=torch.Generator().manual_seed(0)) * 2 - 1
    tds = []
    for e in (env, ours):
        td = e.reset()
        steps = []
        for a in actions:
            td["action"] = a
            td = e.step(td)
            steps.append(td["next"].clone())
            td = td["next"]
        tds.append(torch.stack(steps))
    for key in tds[1].keys(True, True):
        torch.testing.assert_close(tds[0][key], tds[1][key], msg=lambda m, k=key: f"{k}: {m}")
    env.close()
    ours.close()


def test_with_contract_keys_takes_the_gym_env_itself():
    with pytest.raises(TypeError, match="GymEnv/GymWrapper itself"):
        with_contract_keys(make_env("ClothFold"))
