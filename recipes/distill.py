"""The TraKDis student: a Decision Transformer on encoder(image), distilled from the teacher.

    python recipes/distill.py                                  # latest teacher + latest encoder
    python recipes/distill.py --teacher runs/online_dt/A --encoder runs/train_encoder/B
    python recipes/distill.py --no-weight-copy                 # ablation No-Pretrain
    python recipes/distill.py --no-weight-copy --no-distill    # the paper's No-Distill (its budget: trakdis.method)
    python recipes/distill.py --select-episodes 0              # the last round's weights (no selection)

Steps, ablations, outputs (``runs/distill/<name>/``), options and measurements: docs/recipes/distill.md.
"""
from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass, field
from typing import ClassVar, Literal, Optional

from trakdis.data import DataConfig, load_encoded_dataset, student_buffer
from trakdis.envs import task_defaults, task_spec
from trakdis.evaluation import EvalConfig, RunEnvs, run_episodes
from trakdis.objectives import DistillationLoss, MaskedOnlineDTLoss
from trakdis.optim import OptimConfig
from trakdis.student import load_teacher_and_encoder, weight_copied_student
from trakdis.training import SnapshotSelection, mixture_shares, train_rounds
from trakdis.transforms import PickerOdometry
from trakdis.utils.limits import MAX_PARAMS, check_options
from trakdis.utils.run import Run, RunConfig, RunState


