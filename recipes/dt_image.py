"""Baseline DT-image: a Decision Transformer fed by a CNN on the raw 32x32 image, trained end to end
on the expert dataset with the DT loss, without a pretrained state encoder (the paper's "DT-image").

    python recipes/dt_image.py --task ClothFold
    python recipes/evaluate.py --policy runs/dt_image/<name>          # 100 eval-split trials

1. Expert data: the dataset of ``train_encoder.py`` and the method's teacher stage (``--data.*``), its images,
   actions and rewards in the trajectory replay buffer (left-padded windows of ``K`` images,
   hindsight return-to-go), as the teacher's buffer holds states.
2. Model: ``trakdis.modules.ImageTrunk`` (``--trunk.*``: the encoder's CNN, random shift of up to
   ``--trunk.pad`` pixels per image while training) writes ``"image_features"`` for every image of
   a window; the DT (``--model.*``, the teacher's sizes) reads them as its observation. Loss:
   ``MaskedOnlineDTLoss`` (NLL - ``--lambda-entropy`` x entropy), through the DT into the CNN.
3. ``--updates`` updates (cosine decay to ``--min-lr-fraction``); evaluation on the eval split (mean
   action, initial return-to-go ``--eval-rtg``, default the dataset's best return) every
   ``--eval-every`` updates and at the end. Acting: the CNN runs in the env (``EncoderTransform``)
   and ``DTActingPolicy`` keeps the context of features.

Writes ``runs/dt_image/<name>/``: ``config.json``, ``log.csv``, ``curves.png``, ``checkpoint.pt``
(``--resume``) and ``policy.pt`` (for evaluate.py).
"""
from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Optional


from trakdis.data import DataConfig, ensure_dataset, load_trajectories, make_buffer
from trakdis.envs.specs import TaskName
from trakdis.evaluation import EvalConfig
from trakdis.modules import DTModelConfig
from trakdis.modules.baselines import ImageTrunkConfig
from trakdis.optim import OptimConfig
from trakdis.policies import PolicyHandle, save_image_policy
from trakdis.training import train_updates
from trakdis.utils.run import Run, RunConfig, RunState


@dataclass
class DTImageConfig(EvalConfig, OptimConfig, RunConfig):
    """Decision Transformer on CNN image features, trained end to end on expert data (baseline DT-image)."""

    task: TaskName = "ClothFold"
    """cloth task"""
    horizon: int = 100
    """episode length"""
    data: DataConfig = field(default_factory=DataConfig)
    """expert dataset (with pixels)"""
    image_size: int = 32
    """image side"""
    trunk: ImageTrunkConfig = field(default_factory=ImageTrunkConfig)
    """CNN trunk"""
    model: DTModelConfig = field(default_factory=DTModelConfig)
    """Decision Transformer (the teacher's defaults)"""
    updates: int = 1500
    """updates (the teacher's offline pretraining length)"""
    batch_size: int = 32
    """windows per update (each window holds context-len images)"""
    min_lr_fraction: float = 0.1
    """cosine decay of the learning rate to this fraction of --lr"""
    lambda_entropy: float = 0.1
    """entropy bonus weight (the paper's 0.1)"""
    early_windows: bool = True
    """also sample windows that begin before an episode's first step (as online_dt.py)"""
    eval_rtg: Optional[float] = None
    """initial return-to-go at evaluation (default: the best return of the dataset)"""
    eval_episodes: int = 20
    """evaluation episodes (eval split, the same configurations every time; 0: none)"""
    eval_every: int = 500
    """evaluate every N updates (and at the end; 0: only then)"""
    log_every: int = 50
    """log training metrics every N updates"""
    checkpoint_every: int = 250
    """checkpoint every N updates"""
    parallel: bool = False
    """step the envs in worker processes (ParallelEnv; --no-parallel: in turn, the same numbers)"""


