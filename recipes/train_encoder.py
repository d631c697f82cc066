"""Train the CNN state encoder F_c: 32x32 RGB image -> reduced state, on the expert dataset.

    python recipes/train_encoder.py --task ClothFold
    python recipes/train_encoder.py --task ClothFold --no-aug          # the paper's No-Aug ablation

Data, augmentation, student rounds, outputs (``runs/train_encoder/<name>/``): docs/recipes/train_encoder.md.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Literal

import torch

from trakdis.data import DataConfig, EncoderDataConfig
from trakdis.encoder_training import (WeightCopyConfig, encoder_state, error_groups, keep_best_epoch,
                                      mask_unseen_labels, select_member, validation_errors)
from trakdis.envs import TaskName, task_defaults, task_spec
from trakdis.modules import EncoderEnsemble, NormalizedEncoder, StateEncoder
from trakdis.objectives import EncoderLoss
from trakdis.optim import make_optimizer
from trakdis.policies import load_teacher, save_encoder
from trakdis.student import check_unseen_picker_mask
from trakdis.training import train_epoch
from trakdis.transforms import OutOfViewFill
from trakdis.utils.limits import MAX_MEMBERS, MAX_PARAMS, check_option, check_options
from trakdis.utils.run import Run, RunConfig


@dataclass
class TrainEncoderConfig(WeightCopyConfig, EncoderDataConfig, RunConfig):
    """Train the CNN state encoder on the expert dataset's images and states."""

    task: TaskName = "ClothFold"  # cloth task
    horizon: int = 100  # episode length of the dataset
    data: DataConfig = field(default_factory=DataConfig)  # expert dataset (with pixels)
    image_size: int = 32  # image side
    epochs: int = 20  # passes over the training images
    batch_size: int = 128  # images per update
    lr: float = 1e-3  # learning rate (AdamW)
    lr_schedule: Literal["constant", "cosine"] = "constant"
    """'cosine': the learning rate falls to 0 over all epochs (student rounds included), one step per epoch"""
    weight_decay: float = 1e-4  # weight decay
    aug: bool = True  # augment (label-consistent horizontal flip; random shift if --pad > 0) while training
    flip_prob: float = 0.5  # probability of the mirrored image
    pad: int = 0  # random-shift padding in pixels (0: none; a shift keeps the labels, so the encoder learns to ignore position)
    channels: tuple[int, ...] = (32, 32, 32, 32)  # channels of the 4 conv layers
    hidden_dim: int = 256  # width of the MLP head
    head: str = "flatten"  # encoder head: 'flatten' (conv features -> MLP) or 'keypoints' (spatial soft-argmax)
    stem_stride: int = 2  # stride of the first conv layer (1 keeps the full resolution)
    coord_channels: bool = False  # append pixel-coordinate channels to the image (CoordConv)
    members: int = 1  # encoders trained side by side on the same batches; the student reads their mean (a deep ensemble)
    test_time_flip: Literal["auto", "on", "off"] = "auto"
    """the saved encoder also reads the mirrored image, its estimate mirrored back and averaged in (auto: on for
    ClothFold, off for the diagonal folds, as measured in docs/recipes/train_encoder.md; never with --no-aug)"""
    mask_unseen_pickers: bool = False
    """label each picker out of the camera view with a fixed sentinel xyz (for a teacher trained so)"""
    parallel: bool = False
    """play the student rounds' and --select-episodes' episodes on 2 worker processes (ParallelEnv; the same episodes)"""
    max_params: int = MAX_PARAMS  # refuse a --teacher file whose model has more parameters than this (trakdis.utils.limits)

    def __post_init__(self):  # checked while parsing, before the run directory exists
        if self.members < 1:
            raise ValueError(f"--members {self.members}: need at least 1 encoder")
        check_options(self, sizes=("batch_size", "hidden_dim", "max_params"), positive=("lr",),
                      nonnegative=("weight_decay",), counts=("epochs", "pad"))
        check_option("members", self.members, le=MAX_MEMBERS, integer=True)
        super().__post_init__()
        if self.select_episodes < 0 or (self.select_episodes and (self.members < 2 or not self.teacher)):
            raise ValueError(f"--select-episodes {self.select_episodes}: needs --members >= 2 (got {self.members}) "
                             f"and --teacher (the weight copy plays the episodes)")

    @property
    def flips(self) -> bool:
        """Whether the encoder averages in the mirrored view: a test-time augmentation, so never with --no-aug;
        ``--test-time-flip auto``: where it was measured to help (the task's ``TaskDefaults.test_time_flip``)."""
        return self.aug and (self.test_time_flip == "on"
                             or (self.test_time_flip == "auto" and task_defaults(self.task).test_time_flip))


