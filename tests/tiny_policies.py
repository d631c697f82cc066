"""Tiny Decision Transformer policies for the tests of policy files and of the student: test modules
import this as ``from tiny_policies import tiny_actor`` (pytest puts ``tests/`` on ``sys.path``)."""
import torch

from trakdis.envs import task_spec
from trakdis.modules import DTModelConfig, NormalizedEncoder, StateEncoder, make_dt_actor
from trakdis.policies import load_teacher, save_policy


def tiny_actor(key="state"):
    cfg = DTModelConfig(embed_dim=16, n_layer=1, n_head=1, context_len=4, dropout=0.0).for_task(5, 2, horizon=10)
    return cfg, make_dt_actor(cfg, observation_key=key)


def tiny_teacher_and_encoder(tmp_path, *, horizon: int, encoder_scale: float = 1.0):
    """A tiny untrained ClothFold teacher saved under ``tmp_path`` (loaded) and a tiny encoder."""
    spec = task_spec("ClothFold")
    cfg = DTModelConfig(embed_dim=16, n_layer=1, n_head=1, context_len=4, dropout=0.0)
    cfg = cfg.for_task(spec.state_dim, spec.action_dim, horizon=horizon)
    save_policy(tmp_path / "policy.pt", kind="teacher", task="ClothFold", horizon=horizon, dt_config=cfg,
                actor=make_dt_actor(cfg, observation_key="state"), observation_key="state", target_return=-1.0,
                rtg_scale=1.0)
    encoder = NormalizedEncoder(StateEncoder(spec.state_dim, channels=(4, 4, 4, 4), hidden_dim=8),
                                torch.zeros(spec.state_dim), torch.full((spec.state_dim,), encoder_scale))
    return load_teacher(tmp_path), encoder
