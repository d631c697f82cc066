"""Baseline BC-image (the paper's "Behavior Cloning"): a CNN + MLP policy from the 32x32 image to
the expert's action, trained on the expert dataset that the encoder and the teacher use.

    python recipes/bc_image.py --task ClothFold
    python recipes/evaluate.py --policy runs/bc_image/<name>          # 100 eval-split trials

1. Expert data: the same dataset as ``train_encoder.py`` (``--data.*``, collected if missing);
   episodes are split into training and validation sets (``--val-fraction``).
2. Model: ``trakdis.modules.ImageTrunk`` (the encoder's CNN, ``--trunk.*``, random shift of up to
   ``--trunk.pad`` pixels while training, no flip: see its docstring) -> MLP head -> TanhNormal
   actor (``make_bc_actor``); loss: ``BehaviourCloningLoss`` (``--loss-function nll|mse``).
3. ``--epochs`` passes over the training steps; the validation loss every epoch, the policy's
   normalized performance on the eval split (mean action) every ``--eval-every`` epochs and at the end.

Writes ``runs/bc_image/<name>/``: ``config.json``, ``log.csv``, ``curves.png``, ``checkpoint.pt``
(after every epoch; ``--resume``) and ``policy.pt`` (for evaluate.py).
"""
from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Literal

import torch

from trakdis.data import DataConfig, load_train_val_steps
from trakdis.envs.specs import TaskName
from trakdis.evaluation import EvalConfig
from trakdis.modules.baselines import ImageTrunkConfig
from trakdis.optim import OptimConfig, mean_metrics
from trakdis.policies import PolicyHandle, save_image_policy
from trakdis.training import eval_batches, shuffled_batches
from trakdis.utils.run import Run, RunConfig, RunState


@dataclass
class BCImageConfig(EvalConfig, OptimConfig, RunConfig):
    """Behaviour cloning from images on the expert dataset (baseline BC-image)."""

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
    hidden_dims: tuple[int, ...] = (256, 256)
    """MLP head widths"""
    loss_function: Literal["nll", "mse"] = "nll"
    """NLL of the expert's action under the TanhNormal policy, or squared error of its mean action"""
    epochs: int = 30
    """passes over the training steps"""
    batch_size: int = 128
    """steps per update"""
    warmup_steps: int = 20
    """linear learning-rate warm-up (updates)"""
    val_fraction: float = 0.1
    """fraction of the episodes held out for validation"""
    eval_episodes: int = 20
    """evaluation episodes (eval split, the same configurations every time; 0: none)"""
    eval_every: int = 10
    """evaluate every N epochs (and at the end; 0: only then)"""
    parallel: bool = False
    """step the envs in worker processes (ParallelEnv; --no-parallel: in turn, the same numbers)"""


def main(argv=None) -> dict:
    run = Run.start("bc_image", BCImageConfig, argv, description=__doc__)
    cfg = run.cfg
    from trakdis.envs import task_spec
    from trakdis.modules import BCConfig, make_bc_actor, with_image_trunk
    from trakdis.objectives import BehaviourCloningLoss

    spec = task_spec(cfg.task, horizon=cfg.horizon)
    path, train, val, _, _ = load_train_val_steps(cfg.data, task=cfg.task, horizon=cfg.horizon, seed=cfg.seed,
                                                  keys=("pixels", "action"), val_fraction=cfg.val_fraction,
                                                  image_size=cfg.image_size, log=run.print, progress=cfg.progress)
    run.print(f"{path}: {train.shape[0]} training / {0 if val is None else val.shape[0]} validation steps")

    trunk = cfg.trunk.make(cfg.image_size).to(cfg.device)
    bc_cfg = BCConfig(cfg.trunk.feature_dim, spec.action_dim, hidden_dims=cfg.hidden_dims)
    head = make_bc_actor(bc_cfg, device=cfg.device)
    actor = with_image_trunk(head, trunk)
    loss = BehaviourCloningLoss(actor, loss_function=cfg.loss_function, action_eps=bc_cfg.action_eps)
    updater = cfg.make_updater(loss)
    run.print(f"BC-image: {sum(p.numel() for p in actor.parameters()) / 1e6:.2f}M parameters, "
              f"random shift {cfg.trunk.pad} px, loss {cfg.loss_function}")

    state = RunState(run, {"epoch": 0, "final_eval": None}, step_key="epoch", updater=updater)
    state.load()
    state.restore_rng()
    handle = PolicyHandle("bc_image", cfg.task, cfg.horizon, actor=head, encoder=trunk, observation_key="image_features")
    evals = cfg.eval_protocol(cfg.task, cfg.horizon, seed=cfg.seed, log_returns=False)

    def evaluate() -> float | None:  # the current weights, on the same configurations every time (0 episodes: none)
        if not cfg.eval_episodes:
            return None
        res = evals.run_snapshot(run, handle, step=state["epoch"], tag=f"epoch {state['epoch']}", parallel=cfg.parallel,
                                 keep_mode=actor)
        return res.summary()["mean"]

    def validate() -> dict:
        if val is None:
            return {}
        outs = eval_batches(loss, val, 512, device=cfg.device)
        return {f"val/{k}": float(torch.stack([o[k] for o in outs]).mean()) for k in ("loss_bc", "action_mse")}

    while state["epoch"] < cfg.epochs:
        history = [updater.step(batch) for batch in
                   shuffled_batches(train, cfg.batch_size, device=cfg.device, desc=f"epoch {state['epoch'] + 1}")]
        state["epoch"] += 1
        run.log(state["epoch"], {**mean_metrics(history), **validate()})
        run.print(f"epoch {state['epoch']}/{cfg.epochs}: loss_bc {run.logger.last('train/loss_bc'):.4f}, "
                  f"action MSE {run.logger.last('train/action_mse'):.4f}")
        if cfg.eval_every and state["epoch"] % cfg.eval_every == 0 and state["epoch"] < cfg.epochs:
            evaluate()
        if state.save_and_should_stop(cfg.epochs, unit="epoch"):
            return dict(state)
    if state["final_eval"] is None:  # stays None without evaluation episodes
        state["final_eval"] = evaluate()
    save_image_policy(run.dir / "policy.pt", kind="bc_image", task=cfg.task, horizon=cfg.horizon, trunk=trunk,
                      actor=head, head_config=bc_cfg, extra={"dataset": str(path), "epochs": state["epoch"]})
    state.save()
    run.finish()
    if state["final_eval"] is not None:
        run.print(f"BC-image: eval normalized performance {state['final_eval']:.3f} ({cfg.eval_episodes} episodes)")
    return dict(state)


if __name__ == "__main__":
    main(sys.argv[1:])