@dataclass
class DistillConfig(EvalConfig, OptimConfig, RunConfig):
    """Distil the privileged teacher into an image-based student."""

    teacher: str = "latest"  # teacher policy file or online_dt run directory ('latest': the newest under <root>)
    encoder: str = "latest"  # encoder.pt or train_encoder run directory ('latest': the newest under <root>)
    weight_copy: bool = True
    """initialise the student with the teacher's weights (--no-weight-copy: fresh weights, never kept by the
    selection; No-Pretrain, with --no-distill the paper's No-Distill)"""
    distill: bool = True  # learn from the teacher's actions (--no-distill: imitate the expert dataset instead)
    estimate_noise: float = 0.0
    """std of Gaussian noise on the estimated state of every training window (robustness)"""
    SAVED_AS: ClassVar[dict] = {"state_noise": "estimate_noise"}  # the option's earlier name (--state-noise)
    proprio_pickers: bool = False  # the student's picker positions from proprioception (the true state), not the encoder
    picker_odometry: Literal["auto", "on", "off"] = "auto"
    """the encoder's picker estimates fused with the student's own commands (no proprioception); auto: on if the data's
    actions are the executed ones (measured on the three tasks over 3 seeds each: docs/recipes/distill.md)"""
    act: Literal["student", "teacher", "mixed"] = "teacher"  # who acts in the rollouts (student: DAgger; mixed: decaying)
    teacher_context: Literal["window", "step"] = "window"  # what the teacher reads to label a step: window or step alone
    expert_data: bool = True  # distil on the expert dataset's episodes (--data.*): images through the encoder
    rounds: int = 10  # rounds of (roll out, update); --no-distill: rounds of updates only
    episodes_per_round: int = 0  # episodes rolled out per round into the distillation data (0: the expert data only)
    updates_per_round: int = 50  # updates per round
    batch_size: int = 64  # windows per update
    lr: float = 1e-4  # learning rate
    warmup_steps: int = 20  # linear learning-rate warm-up (updates)
    min_lr_fraction: float = 1.0  # cosine decay of --lr to this fraction by the last round's last update (1: constant)
    loss_function: Literal["nll", "mse"] = "nll"  # the student's NLL of the teacher's action (paper), or squared error
    return_to_go: Literal["acting", "hindsight"] = "acting"  # rollouts' return-to-go: the acting countdown, or reached
    kl_coef: float = 0.0  # weight of an extra teacher-student KL term (0: the paper's NLL only)
    expert_coef: Optional[float] = None
    """weight of the student's NLL of the expert's own actions beside the teacher's, on the expert data (knowledge
    distillation's hard labels; 0: the paper's loss, the teacher's actions alone; default: per task, as measured in
    docs/recipes/distill.md; 0 wherever the data has rollouts)"""
    buffer_capacity: int = 200  # trajectories kept for distillation
    early_windows: bool = True  # also sample windows that begin before an episode's first step (see online_dt.py)
    data: DataConfig = field(default_factory=DataConfig)  # expert dataset for --no-distill and --expert-data
    eval_episodes: int = 10  # evaluation episodes (eval split, the same configurations every time; 0: none)
    eval_every: int = 5  # also evaluate every N rounds (0: only before the rounds and at the end)
    select_episodes: Optional[int] = None
    """train-split episodes scoring the copy and every --select-every rounds' student (0: keep the last; default: per
    task, none on ClothFold and 30 on the diagonal folds, as measured in docs/recipes/distill.md)"""
    select_every: int = 5  # rounds between the scored snapshots (and the last); a later one is kept only if measurably better
    select_margin: float = 1.0  # standard errors of the paired gain by which a snapshot must beat the one kept so far
    eval_teacher: bool = True  # also evaluate the teacher on the evaluation episodes
    parallel: bool = False  # step the envs in worker processes (ParallelEnv; --no-parallel: in turn, the same numbers)
    max_params: int = MAX_PARAMS  # refuse a teacher or encoder file with a larger model (trakdis.utils.limits)

    def __post_init__(self):  # checked while parsing, before the run directory exists
        if self.episodes_per_round < 0 or (self.distill and self.episodes_per_round == 0 and not self.expert_data):
            raise ValueError(f"--episodes-per-round {self.episodes_per_round}: distillation needs rollouts (>= 1) "
                             "or --expert-data")
        if self.expert_coef is not None and not self.expert_coef >= 0:  # also NaN
            raise ValueError(f"--expert-coef {self.expert_coef}: must be >= 0")
        if self.expert_coef and not self.expert_actions:
            raise ValueError(f"--expert-coef {self.expert_coef}: the expert's actions exist on the expert data alone "
                             "(--expert-data, --episodes-per-round 0, with distillation)")
        if not 0.0 < self.min_lr_fraction <= 1.0:  # also NaN
            raise ValueError(f"--min-lr-fraction {self.min_lr_fraction}: must be in (0, 1]")
        if (self.select_episodes or 0) < 0 or self.select_every < 1:
            raise ValueError(f"--select-episodes {self.select_episodes} / --select-every {self.select_every}: "
                             "need >= 0 episodes and >= 1 round")
        if self.picker_odometry == "on" and not self.proprio_pickers and self.data.action_labels != "executed":
            raise ValueError(f"--picker-odometry integrates the executed actions: --data.action-labels "
                             f"{self.data.action_labels!r} needs 'executed'")
        check_options(self, sizes=("batch_size", "buffer_capacity", "select_every", "max_params"),
                      counts=("rounds", "updates_per_round"), nonnegative=("estimate_noise", "kl_coef"))
        super().__post_init__()

    @property
    def odometry(self) -> bool:
        """Whether the student's pickers are fused with its commands: --picker-odometry, auto resolved to on where the
        data's actions are the executed ones; never with --proprio-pickers (they give the pickers outright)."""
        auto = self.picker_odometry == "auto" and self.data.action_labels == "executed"
        return (self.picker_odometry == "on" or auto) and not self.proprio_pickers

    @property
    def expert_actions(self) -> bool:
        """Whether every distillation window holds the expert's own actions (the expert data, no rollouts)."""
        return self.distill and self.expert_data and self.episodes_per_round == 0

    def resolved_expert_coef(self, task: str) -> float:
        """``--expert-coef``, or unset the task's ``TaskDefaults.expert_coef`` where the windows hold the expert's
        own actions (else 0)."""
        if self.expert_coef is not None:
            return self.expert_coef
        return task_defaults(task).expert_coef if self.expert_actions else 0.0

    def resolved_select_episodes(self, task: str) -> int:
        """``--select-episodes``, or unset the task's ``TaskDefaults.select_episodes``."""
        return task_defaults(task).select_episodes if self.select_episodes is None else self.select_episodes


PRESETS = {"paper": {"optimizer": "lamb", "lr": 1e-4, "rounds": 60, "episodes_per_round": 1, "eval_episodes": 100,
                     "expert_data": False, "loss_function": "nll",
                     "eval_every": 10, "updates_per_round": 100, "batch_size": 256}}


