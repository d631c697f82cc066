"""Train the CNN state encoder F_c: 32x32 RGB image -> reduced state, on the expert dataset.

    python recipes/train_encoder.py --task ClothFold
    python recipes/train_encoder.py --task ClothFold --no-aug          # the paper's No-Aug ablation

Data, augmentation, student rounds, outputs (``runs/train_encoder/<name>/``): docs/recipes/train_encoder.md.
"""
from __future__ import annotations

import copy
import sys
from dataclasses import dataclass, field
from typing import Literal

import torch
from tensordict import TensorDict

from trakdis.data import DataConfig, load_train_val_steps
from trakdis.envs import task_defaults, task_spec
from trakdis.envs.specs import TaskName
from trakdis.modules import EncoderEnsemble, NormalizedEncoder, StateEncoder
from trakdis.objectives import EncoderLoss
from trakdis.optim import make_optimizer
from trakdis.policies import load_teacher, save_encoder
from trakdis.student import check_unseen_picker_mask, student_rollout_steps, weight_copy_race
from trakdis.transforms import OutOfViewFill
from trakdis.training import eval_batches, train_epoch
from trakdis.utils.limits import MAX_MEMBERS, MAX_PARAMS, check_option, check_options
from trakdis.utils.run import Run, RunConfig, RunState


@dataclass
class TrainEncoderConfig(RunConfig):
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
    select_episodes: int = 0
    """with --members K > 1 and --teacher: keep the one member whose weight copy (the teacher's weights on its
    estimates) scores best on this many train-split episodes, instead of the members' mean (0: the mean)"""
    select_chunk: int = 10
    """--select-episodes in chunks of this many: after each, a member whose weight copy is below the leading one's
    by more than 2 standard errors of their paired difference plays no more (racing; 0: all play every episode)"""
    test_time_flip: Literal["auto", "on", "off"] = "auto"
    """the saved encoder also reads the mirrored image, its estimate mirrored back and averaged in (auto: on for
    ClothFold, off for the diagonal folds, as measured in docs/recipes/train_encoder.md; never with --no-aug)"""
    extra_noise: tuple[float, ...] = ()
    """also train on datasets of the same size collected with these expert movement noises"""
    extra_aim_error: tuple[float, ...] = ()
    """also train on datasets of the same size whose expert aims at source corners misplaced by these stds (m):
    images of missed grasps, labelled with the true state (the main dataset's movement noise)"""
    extra_seeds: tuple[int, ...] = ()
    """also train on datasets like the main one (its size and movement noise) collected with these seeds (default
    paths ..._seed<k>...; collected if missing): more episodes of the same expert"""
    extra_data: tuple[str, ...] = ()
    """also train on these existing datasets of the task (directories with images), e.g. more expert episodes"""
    val_fraction: float = 0.1  # fraction of the episodes held out for validation
    teacher: str = ""
    """teacher policy file or online_dt run directory: also train on the weight-copied student's images"""
    student_rounds: int = 2  # rounds of (student rollouts, training) with --teacher
    student_episodes: int = 20  # student rollouts per round
    student_epochs: int = 5  # passes over all training images after each round's rollouts
    mask_unseen_pickers: bool = False
    """label each picker out of the camera view with a fixed sentinel xyz (for a teacher trained so)"""
    parallel: bool = False
    """play the student rounds' and --select-episodes' episodes on 2 worker processes (ParallelEnv; the same episodes)"""
    max_params: int = MAX_PARAMS
    """refuse a --teacher file whose model has more parameters than this (trakdis.utils.limits)"""

    def __post_init__(self):  # checked while parsing, before the run directory exists
        if self.members < 1:
            raise ValueError(f"--members {self.members}: need at least 1 encoder")
        check_options(self, sizes=("batch_size", "hidden_dim", "max_params"), positive=("lr",),
                      nonnegative=("weight_decay",), counts=("epochs", "student_rounds", "student_episodes",
                                                             "student_epochs", "pad"))
        check_option("members", self.members, le=MAX_MEMBERS, integer=True)
        super().__post_init__()
        if self.select_chunk < 0:
            raise ValueError(f"--select-chunk {self.select_chunk}: must be >= 0 (0: no racing)")
        if self.select_episodes < 0 or self.select_episodes and (self.members < 2 or not self.teacher):
            raise ValueError(f"--select-episodes {self.select_episodes}: needs --members >= 2 (got {self.members}) "
                             f"and --teacher (the weight copy plays the episodes)")

    @property
    def flips(self) -> bool:
        """Whether the encoder averages in the mirrored view: a test-time augmentation, so never with --no-aug;
        ``--test-time-flip auto``: where it was measured to help (the task's ``TaskDefaults.test_time_flip``)."""
        return self.aug and (self.test_time_flip == "on"
                             or self.test_time_flip == "auto" and task_defaults(self.task).test_time_flip)