def main(argv=None) -> dict:
    run = Run.start("dt_image", DTImageConfig, argv, description=__doc__)
    cfg = run.cfg
    from trakdis.envs import task_spec
    from trakdis.modules import make_dt_actor, recipe_hidden_action_dims, with_image_trunk
    from trakdis.objectives import MaskedOnlineDTLoss

    spec = task_spec(cfg.task, horizon=cfg.horizon)
    path = ensure_dataset(cfg.data, task=cfg.task, horizon=cfg.horizon, seed=cfg.seed, pixels=True,
                          image_size=cfg.image_size, log=run.print, progress=cfg.progress)
    data, lengths = load_trajectories(path, keys=("pixels", "action", "reward"), action_labels=cfg.data.action_labels)
    trunk = cfg.trunk.make(cfg.image_size).to(cfg.device)
    dt_cfg = cfg.model.for_task(cfg.trunk.feature_dim, spec.action_dim, cfg.horizon, hidden_action_dims=recipe_hidden_action_dims(cfg.task),
                                grasp_dims=spec.grasp_dims)
    head = make_dt_actor(dt_cfg, observation_key="image_features", device=cfg.device)
    actor = with_image_trunk(head, trunk)
    loss = MaskedOnlineDTLoss(actor, lambda_entropy=cfg.lambda_entropy, action_eps=dt_cfg.action_eps)
    updater = cfg.make_updater(loss, decay_steps=cfg.updates, min_lr_fraction=cfg.min_lr_fraction)
    run.print(f"DT-image: {sum(p.numel() for p in actor.parameters()) / 1e6:.2f}M parameters (CNN "
              f"{sum(p.numel() for p in trunk.parameters()) / 1e6:.2f}M), K={dt_cfg.context_len}, "
              f"random shift {cfg.trunk.pad} px")
    # uint8 images in the buffer: 40 episodes x 100 steps x 3x32x32 is 12 MB
    buffer = make_buffer(data.shape[0], dt_cfg.context_len, cfg.horizon, 1.0,
                         keys=("pixels",), seed=cfg.seed, early_windows=cfg.early_windows)
    returns = data.get("reward").sum(dim=(-2, -1))
    state = RunState(run, {"updates": 0, "best_return": float(returns.max()), "final_eval": None}, step_key="updates",
                     updater=updater, sampler=buffer.sampler)
    buffer.load_offline(data.to_tensordict(), lengths)  # the same data on resume; the sampler state follows
    state.load()
    state.restore_rng()
    run.print(f"{path}: {data.shape[0]} expert episodes, return {returns.mean():.3f} (best {returns.max():.3f})")
    eval_rtg = cfg.eval_rtg if cfg.eval_rtg is not None else state["best_return"]
    handle = PolicyHandle("dt_image", cfg.task, cfg.horizon, actor=head, encoder=trunk, observation_key="image_features",
                          target_return=eval_rtg)
    evals = cfg.eval_protocol(cfg.task, cfg.horizon, seed=cfg.seed, log_returns=False)

    def evaluate(u: int) -> float | None:  # the current weights, on the same configurations every time (0: none)
        if not cfg.eval_episodes:
            return None
        res = evals.run_snapshot(run, handle, step=u, tag=f"update {u}", parallel=cfg.parallel, keep_mode=actor)
        return res.summary()["mean"]

    if not train_updates(run, updater, lambda: buffer.sample(cfg.batch_size).to(cfg.device), state=state,
                         total=cfg.updates, log_every=cfg.log_every, checkpoint_every=cfg.checkpoint_every,
                         on_log=lambda u: run.print(f"update {u}/{cfg.updates}: loss_nll "
                                                    f"{run.logger.last('train/loss_nll'):.3f}"),
                         on_update=lambda u: evaluate(u) if cfg.eval_every and u % cfg.eval_every == 0 and u < cfg.updates else None):
        return dict(state)
    if state["final_eval"] is None:  # stays None without evaluation episodes
        state["final_eval"] = evaluate(state["updates"])
    save_image_policy(run.dir / "policy.pt", kind="dt_image", task=cfg.task, horizon=cfg.horizon, trunk=trunk,
                      actor=head, head_config=dt_cfg, target_return=eval_rtg,
                      extra={"dataset": str(path), "updates": state["updates"]})
    state.save()
    run.finish()
    if state["final_eval"] is not None:
        run.print(f"DT-image: eval normalized performance {state['final_eval']:.3f} ({cfg.eval_episodes} episodes)")
    return dict(state)


if __name__ == "__main__":
    main(sys.argv[1:])