def main(argv=None) -> dict:
    run = Run.start("distill", DistillConfig, argv, presets=PRESETS, description=__doc__)
    cfg = run.cfg
    teacher, encoder, enc_file, enc_path = load_teacher_and_encoder(cfg.teacher, cfg.encoder, root=cfg.root,
                                                                    device=cfg.device, max_params=cfg.max_params)
    task, horizon = teacher.task, teacher.horizon
    # Teacher and student read states standardised with the teacher's statistics (the student's
    # weights start as the teacher's, and the encoder's estimates live in state units).
    pickers = task_spec(task).state_groups["pickers"]
    proprio_dims = tuple(range(pickers.start, pickers.stop)) if cfg.proprio_pickers else ()
    odometry = cfg.odometry
    student_handle, dt_cfg = weight_copied_student(teacher, encoder, weight_copy=cfg.weight_copy, device=cfg.device,
                                                   normalizer_keys=("state", "state_estimate"), proprio_dims=proprio_dims,
                                                   picker_odometry=odometry)
    student, normalizer = student_handle.actor, student_handle.normalizer
    teacher.actor.eval().requires_grad_(False)
    expert_coef = cfg.resolved_expert_coef(task)
    run.print(f"{task}: teacher {teacher.source}, encoder {enc_path} (val MAE {enc_file.get('val_mae', float('nan')):.4f}), "
              f"weight copy {cfg.weight_copy}, {'distillation' if cfg.distill else 'expert imitation (--no-distill)'}"
              + (f", the expert's actions beside the teacher's (--expert-coef {expert_coef:g})" if expert_coef else "")
              + (", picker odometry" if odometry else ""))

    if cfg.distill:
        loss = DistillationLoss(student, teacher.actor, kl_coef=cfg.kl_coef, loss_function=cfg.loss_function,
                                action_eps=dt_cfg.action_eps, teacher_context=cfg.teacher_context,
                                expert_coef=expert_coef)
    else:
        loss = MaskedOnlineDTLoss(student, lambda_entropy=0.0, action_eps=dt_cfg.action_eps)
    updater = cfg.make_updater(loss, decay_steps=cfg.rounds * cfg.updates_per_round,
                               min_lr_fraction=cfg.min_lr_fraction)
    buffer = student_buffer(cfg.buffer_capacity, dt_cfg.context_len, horizon, teacher.rtg_scale, normalizer=normalizer,
                            distill=cfg.distill, proprio_dims=proprio_dims, state_noise=cfg.estimate_noise, seed=cfg.seed,
                            early_windows=cfg.early_windows, relabel_return_to_go=not cfg.distill or cfg.expert_data
                            or cfg.return_to_go == "hindsight")
    state = RunState(run, {"rounds": 0, "updates": 0, "initial_eval": None, "teacher_eval": None, "round_evals": {}},
                     step_key="updates", updater=updater, buffer=buffer)
    if state.resuming:
        state.load()
    elif not cfg.distill or cfg.expert_data:
        # The expert dataset's images through the frozen encoder (No-Distill: with the expert's
        # actions as targets; --expert-data: with the teacher's labels on the true states).
        keys = ("action", "reward", *(("state",) if cfg.proprio_pickers or cfg.distill else ()))
        data, lengths, path = load_encoded_dataset(cfg.data, encoder, task=task, horizon=horizon, seed=cfg.seed,
                                                   keys=keys, log=run.print, progress=cfg.progress)
        if odometry:  # what the student reads when acting: the fused pickers
            fuse = PickerOdometry.for_task(task, teacher.env_kwargs)
            data.set("state_estimate", fuse.filter(data["state_estimate"], data["action"]))
        buffer.load_offline(data, lengths)
        run.print(f"{'--expert-data' if cfg.distill else '--no-distill'}: {data.shape[0]} expert episodes from {path}")

    evals = cfg.eval_protocol(task, horizon, seed=cfg.seed, log_returns=False)

    def evaluate(tag, prefix="eval") -> float | None:  # the student, on the same eval configurations every time
        return evals.run(run, student_handle, eval_env, step=state["updates"], tag=tag, prefix=prefix, keep_mode=student,
                         state_error_cm=task_spec(task).state_error_cm).summary()["mean"] if cfg.eval_episodes else None

    eval_env = cfg.make_env(student_handle)
    # Early stopping: the snapshots play the same train-split episodes (configurations no evaluation
    # plays); the weight copy is kept unless a later snapshot beats it measurably (docs: the cause). Fresh weights
    # (--no-weight-copy) are no candidate: there is no copy to guard, and an untrained DT kept because no round beat
    # it measurably would be the final policy; the first round scored is then the one the later ones must beat.
    select_episodes = cfg.resolved_select_episodes(task)
    select_env = cfg.make_env(student_handle, "train") if select_episodes and cfg.rounds else None
    selection = SnapshotSelection.on_episodes(run, student_handle, evals, select_env, state, episodes=select_episodes,
                                              module=student, every=cfg.select_every, margin=cfg.select_margin,
                                              name="student")
    # its rollouts carry the estimate too (fused the student's way)
    teacher_actor_handle = dataclasses.replace(teacher, encoder=encoder, picker_odometry=odometry)
    actors = {"teacher": [teacher_actor_handle], "student": [student_handle],
              "mixed": [teacher_actor_handle, student_handle]}[cfg.act] if cfg.distill and cfg.episodes_per_round else []
    # Rollouts carry both the true state and the encoder's estimate (--estimate-noise: the buffer adds it).
    roll_envs = [cfg.make_env(h, "train") for h in actors]
    state.restore_rng()  # after building the envs, so the RNG streams continue exactly
    with RunEnvs(None, eval_env, select_env, *roll_envs):  # closed on exit
        if cfg.eval_teacher and cfg.eval_episodes and state["teacher_eval"] is None:  # on its own env, closed afterwards
            state["teacher_eval"] = evals.run_snapshot(run, teacher, step=state["updates"], tag="teacher",
                                                       prefix="eval_teacher", parallel=cfg.parallel,
                                                       keep_mode=student, desc="eval (teacher)").summary()["mean"]
        if state["initial_eval"] is None:
            state["initial_eval"] = evaluate("student before training")
        if select_env is not None and cfg.weight_copy:
            selection.consider(0)

        def roll_out(r: int):  # round r's rollouts into the buffer (--act mixed: DAgger's decaying mixture)
            metrics, parts = {}, []
            shares = [cfg.episodes_per_round] if cfg.act != "mixed" else mixture_shares(cfg.episodes_per_round, r, cfg.rounds)
            for i, (handle, n) in enumerate(zip(actors, shares)):
                if n > 0:
                    res = run_episodes(roll_envs[i], handle.make_policy(), n, max_steps=horizon, deterministic=True,
                                       keep_episodes=True, desc=f"rollout ({handle.kind})", collector=cfg.collector,
                                       seed=cfg.seed + 1000 * (r + 1) + 100 * i)
                    buffer.add_episodes(res.episodes, keys=("state", "state_estimate", "action", "return_to_go"))
                    metrics[f"rollout/{handle.kind}_normalized_performance"] = float(res.final_performance.mean())
                    parts.append(f"rollout ({handle.kind}) {res.final_performance.mean():.3f}")
            return {**metrics, "round": r + 1}, ", ".join(parts)

        def after_round(r: int):  # every round but the last
            if select_env is not None:
                selection.after_round(r)
            if cfg.eval_every and r % cfg.eval_every == 0:
                state["round_evals"][r] = evaluate(f"student after round {r}")

        if not train_rounds(run, updater, lambda: buffer.sample(cfg.batch_size).to(cfg.device), state=state,
                            rounds=cfg.rounds, updates_per_round=cfg.updates_per_round, roll_out=roll_out, model=student,
                            loss_key="train/loss_distill" if cfg.distill else "train/loss_nll", eval_every=1,
                            evaluate=after_round):
            return dict(state)
        # The curve (eval/) ends with the last round's weights; a kept earlier snapshot is the final score
        # (eval_kept/ at the same step), its evaluation reused when the curve already has it.
        # --rounds 0 (the weight copy alone): the policy did not change, its evaluation stands.
        final = evaluate("student after distillation") if cfg.rounds > 0 else state["initial_eval"]
        if select_env is not None:
            best = selection.finish(cfg.rounds, run.print)
            if best != cfg.rounds and cfg.eval_episodes:
                final = state["initial_eval"] if best == 0 else state["round_evals"].get(best)
                if final is None:
                    final = evaluate(f"the kept student (round {best})", prefix="eval_kept")
                else:
                    run.log(state["updates"], {"eval_kept/normalized_performance": final})
                    run.print(f"the kept student (round {best}): its evaluation on the curve, {final:.3f}")
    state["final_eval"] = final
    student_handle.save(run.dir / "policy.pt", dt_cfg, encoder_file=enc_file,
                        extra={"teacher": teacher.source, "weight_copy": cfg.weight_copy, "distill": cfg.distill,
                               "estimate_noise": cfg.estimate_noise, "expert_coef": expert_coef,
                               "proprio_dims": list(proprio_dims), "picker_odometry": odometry,
                               "select_episodes": select_episodes, **selection.summary()})
    state.finish()
    scores = [f"{k} {'not evaluated' if state[v] is None else format(state[v], '.3f')}"
              for k, v in (("teacher", "teacher_eval"), ("student before", "initial_eval"), ("after", "final_eval"))]
    run.print(f"eval normalized performance: {', '.join(scores)} ({cfg.eval_episodes} episodes)")
    return dict(state)


if __name__ == "__main__":
    main(sys.argv[1:])