def main(argv=None) -> dict:
    run = Run.start("train_encoder", TrainEncoderConfig, argv, description=__doc__)
    cfg = run.cfg
    spec = task_spec(cfg.task, horizon=cfg.horizon)
    if cfg.teacher and min(cfg.student_rounds, cfg.student_episodes, cfg.student_epochs) < 0 or \
            cfg.teacher and cfg.student_rounds > 0 and min(cfg.student_episodes, cfg.student_epochs) < 1:
        raise ValueError(f"--student-rounds {cfg.student_rounds} >= 0 needs --student-episodes "
                         f"({cfg.student_episodes}) and --student-epochs ({cfg.student_epochs}) >= 1")
    # the expert images and states, split by episode; --extra-* datasets join the training steps
    path, train, val, train_episodes, val_episodes = load_train_val_steps(
        cfg.data, task=cfg.task, horizon=cfg.horizon, seed=cfg.seed, keys=("pixels", "state"),
        val_fraction=cfg.val_fraction, image_size=cfg.image_size, extra_noise=cfg.extra_noise,
        extra_aim_error=cfg.extra_aim_error, extra_seeds=cfg.extra_seeds,
        extra_data=cfg.extra_data, log=run.print,
        progress=cfg.progress)
    # --mask-unseen-pickers: the labels (training and validation) are what the teacher reads, a picker
    # out of the image replaced by the sentinel the encoder then learns to output for it
    fill = OutOfViewFill.for_task(cfg.task, image_size=cfg.image_size) if cfg.mask_unseen_pickers else None
    if fill is not None:
        run.print(f"--mask-unseen-pickers: {1 - float(fill.visible(train['state']).float().mean()):.1%} of the training "
                  f"images' picker positions are out of view (label {[round(v, 3) for v in fill.fill.tolist()]})")
        train.set("state", fill.mask(train["state"]))
        if val is not None:
            val.set("state", fill.mask(val["state"]))
    mean, std = train["state"].mean(0), train["state"].std(0).clamp_min(1e-3)
    run.print(f"{path}: {train.shape[0]} training / {0 if val is None else val.shape[0]} validation images "
              f"({len(train_episodes)} / {len(val_episodes)} episodes)")

    members = [NormalizedEncoder(StateEncoder(spec.state_dim, image_size=cfg.image_size, channels=cfg.channels,
                                              hidden_dim=cfg.hidden_dim, head=cfg.head, stem_stride=cfg.stem_stride,
                                              coord_channels=cfg.coord_channels), mean, std) for _ in range(cfg.members)]
    encoder = (members[0] if cfg.members == 1 else EncoderEnsemble(members)).to(cfg.device)  # --members: their mean
    flip = cfg.flips
    loss = EncoderLoss(encoder, state_mirror=spec.state_mirror, augment=cfg.aug, flip_prob=cfg.flip_prob, pad=cfg.pad)
    optim = make_optimizer("adamw", encoder.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    with_rounds = bool(cfg.teacher) and cfg.student_rounds > 0
    total_epochs = cfg.epochs + (cfg.student_rounds * cfg.student_epochs if with_rounds else 0)
    schedule = {} if cfg.lr_schedule == "constant" else {
        "schedule": torch.optim.lr_scheduler.CosineAnnealingLR(optim, T_max=total_epochs)}
    n_params = sum(p.numel() for p in encoder.parameters())
    run.print(f"encoder: {cfg.members} x {n_params / cfg.members / 1e6:.2f}M parameters, augmentation "
              f"{'on' if cfg.aug else 'off'}, test-time flip {'on' if flip else 'off'}")

    state = RunState(run, {"epoch": 0, "best": {"val_mae": float("inf"), "state_dict": None, "epoch": -1},
                           "rounds_done": 0, "student_steps": None, "member_scores": {}},
                     step_key="epoch", counters_key=None, encoder=encoder, optim=optim, **schedule)
    state.load()
    teacher = load_teacher(cfg.teacher, task=cfg.task, horizon=cfg.horizon, max_params=cfg.max_params) if with_rounds or cfg.select_episodes else None
    state.restore_rng()  # after the teacher's modules are built (their init draws), so the RNG streams continue exactly
    mask_meta = {"mask_unseen_pickers": fill is not None, "out_of_view_fill": None if fill is None else fill.to_dict()}
    if teacher is not None:  # the student rounds' student acts with the teacher's (masked or not) states
        check_unseen_picker_mask(teacher, mask_meta, encoder_source=f"{run.dir} (this train_encoder.py run)")

    def validate() -> dict:
        if val is None:
            return {"mae": float("nan")}
        errs = eval_batches(loss, val, 1024, lambda b: (encoder(b["pixels"]) - b["state"]).abs(), device=cfg.device)
        return spec.state_error_cm(torch.cat(errs))

    while state["epoch"] < total_epochs:
        if with_rounds and state["epoch"] == cfg.epochs + state["rounds_done"] * cfg.student_epochs:
            # The images the weight-copied student sees: its error there is what the teacher's
            # weights must act on (docs/recipes/distill.md), and expert images never show them.
            new, metrics = student_rollout_steps(teacher, encoder, episodes=cfg.student_episodes, image_size=cfg.image_size,
                                                 seed=cfg.seed + 5000 + state["rounds_done"], label_fill=fill,
                                                 parallel=cfg.parallel)
            new = new.to_dict()  # plain tensors: the checkpoint loader refuses TensorDicts
            old = state["student_steps"]
            state["student_steps"] = new if old is None else {k: torch.cat([old[k], v]) for k, v in new.items()}
            state["rounds_done"] += 1
            run.log(state["epoch"], {f"student/{k}": v for k, v in metrics.items()})
            run.print(f"student round {state['rounds_done']}/{cfg.student_rounds}: normalized performance "
                      f"{metrics['normalized_performance']:.3f}, encoder error on its states: corners "
                      f"{metrics['corners_cm']:.2f} cm, pickers {metrics['pickers_cm']:.2f} cm; +{len(new['state'])} images")
        student = state["student_steps"]
        epoch_train = train if student is None else torch.cat(
            [train, TensorDict(student, batch_size=[len(student["state"])])])
        totals = train_epoch(loss, optim, epoch_train, cfg.batch_size, loss_key="loss_encoder",
                             metrics=("loss_encoder", "mae"), device=cfg.device, desc=f"epoch {state['epoch'] + 1}")
        state["epoch"] += 1
        if schedule:
            schedule["schedule"].step()
        val_err = validate()
        val_mae = val_err["mae"]
        # Model selection on the expert validation episodes during the first epochs; after student
        # rounds the newest encoder is kept (those rounds aim at other states than the validation's).
        if val is None or val_mae < state["best"]["val_mae"] or state["epoch"] > cfg.epochs:
            state["best"] = {"val_mae": val_mae, "state_dict": copy.deepcopy(encoder.state_dict()),
                             "epoch": state["epoch"], "val_error_cm": {k: v for k, v in val_err.items() if k != "mae"}}
        run.log(state["epoch"], {"train/loss_encoder": totals["loss_encoder"], "train/mae": totals["mae"],
                                 **{f"val/{k}": v for k, v in val_err.items()}})
        groups = ", ".join(f"{k.removesuffix('_cm')} {v:.2f} cm" for k, v in val_err.items() if k != "mae")
        run.print(f"epoch {state['epoch']}/{total_epochs}: train MSE {totals['loss_encoder']:.5f}, "
                  f"train MAE {totals['mae']:.4f} (augmented: {cfg.aug}), validation MAE {val_mae:.4f} ({groups})")
        if state.save_and_should_stop(total_epochs, unit="epoch"):
            return state["best"]
    best = state["best"]
    encoder.load_state_dict(best["state_dict"])
    mirror = spec.state_mirror if flip else None  # the saved encoder also reads the mirrored image, if flip
    selected = None
    if cfg.select_episodes:
        # Which of several encoders trained alike the teacher's weights fold well with is not told by
        # their errors on held-out images (docs/recipes/train_encoder.md): the copy's own episodes tell.
        # Raced (the members that fall clearly behind stop early); a run killed during the race plays it again.
        if len(state["member_scores"]) < cfg.members:
            def report(scores, survivors):
                run.print(f"weight copies after {max(map(len, scores.values()))} episodes: " + ", ".join(
                    f"member {k} {sum(v) / len(v):.3f}" + ("" if k in survivors else f" (stops at {len(v)})")
                    for k, v in scores.items() if v))

            members = [EncoderEnsemble([member], state_mirror=mirror) for member in encoder.members]
            state["member_scores"] = {k: v.tolist() for k, v in weight_copy_race(
                teacher, members, episodes=cfg.select_episodes, seed=cfg.seed + 9000, chunk=cfg.select_chunk,
                parallel=cfg.parallel, on_chunk=report).items()}
            state.save()
        scores = state["member_scores"]
        for k, v in scores.items():
            run.print(f"member {k}: weight copy {sum(v) / len(v):.3f} on {len(v)} train-split episodes")
        means = {k: sum(v) / len(v) for k, v in scores.items()}
        played = max(map(len, scores.values()))
        selected = max((k for k, v in scores.items() if len(v) == played), key=means.get)  # of those that played all
        run.log(state["epoch"], {f"select/member{k}_normalized_performance": m for k, m in means.items()})
        run.print(f"--select-episodes: member {selected} kept")
        encoder = encoder.members[selected]
    if flip:  # training, validation and rounds read each image once
        encoder = EncoderEnsemble(list(getattr(encoder, "members", [encoder])), state_mirror=mirror)
        groups = ", ".join(f"{k.removesuffix('_cm')} {v:.2f} cm" for k, v in validate().items() if k != "mae")
        run.print(f"--test-time-flip: validation error with the mirrored view averaged in: {groups}")
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
