"""The privileged teacher: a Decision Transformer on the true reduced state, trained offline on
expert data and then fine-tuned online on its own rollouts, as in TraKDis: labelled with the scripted
expert's actions (DAgger, the default) or with their own (``--online-labels executed``: Online DT,
Zheng et al. 2022).

    python recipes/online_dt.py                       # ClothFold: 20 demonstrations, DAgger (the main job)
    python recipes/online_dt.py --preset cpu          # the strongest teacher measured on a 2-core CPU (minutes)
    python recipes/online_dt.py --preset paper        # the paper's model and optimiser (slow on a CPU)
    python recipes/online_dt.py --resume              # continue the latest run after a kill

Steps, outputs (``runs/online_dt/<name>/``), options and measurements: docs/recipes/online_dt.md.
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field

from trakdis.data import DataConfig, StateBufferConfig
from trakdis.envs import TaskName, task_spec
from trakdis.evaluation import EvalConfig, RunEnvs
from trakdis.modules import DTModelConfig, make_dt_actor, recipe_hidden_action_dims
from trakdis.objectives import MaskedOnlineDTLoss
from trakdis.optim import OptimConfig
from trakdis.policies import PolicyHandle
from trakdis.teacher import OnlinePhaseConfig, TeacherEvalConfig, TeacherEvaluations, teacher_state
from trakdis.training import SelectionConfig, SnapshotSelection, buffer_batches, train_rounds, train_updates
from trakdis.utils.limits import MAX_HORIZON, check_option, check_options
from trakdis.utils.run import Run, RunConfig


@dataclass
class OnlineDTConfig(OnlinePhaseConfig, SelectionConfig, StateBufferConfig, TeacherEvalConfig, EvalConfig, OptimConfig,
                     RunConfig):
    """Teacher: offline Decision Transformer pretraining on expert data, then online fine-tuning."""

    task: TaskName = "ClothFold"  # cloth task
    horizon: int = 100  # episode length
    # the main job's data and head (docs/recipes/online_dt.md, "The main job's online phase against its control"):
    # 20 demonstrations, so that the online phase has something to add; a log-std floor of -1.5, so that DAgger's
    # grasp corrections do not swamp the clipped updates. The presets and the method's teacher keep 40 (200) and -2.5.
    data: DataConfig = field(default_factory=lambda: DataConfig(episodes=20))  # expert dataset
    model: DTModelConfig = field(default_factory=lambda: DTModelConfig(log_std_min=-1.5))
    """Decision Transformer"""
    min_lr_fraction: float = 0.1  # cosine decay of --lr to this fraction by the end of pretraining (1: constant)
    batch_size: int = 64  # windows per update
    lambda_entropy: float = 0.1  # entropy bonus weight (paper: 0.1); initial temperature with --learn-temperature
    learn_temperature: bool = False  # learn the entropy temperature toward a target entropy of -action_dim (Online DT)
    offline_updates: int = 1500  # offline pretraining updates
    collect_pixels: bool = False  # also store the 32x32 images in the dataset this run collects (for train_encoder.py)
    log_every: int = 50  # log training metrics every N updates
    checkpoint_every: int = 500  # checkpoint every N offline updates (online: after every round)

    def __post_init__(self):  # checked while parsing, before the run directory exists
        if self.horizon < 1:
            raise ValueError(f"--horizon {self.horizon}: must be >= 1")
        check_options(self, sizes=("horizon", "batch_size", "log_every", "checkpoint_every"),
                      counts=("offline_updates",), nonnegative=("lambda_entropy",))
        check_option("min_lr_fraction", self.min_lr_fraction, gt=0, le=1)
        check_option("horizon", self.horizon, le=MAX_HORIZON, integer=True)
        super().__post_init__()


PRESETS = {"paper": {  # the paper's sizes, optimiser, data and online schedule (Online DT's executed labels)
    "model": {**DTModelConfig.PAPER_SIZES, "log_std_min": DTModelConfig.log_std_min}, "online_labels": "executed",
    "optimizer": "lamb", "lr": 1e-4, "weight_decay": 1e-4, "warmup_steps": 10000,
    "batch_size": 256, "data": {"episodes": 8000}, "offline_updates": 5000, "online_rounds": 1500, "episodes_per_round": 1,
    "updates_per_round": 300, "buffer_capacity": 1000, "buffer_replacement": "oldest", "min_lr_fraction": 1.0,
    "eval_rtg": -1.0, "eval_episodes": 100, "expert_episodes": 100, "eval_every": 50},
    # the strongest teacher measured on a 2-core CPU (docs/recipes/online_dt.md): 5x the method teacher's 40
    # demonstrations, about as many passes over them (19 against 24), DAgger online, early stopping between the
    # offline and the final teacher
    "cpu": {"data": {"episodes": 200}, "model": {"log_std_min": DTModelConfig.log_std_min}, "offline_updates": 6000,
            "online_labels": "expert", "eval_episodes": 100, "select_episodes": 30, "select_every": 8}}


def main(argv=None) -> dict:
    run = Run.start("online_dt", OnlineDTConfig, argv, presets=PRESETS, description=__doc__)
    cfg = run.cfg
    # the parts: the DT, its loss (DAgger: the expert's actions as targets), the optimiser, the run's counters
    spec = task_spec(cfg.task, horizon=cfg.horizon)
    dt_cfg = cfg.model.for_task(spec.state_dim, spec.action_dim, cfg.horizon, hidden_action_dims=recipe_hidden_action_dims(cfg.task),
                                grasp_dims=spec.grasp_dims)
    actor = make_dt_actor(dt_cfg, observation_key="state", device=cfg.device)
    loss = MaskedOnlineDTLoss(actor, lambda_entropy=cfg.lambda_entropy, learn_temperature=cfg.learn_temperature,
                              action_eps=dt_cfg.action_eps)
    if cfg.action_target is not None:  # DAgger: the expert's action, stored beside the executed one
        loss.set_keys(action_target=cfg.action_target)
    updater = cfg.make_updater(loss, decay_steps=cfg.offline_updates, min_lr_fraction=cfg.min_lr_fraction)
    run.print(f"{cfg.task}: DT with {sum(p.numel() for p in actor.parameters()) / 1e6:.2f}M parameters "
              f"({dt_cfg.embed_dim}x{dt_cfg.n_layer}, K={dt_cfg.context_len}; action dims {list(dt_cfg.hidden_action_dims)} "
              f"left out of its action tokens)")
    state = teacher_state(run, updater, buffer_capacity=cfg.buffer_capacity)  # its counters, phases and updater
    phases = state.phases
    # 1. the expert data in the replay buffer. The DT reads standardised states (buffer windows and acting; noisy
    # ones with --train-state-noise; out-of-view pickers masked with --mask-unseen-pickers); the data stay raw.
    buffer, normalizer = cfg.state_buffer(state, cfg.data, phases=phases, task=cfg.task, horizon=cfg.horizon,
                                          seed=cfg.seed, context_len=cfg.model.context_len,
                                          target_key=cfg.action_target, extra_capacity=cfg.rollout_capacity,
                                          collect_pixels=cfg.collect_pixels, log=run.print, progress=cfg.progress)
    state.load()  # resumed: the updater and the buffer as checkpointed
    eval_rtg = cfg.eval_rtg if cfg.eval_rtg is not None else state["best_return"]
    explore_rtg = cfg.exploration_rtg if cfg.exploration_rtg is not None else eval_rtg
    handle = PolicyHandle("teacher", cfg.task, cfg.horizon, actor=actor, observation_key="state",
                          target_return=eval_rtg, rtg_scale=cfg.rtg_scale, normalizer=normalizer)
    evals, eval_env = cfg.eval_protocol(cfg.task, cfg.horizon, seed=cfg.seed, policy_seed=cfg.seed), cfg.make_env(handle)
    evaluations = TeacherEvaluations(run, evals, handle, eval_env, state)
    explore_env = cfg.make_env(handle, "train", target_return=explore_rtg) if state["rounds"] < cfg.online_rounds else None
    roll_out = cfg.rollouts(explore_env, handle, buffer, task=cfg.task, horizon=cfg.horizon, seed=cfg.seed,
                            close_radius=cfg.data.close_radius, collector=cfg.collector, phases=phases,
                            workers=cfg.num_envs)
    # early stopping: the snapshots play the same train-split episodes, configurations no evaluation plays
    select_env = cfg.make_env(handle, "train") if cfg.select_episodes and cfg.online_rounds else None
    selection = (SnapshotSelection.on_episodes(run, handle, evals, select_env, state, episodes=cfg.select_episodes,
                                               every=cfg.select_every, margin=cfg.select_margin, name="teacher")
                 if select_env is not None else None)
    sample = buffer_batches(buffer, cfg.batch_size, cfg.device)
    state.restore_rng()  # after building the envs, so the RNG streams continue exactly
    with RunEnvs(phases, eval_env, explore_env, select_env, evals=evals) as envs:  # closes them, cancels unfinished evaluations
        evaluations.expert(cache_root=cfg.data.root, use_cache=cfg.expert_cache, background=cfg.background_eval,
                           episodes=cfg.expert_episodes)  # 2. the scripted expert on the same episodes
        # 3. offline pretraining; the env workers start on the core that training leaves idle
        envs.start_workers(cfg.collector == "sync")  # multi_sync: these envs only describe the processes' envs
        with phases.phase("offline training"):
            if not train_updates(run, updater, sample, state=state, total=cfg.offline_updates, log_every=cfg.log_every,
                                 checkpoint_every=cfg.checkpoint_every, log_extra={"phase": 0}, desc="offline"):
                return dict(state)
        envs.join_workers()
        background = cfg.background_eval and state["rounds"] < cfg.online_rounds  # from its file, while the rounds run
        evaluations.offline(run.dir / "policy_offline.pt", dt_cfg, background=background)
        # 4. online fine-tuning: each round rolls out (train split), adds to the buffer (not the control), updates
        if selection is not None:  # the offline teacher: kept unless a later snapshot is measurably better
            selection.consider(0)
        if state["rounds"] < cfg.online_rounds:
            run.print(f"online fine-tuning: {cfg.online_rounds} rounds x {cfg.episodes_per_round} episodes, "
                      f"exploration return-to-go {explore_rtg:.3f} (evaluation: {eval_rtg:.3f})")
            updater.set_constant_lr(cfg.online_lr if cfg.online_lr is not None else cfg.lr * cfg.min_lr_fraction)
            if not train_rounds(run, updater, sample, state=state, rounds=cfg.online_rounds, model=actor,
                                updates_per_round=cfg.updates_per_round, roll_out=roll_out, phases=phases,
                                phase="online updates", log_extra={"phase": 1}, loss_key="train/loss_nll",
                                stop_key="updates", selection=selection, evaluate=evaluations.after_round,
                                eval_every=cfg.eval_every):
                return dict(state)
            envs.close(explore_env)  # its workers' cores go to the final evaluation
        kept = selection.finish(cfg.online_rounds, run.print) if selection is not None else cfg.online_rounds
        evaluations.final(kept, cfg.online_rounds)  # then the expert's and the offline teacher's background ones
    # 5. save: the policy, the checkpoint, the curves, the phases' times
    handle.save(run.dir / "policy.pt", dt_cfg, extra=selection.summary() if selection is not None else None)
    state.finish(columns=("train/loss_nll", "train/entropy", "online/normalized_performance", "eval/normalized_performance",
                          "eval_expert/normalized_performance"), extra={"num_envs": cfg.num_envs, "parallel": cfg.parallel})
    numbers, line = evaluations.summary()
    run.print(f"eval normalized performance (mean +- standard error): {line or 'not evaluated'}; "
              f"{time.time() - run.t0:.0f} s")
    return {**state, **numbers, "episodes_simulated": phases.episodes}


if __name__ == "__main__":
    main(sys.argv[1:])