def main(argv=None) -> dict:
    run = Run.start("train_encoder", TrainEncoderConfig, argv, description=__doc__)
    cfg = run.cfg
    spec = task_spec(cfg.task, horizon=cfg.horizon)
    cfg.check_student_rounds()
    # the expert images and states, split by episode; --extra-* datasets join the training steps
    path, train, val, train_episodes, val_episodes = cfg.train_val_steps(
        cfg.data, task=cfg.task, horizon=cfg.horizon, seed=cfg.seed, keys=("pixels", "state"), image_size=cfg.image_size,
        log=run.print, progress=cfg.progress)
    fill = OutOfViewFill.for_task(cfg.task, image_size=cfg.image_size) if cfg.mask_unseen_pickers else None
    mask_unseen_labels(fill, train, val, log=run.print)  # the labels (training and validation): what the teacher reads
    mean, std = train["state"].mean(0), train["state"].std(0).clamp_min(1e-3)
    run.print(f"{path}: {train.shape[0]} training / {0 if val is None else val.shape[0]} validation images "
              f"({len(train_episodes)} / {len(val_episodes)} episodes)")
    # the encoder (--members: their mean), its loss (augmented), optimiser and learning-rate schedule
    members = [NormalizedEncoder(StateEncoder(spec.state_dim, image_size=cfg.image_size, channels=cfg.channels,
                                              hidden_dim=cfg.hidden_dim, head=cfg.head, stem_stride=cfg.stem_stride,
                                              coord_channels=cfg.coord_channels), mean, std) for _ in range(cfg.members)]
    encoder = (members[0] if cfg.members == 1 else EncoderEnsemble(members)).to(cfg.device)
    loss = EncoderLoss(encoder, state_mirror=spec.state_mirror, augment=cfg.aug, flip_prob=cfg.flip_prob, pad=cfg.pad)
    optim = make_optimizer("adamw", encoder.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    total_epochs = cfg.epochs + cfg.round_epochs
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optim, T_max=total_epochs) if cfg.lr_schedule == "cosine" else None
    run.print(f"encoder: {cfg.members} x {sum(p.numel() for p in encoder.parameters()) / cfg.members / 1e6:.2f}M "
              f"parameters, augmentation {'on' if cfg.aug else 'off'}, test-time flip {'on' if cfg.flips else 'off'}")
    state = encoder_state(run, encoder, optim, schedule=schedule)  # its counters, the encoder, the optimiser
    state.load()
    teacher = (load_teacher(cfg.teacher, task=cfg.task, horizon=cfg.horizon, max_params=cfg.max_params)
               if cfg.with_rounds or cfg.select_episodes else None)
    state.restore_rng()  # after the teacher's modules are built (their init draws), so the RNG streams continue exactly
    mask_meta = {"mask_unseen_pickers": fill is not None, "out_of_view_fill": None if fill is None else fill.to_dict()}
    if teacher is not None:  # the student rounds' student acts with the teacher's (masked or not) states
        check_unseen_picker_mask(teacher, mask_meta, encoder_source=f"{run.dir} (this train_encoder.py run)")
    # the expert's images, then each student round's: those the weight-copied student sees (docs/recipes/distill.md)
    rounds = cfg.student_rounds_of(state, teacher, first_epoch=cfg.epochs, seed=cfg.seed + 5000,
                                   image_size=cfg.image_size, label_fill=fill, parallel=cfg.parallel)
    while state["epoch"] < total_epochs:
        if rounds.due():
            rounds.play(encoder, run)
        totals = train_epoch(loss, optim, rounds.training_data(train), cfg.batch_size, loss_key="loss_encoder",
                             metrics=("loss_encoder", "mae"), device=cfg.device, desc=f"epoch {state['epoch'] + 1}")
        state["epoch"] += 1
        if schedule is not None:
            schedule.step()
        val_err = validation_errors(loss, encoder, val, spec.state_error_cm, device=cfg.device)
        # the epoch kept: the best on the expert validation episodes, the newest once the student rounds began
        keep_best_epoch(state, encoder, val_err, always=val is None or state["epoch"] > cfg.epochs)
        run.log(state["epoch"], {"train/loss_encoder": totals["loss_encoder"], "train/mae": totals["mae"],
                                 **{f"val/{k}": v for k, v in val_err.items()}})
        run.print(f"epoch {state['epoch']}/{total_epochs}: train MSE {totals['loss_encoder']:.5f}, train MAE "
                  f"{totals['mae']:.4f} (augmented: {cfg.aug}), validation MAE {val_err['mae']:.4f} ({error_groups(val_err)})")
        if state.save_and_should_stop(total_epochs, unit="epoch"):
            return state["best"]
    best = state["best"]
    encoder.load_state_dict(best["state_dict"])
    mirror = spec.state_mirror if cfg.flips else None  # the saved encoder also reads the mirrored image, if flip
    selected = None
    if cfg.select_episodes:  # the member whose weight copy folds best (docs/recipes/train_encoder.md)
        selected = select_member(run, state, teacher, encoder, episodes=cfg.select_episodes, seed=cfg.seed + 9000,
                                 chunk=cfg.select_chunk, parallel=cfg.parallel, state_mirror=mirror)
        encoder = encoder.members[selected]
    if cfg.flips:  # training, validation and rounds read each image once
        encoder = EncoderEnsemble(list(getattr(encoder, "members", [encoder])), state_mirror=mirror)
        run.print(f"--test-time-flip: validation error with the mirrored view averaged in: "
                  f"{error_groups(validation_errors(loss, encoder, val, spec.state_error_cm, device=cfg.device))}")
    save_encoder(run.dir / "encoder.pt", encoder.cpu(), task=cfg.task,
                 extra={"val_mae": best["val_mae"], "val_error_cm": best.get("val_error_cm"), "epoch": best["epoch"],
                        "aug": cfg.aug, "dataset": str(path), "student_rounds": state["rounds_done"],
                        "member_scores": dict(state["member_scores"]) or None, "selected_member": selected, **mask_meta})
    run.finish()
    run.print(f"encoder.pt: epoch {best['epoch']}, validation MAE {best['val_mae']:.4f} "
              f"(state units, mean over {spec.state_dim} dims)")
    return best


if __name__ == "__main__":
    main(sys.argv[1:])
