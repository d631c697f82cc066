"""End to end on the real pieces: expert dataset (real cloth env, tiny) -> replay buffer windows ->
EncoderTransform with the project's StateEncoder -> the DT loss (the contract of docs/design.md)."""

import torch

from trakdis.data import TrajectoryReplayBuffer, collect_expert_dataset, load_expert_dataset
from trakdis.envs import task_spec
from trakdis.modules import DTModelConfig, StateEncoder, make_dt_actor
from trakdis.objectives import MaskedOnlineDTLoss
from trakdis.transforms import EncoderTransform


def test_dataset_buffer_encoder_dt_loss(tmp_path):
    task = "ClothFoldDiagonalUnpinned"
    spec = task_spec(task)
    path = collect_expert_dataset(tmp_path / "ds", task, num_episodes=2, horizon=5, image_size=32, progress=False, noise=0.1)
    steps, meta = load_expert_dataset(path)
    torch.manual_seed(0)
    encoder = StateEncoder(spec.state_dim, image_size=32, channels=(8, 8, 8, 8), hidden_dim=16)
    rb = TrajectoryReplayBuffer(
        capacity=4, context_len=3, max_len=5, keys=("state", "pixels", "action"), seed=0,
        transform=EncoderTransform(encoder, in_keys=["pixels"], out_keys=["state_estimate"]),
    )
    rb.load_offline(steps, meta["lengths"])
    batch = rb.sample(6)
    assert batch["state_estimate"].shape == (6, 3, spec.state_dim)
    assert batch["timestep"].max() < 5 and batch["mask"][:, -1].all()
    cfg = DTModelConfig(state_dim=spec.state_dim, action_dim=spec.action_dim, embed_dim=16, n_layer=1, n_head=2, context_len=3)
    for key in ("state", "state_estimate"):  # teacher and student observation keys
        loss = MaskedOnlineDTLoss(make_dt_actor(cfg, observation_key=key), lambda_entropy=0.1)
        out = loss(batch.clone())
        total = out["loss_nll"] + out["loss_entropy"]
        assert torch.isfinite(total)
        total.backward()
