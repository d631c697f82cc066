"""The TraKDis student: a Decision Transformer on encoder(image), distilled from the teacher.

    python recipes/distill.py                                  # latest teacher + latest encoder
    python recipes/distill.py --teacher runs/online_dt/A --encoder runs/train_encoder/B
    python recipes/distill.py --no-weight-copy                 # ablation No-Pretrain
    python recipes/distill.py --no-weight-copy --no-distill    # the paper's No-Distill (its budget: trakdis.method)
    python recipes/distill.py --select-episodes 0              # the last round's weights (no selection)

Steps, ablations, outputs (``runs/distill/<name>/``), options and measurements: docs/recipes/distill.md.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Optional

from trakdis.data import student_buffer
from trakdis.evaluation import EvalConfig, RunEnvs
from trakdis.optim import OptimConfig
from trakdis.student import DAggerRollouts, StudentConfig, StudentEvaluations, distill_state, load_teacher_and_encoder
from trakdis.training import SelectionConfig, SnapshotSelection, buffer_batches, train_rounds
from trakdis.utils.limits import MAX_PARAMS, check_options
from trakdis.utils.run import Run, RunConfig


@dataclass
class DistillConfig(StudentConfig, SelectionConfig, EvalConfig, OptimConfig, RunConfig):
    """Distil the privileged teacher into an image-based student."""

    teacher: str = "latest"  # teacher policy file or online_dt run directory ('latest': the newest under <root>)
    encoder: str = "latest"  # encoder.pt or train_encoder run directory ('latest': the newest under <root>)
    rounds: int = 10  # rounds of (roll out, update); --no-distill: rounds of updates only
    updates_per_round: int = 50  # updates per round
    batch_size: int = 64  # windows per update
    lr: float = 1e-4  # learning rate
    warmup_steps: int = 20  # linear learning-rate warm-up (updates)
    min_lr_fraction: float = 1.0  # cosine decay of --lr to this fraction by the last round's last update (1: constant)
    buffer_capacity: int = 200  # trajectories kept for distillation
    early_windows: bool = True  # also sample windows that begin before an episode's first step (see online_dt.py)
    eval_episodes: int = 10  # evaluation episodes (eval split, the same configurations every time; 0: none)
    eval_every: int = 5  # also evaluate every N rounds (0: only before the rounds and at the end)
    select_episodes: Optional[int] = None
    """train-split episodes scoring the copy and every --select-every rounds' student (0: keep the last; default: per
    task, none on ClothFold and 30 on the diagonal folds, as measured in docs/recipes/distill.md)"""
    select_every: int = 5  # rounds between the scored snapshots (and the last); a later one is kept only if measurably better
    eval_teacher: bool = True  # also evaluate the teacher on the evaluation episodes
    parallel: bool = False  # step the envs in worker processes (ParallelEnv; --no-parallel: in turn, the same numbers)
    max_params: int = MAX_PARAMS  # refuse a teacher or encoder file with a larger model (trakdis.utils.limits)

    def __post_init__(self):  # checked while parsing, before the run directory exists
        if not 0.0 < self.min_lr_fraction <= 1.0:  # also NaN
            raise ValueError(f"--min-lr-fraction {self.min_lr_fraction}: must be in (0, 1]")
        check_options(self, sizes=("batch_size", "buffer_capacity", "max_params"), counts=("rounds", "updates_per_round"))
        super().__post_init__()


PRESETS = {"paper": {"optimizer": "lamb", "lr": 1e-4, "rounds": 60, "episodes_per_round": 1, "eval_episodes": 100,
                     "expert_data": False, "loss_function": "nll",
                     "eval_every": 10, "updates_per_round": 100, "batch_size": 256}}


def main(argv=None) -> dict:
    run = Run.start("distill", DistillConfig, argv, presets=PRESETS, description=__doc__)
    cfg = run.cfg
    # the parts: the teacher and the encoder, and the student they make. Teacher and student read states
    # standardised with the teacher's statistics (the student's weights start as the teacher's, and the encoder's
    # estimates live in state units).
    teacher, encoder, enc_file, enc_path = load_teacher_and_encoder(cfg.teacher, cfg.encoder, root=cfg.root,
                                                                    device=cfg.device, max_params=cfg.max_params)
    task, horizon = teacher.task, teacher.horizon
    student_handle, dt_cfg = cfg.make_student(teacher, encoder, device=cfg.device)
    student = student_handle.actor
    teacher.actor.eval().requires_grad_(False)
    expert_coef = cfg.resolved_expert_coef(task)
    run.print(f"{task}: teacher {teacher.source}, encoder {enc_path} (val MAE {enc_file.get('val_mae', float('nan')):.4f}), "
              f"weight copy {cfg.weight_copy}, {'distillation' if cfg.distill else 'expert imitation (--no-distill)'}"
              + (f", the expert's actions beside the teacher's (--expert-coef {expert_coef:g})" if expert_coef else "")
              + (", picker odometry" if cfg.odometry else "")
              + (f" holding the corner closed on within {100 * student_handle.hold_radius:g} cm"
                 if student_handle.hold_radius else ""))
    loss = cfg.make_loss(student, teacher.actor, action_eps=dt_cfg.action_eps, expert_coef=expert_coef)
    updater = cfg.make_updater(loss, decay_steps=cfg.rounds * cfg.updates_per_round,
                               min_lr_fraction=cfg.min_lr_fraction)
    buffer = student_buffer(cfg.buffer_capacity, dt_cfg.context_len, horizon, teacher.rtg_scale,
                            normalizer=student_handle.normalizer, distill=cfg.distill,
                            proprio_dims=student_handle.proprio_dims, state_noise=cfg.estimate_noise, seed=cfg.seed,
                            early_windows=cfg.early_windows, relabel_return_to_go=cfg.relabel_return_to_go)
    state = distill_state(run, updater, buffer)  # its counters, the evaluations' means, the updater and the buffer
    if state.resuming:
        state.load()
    else:  # --no-distill (the expert's actions as targets), --expert-data (the teacher's labels): the expert data
        cfg.load_expert_data(buffer, encoder, teacher, seed=cfg.seed, log=run.print, progress=cfg.progress)
    evals = cfg.eval_protocol(task, horizon, seed=cfg.seed, log_returns=False)
    eval_env = cfg.make_env(student_handle)
    evaluations = StudentEvaluations(run, evals, student_handle, eval_env, state)  # the same configurations every time
    # Early stopping: the snapshots play the same train-split episodes (configurations no evaluation
    # plays); the weight copy is kept unless a later snapshot beats it measurably (docs: the cause). Fresh weights
    # (--no-weight-copy) are no candidate: there is no copy to guard, and an untrained DT kept because no round beat
    # it measurably would be the final policy; the first round scored is then the one the later ones must beat.
    select_episodes = cfg.resolved_select_episodes(task)
    select_env = cfg.make_env(student_handle, "train") if select_episodes and cfg.rounds else None
    selection = SnapshotSelection.on_episodes(run, student_handle, evals, select_env, state, episodes=select_episodes,
                                              module=student, every=cfg.select_every, margin=cfg.select_margin,
                                              name="student")
    # Rollouts carry both the true state and the encoder's estimate (--estimate-noise: the buffer adds it).
    actors = cfg.acting_policies(teacher, student_handle, encoder)
    roll_out = DAggerRollouts(actors, [cfg.make_env(h, "train") for h in actors], buffer, cfg.episodes_per_round,
                              cfg.rounds, horizon, cfg.seed, collector=cfg.collector, mixed=cfg.act == "mixed")
    state.restore_rng()  # after building the envs, so the RNG streams continue exactly
    with RunEnvs(None, eval_env, select_env, *roll_out.envs):  # closed on exit
        if cfg.eval_teacher:  # on its own env, closed afterwards
            evaluations.teacher(teacher, parallel=cfg.parallel)
        evaluations.initial()
        if cfg.weight_copy:
            selection.consider(0)
        if not train_rounds(run, updater, buffer_batches(buffer, cfg.batch_size, cfg.device), state=state,
                            rounds=cfg.rounds, updates_per_round=cfg.updates_per_round, roll_out=roll_out, model=student,
                            loss_key="train/loss_distill" if cfg.distill else "train/loss_nll", selection=selection,
                            evaluate=evaluations.after_round, eval_every=cfg.eval_every):
            return dict(state)
        # the curve (eval/) ends with the last round's weights; a kept earlier snapshot is the final score
        evaluations.final(cfg.rounds, selection)
    student_handle.save(run.dir / "policy.pt", dt_cfg, encoder_file=enc_file,
                        extra={"teacher": teacher.source, "weight_copy": cfg.weight_copy, "distill": cfg.distill,
                               "estimate_noise": cfg.estimate_noise, "expert_coef": expert_coef,
                               "proprio_dims": list(student_handle.proprio_dims), "picker_odometry": cfg.odometry,
                               "hold_radius": student_handle.hold_radius,
                               "select_episodes": select_episodes, **selection.summary()})
    state.finish()
    run.print(evaluations.report())
    return dict(state)


if __name__ == "__main__":
    main(sys.argv[1:])
