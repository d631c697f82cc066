"""A loaded policy's acting env (trakdis.policies.acting)."""
import pytest
from tiny_policies import tiny_actor

from trakdis.policies import load_policy, make_acting_env, save_policy


def test_bad_state_noise_and_horizon_are_refused(tmp_path):
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
