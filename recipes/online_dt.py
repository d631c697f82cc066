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
from typing import ClassVar, Literal

from trakdis.data import DataConfig, expert_targets, offline_state_buffer
from trakdis.envs import task_spec
from trakdis.envs.specs import TaskName
from trakdis.evaluation import EvalConfig, RunEnvs, compare_scores
from trakdis.modules import DTModelConfig, make_dt_actor, recipe_hidden_action_dims
from trakdis.objectives import MaskedOnlineDTLoss
from trakdis.optim import OptimConfig
from trakdis.policies import PolicyHandle
from trakdis.training import SnapshotSelection, online_rollouts, train_rounds, train_updates
from trakdis.transforms import OutOfViewFill
from trakdis.utils.limits import MAX_HORIZON, check_option, check_options
from trakdis.utils.run import Run, RunConfig, RunState

MAIN_JOB_EPISODES = 20
MAIN_JOB_LOG_STD_MIN = -1.5


@dataclass
class OnlineDTConfig(EvalConfig, OptimConfig, RunConfig):
    """Teacher: offline Decision Transformer pretraining on expert data, then online fine-tuning."""

    task: TaskName = "ClothFold"  # cloth task
    horizon: int = 100  # episode length
    # the main job's data and head (docs/recipes/online_dt.md, "The main job's online phase against its control"):
    # 20 demonstrations, so that the online phase has something to add; a log-std floor of -1.5, so that DAgger's
    # grasp corrections do not swamp the clipped updates. The presets and the method's teacher keep 40 (200) and -2.5.
    data: DataConfig = field(default_factory=lambda: DataConfig(episodes=MAIN_JOB_EPISODES))  # expert dataset
    model: DTModelConfig = field(default_factory=lambda: DTModelConfig(log_std_min=MAIN_JOB_LOG_STD_MIN))
    """Decision Transformer"""
    min_lr_fraction: float = 0.1  # cosine decay of --lr to this fraction by the end of pretraining (1: constant)
    online_lr: float | None = None  # constant lr of the online phase (default: the last offline one)
    batch_size: int = 64  # windows per update
    lambda_entropy: float = 0.1  # entropy bonus weight (paper: 0.1); initial temperature with --learn-temperature
    learn_temperature: bool = False  # learn the entropy temperature toward a target entropy of -action_dim (Online DT)
    state_scale_floor: float = 1e-3  # lower bound (metres) of the state normaliser's per-dimension scale
    train_state_noise: float = 0.0
    """std (m) of Gaussian noise on the training windows' true states (acting: exact)"""
    mask_unseen_pickers: bool = False  # train and act with a picker out of the 32x32 camera view as a fixed sentinel
    rtg_scale: float = 1.0  # return-to-go scale (rewards and targets are multiplied by it)
    buffer_capacity: int | None = None  # trajectories in the replay buffer (default: the dataset's; DAgger: +rollouts)
    buffer_replacement: Literal["oldest", "lowest_return"] = "lowest_return"
    """which trajectory a rollout replaces in a full buffer: the lowest-return one if it beats it, or the oldest"""
    early_windows: bool = True  # also sample windows that begin before an episode's first step (DT/ODT reference: no)
    offline_updates: int = 1500  # offline pretraining updates
    online_rounds: int = 8  # online rounds (roll out, add to the buffer, update)
    episodes_per_round: int = 8  # episodes rolled out per online round (train split; their actions: --exploration)
    updates_per_round: int = 150  # updates after each online rollout
    exploration_rtg: float | None = None  # initial return-to-go of the online rollouts (default: the evaluation's)
    offline_control: bool = False  # the online schedule without adding the rollouts to the buffer (the control)
    exploration: Literal["mean", "sample"] = "mean"  # the online rollouts' actions: the policy's mean, or samples
    online_labels: Literal["executed", "expert"] = "expert"
    """what the DT learns on its rollouts: the actions it executed (Online DT), or the scripted expert's
    action at each state it reached (DAgger; its context still reads the executed ones)"""
    SAVED_WITHOUT: ClassVar[dict] = {"online_labels": "executed"}  # a run saved before the option resumes as it ran
    SAVED_AS: ClassVar[dict] = {"state_noise": "train_state_noise"}  # the option's earlier name (--state-noise)
    select_episodes: int = 0
    """early stopping: train-split episodes that the offline teacher and the teacher every --select-every rounds
    (and after the last) play; the one kept beats the earlier ones by --select-margin standard errors (0: the last)"""
    select_every: int = 4  # rounds between the snapshots --select-episodes compares
    select_margin: float = 1.0  # standard errors of the paired difference a later snapshot must win by
    eval_rtg: float | None = None  # initial return-to-go at evaluation (default: the offline data's best return)
    expert_episodes: int = 10  # the scripted expert on the first N evaluation episodes, for comparison (0: none)
    expert_cache: bool = True  # reuse the expert's evaluation cached in <data.root>/expert_scores/
    background_eval: bool = True  # evaluate the expert and the offline teacher in a low-priority background process
    collect_pixels: bool = False  # also store the 32x32 images in the dataset this run collects (for train_encoder.py)
    log_every: int = 50  # log training metrics every N updates
    checkpoint_every: int = 500  # checkpoint every N offline updates (online: after every round)

    def __post_init__(self):  # checked while parsing, before the run directory exists
        for name, low in (("horizon", 1), ("expert_episodes", 0)):
            if getattr(self, name) < low:
                raise ValueError(f"--{name.replace('_', '-')} {getattr(self, name)}: must be >= {low}")
        check_options(self, sizes=("horizon", "batch_size", "log_every", "checkpoint_every", "select_every",
                                   "buffer_capacity"),
                      counts=("offline_updates", "online_rounds", "episodes_per_round", "updates_per_round",
                              "select_episodes"),
                      positive=("rtg_scale", "state_scale_floor", "online_lr"),
                      nonnegative=("lambda_entropy", "train_state_noise", "select_margin"))
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
    spec = task_spec(cfg.task, horizon=cfg.horizon)
    dt_cfg = cfg.model.for_task(spec.state_dim, spec.action_dim, cfg.horizon, hidden_action_dims=recipe_hidden_action_dims(cfg.task),
                                grasp_dims=spec.grasp_dims)
    actor = make_dt_actor(dt_cfg, observation_key="state", device=cfg.device)
    loss = MaskedOnlineDTLoss(actor, lambda_entropy=cfg.lambda_entropy, learn_temperature=cfg.learn_temperature,
                              action_eps=dt_cfg.action_eps)
    # DAgger: the loss's target is the expert's action, stored beside the executed one (the demonstrations': theirs)
    target = "expert_action" if cfg.online_labels == "expert" else None
    if target:
        loss.set_keys(action_target=target)
    updater = cfg.make_updater(loss, decay_steps=cfg.offline_updates, min_lr_fraction=cfg.min_lr_fraction)
    run.print(f"{cfg.task}: DT with {sum(p.numel() for p in actor.parameters()) / 1e6:.2f}M parameters "
              f"({dt_cfg.embed_dim}x{dt_cfg.n_layer}, K={dt_cfg.context_len}; action dims {list(dt_cfg.hidden_action_dims)} "
              f"left out of its action tokens)")
    scores = dict.fromkeys(f"{k}_{v}" for k in ("expert", "offline", "final") for v in ("eval", "scores"))
    state = RunState(run, {"updates": 0, "rounds": 0, "best_return": None, "normalizer": None, **scores,
                           "buffer_capacity": cfg.buffer_capacity}, step_key="updates", phases_key="phases", updater=updater)
    phases = state.phases
    record = lambda name: lambda s: state.update({f"{name}_eval": float(s.mean()), f"{name}_scores": s.tolist()})  # noqa: E731
    # 1. the expert data in the replay buffer. The DT reads standardised states (buffer windows and acting; noisy
    # ones with --train-state-noise; out-of-view pickers masked with --mask-unseen-pickers); the data stay raw.
    buffer, normalizer = offline_state_buffer(
        state, cfg.data, phases=phases, task=cfg.task, horizon=cfg.horizon, seed=cfg.seed,
        context_len=cfg.model.context_len, rtg_scale=cfg.rtg_scale, min_scale=cfg.state_scale_floor,
        state_noise=cfg.train_state_noise, fill=OutOfViewFill.for_task(cfg.task) if cfg.mask_unseen_pickers else None,
        early_windows=cfg.early_windows, replacement=cfg.buffer_replacement, collect_pixels=cfg.collect_pixels,
        log=run.print, progress=cfg.progress, target_key=target,
        extra_capacity=cfg.online_rounds * cfg.episodes_per_round if target else 0)  # DAgger keeps every rollout
    state.load()  # resumed: the updater and the buffer as checkpointed
    eval_rtg = cfg.eval_rtg if cfg.eval_rtg is not None else state["best_return"]
    explore_rtg = cfg.exploration_rtg if cfg.exploration_rtg is not None else eval_rtg
    handle = PolicyHandle("teacher", cfg.task, cfg.horizon, actor=actor, observation_key="state",
                          target_return=eval_rtg, rtg_scale=cfg.rtg_scale, normalizer=normalizer)
    evals, eval_env = cfg.eval_protocol(cfg.task, cfg.horizon, seed=cfg.seed, policy_seed=cfg.seed), cfg.make_env(handle)
    explore_env = cfg.make_env(handle, "train", target_return=explore_rtg) if state["rounds"] < cfg.online_rounds else None
    # early stopping: the snapshots play the same train-split episodes, configurations no evaluation plays
    select_env = cfg.make_env(handle, "train") if cfg.select_episodes and cfg.online_rounds else None
    selection = SnapshotSelection.on_episodes(run, handle, evals, select_env, state, episodes=cfg.select_episodes,
                                              every=cfg.select_every, margin=cfg.select_margin, name="teacher") \
        if select_env is not None else None
    sample = lambda: buffer.sample(cfg.batch_size).to(cfg.device)  # noqa: E731
    state.restore_rng()  # after building the envs, so the RNG streams continue exactly
    with RunEnvs(phases, eval_env, explore_env, select_env, evals=evals) as envs:  # closes them, cancels unfinished evaluations
        if state["expert_eval"] is None:  # 2. the scripted expert on the same episodes
            evals.expert_scores(run, eval_env, phases, cache_root=cfg.data.root, use_cache=cfg.expert_cache,
                                background=cfg.background_eval, episodes=cfg.expert_episodes,
                                on_scores=record("expert"))
        # 3. offline pretraining; the env workers start on the core that training leaves idle
        envs.start_workers(cfg.collector == "sync")  # multi_sync: these envs only describe the processes' envs
        with phases.phase("offline training"):
            if not train_updates(run, updater, sample, state=state, total=cfg.offline_updates, log_every=cfg.log_every,
                                 checkpoint_every=cfg.checkpoint_every, log_extra={"phase": 0}, desc="offline"):
                return dict(state)
        envs.join_workers()
        if state["offline_eval"] is None:  # in the background (from its file) while online fine-tuning runs
            state.once("offline_policy_saved", lambda: handle.save(run.dir / "policy_offline.pt", dt_cfg))
            background = cfg.background_eval and state["rounds"] < cfg.online_rounds
            if evals.evaluate(run, handle, eval_env, phases, "offline teacher", step=state["updates"],
                              tag="after offline pretraining", on_scores=record("offline"),
                              background=run.dir / "policy_offline.pt" if background else None) is not None:
                state.save()
        # 4. online fine-tuning: each round rolls out (train split), adds to the buffer (not the control), updates
        roll_out = lambda r: online_rollouts(  # noqa: E731
            explore_env, handle, buffer, cfg.episodes_per_round, horizon=cfg.horizon, seed=cfg.seed + 1000 * (r + 1),
            policy_seed=cfg.seed, deterministic=cfg.exploration == "mean", add=not cfg.offline_control,
            collector=cfg.collector, phases=phases, workers=cfg.num_envs, extra={"online/round": r + 1},
            label=(lambda ep: expert_targets(ep, cfg.task, out_key=target, close_radius=cfg.data.close_radius))
            if target else None)
        if selection is not None:  # the offline teacher: kept unless a later snapshot is measurably better
            selection.consider(0)

        def after_round(r: int):  # every round but the last
            if selection is not None:
                selection.after_round(r)
            if cfg.eval_every and r % cfg.eval_every == 0:
                evals.evaluate(run, handle, eval_env, phases, "mid-run", step=state["updates"], tag=f"after round {r}")
        if state["rounds"] < cfg.online_rounds:
            run.print(f"online fine-tuning: {cfg.online_rounds} rounds x {cfg.episodes_per_round} episodes, "
                      f"exploration return-to-go {explore_rtg:.3f} (evaluation: {eval_rtg:.3f})")
            updater.set_constant_lr(cfg.online_lr if cfg.online_lr is not None else cfg.lr * cfg.min_lr_fraction)
            if not train_rounds(run, updater, sample, state=state, rounds=cfg.online_rounds, model=actor,
                                updates_per_round=cfg.updates_per_round, roll_out=roll_out, phases=phases,
                                phase="online updates", log_extra={"phase": 1}, loss_key="train/loss_nll",
                                stop_key="updates", eval_every=1, evaluate=after_round):
                return dict(state)
            envs.close(explore_env)  # its workers' cores go to the final evaluation
        kept = selection.finish(cfg.online_rounds, run.print) if selection is not None else cfg.online_rounds
        if kept > 0:
            evals.evaluate(run, handle, eval_env, phases, "final teacher", step=state["updates"],
                           tag="after online fine-tuning" + (f" (round {kept}, kept)" if kept < cfg.online_rounds else ""),
                           on_scores=record("final"))
        evals.finish_pending(run, phases)  # the offline teacher's and the expert's background evaluations
        if kept == 0:  # the offline teacher (no online round, or kept by the selection): its evaluation stands
            state.update(final_eval=state["offline_eval"], final_scores=state["offline_scores"])
    # 5. save: the policy, the checkpoint, the curves, the phases' times
    handle.save(run.dir / "policy.pt", dt_cfg, extra=selection.summary() if selection is not None else None)
    state.finish(columns=("train/loss_nll", "train/entropy", "online/normalized_performance", "eval/normalized_performance",
                          "eval_expert/normalized_performance"), extra={"num_envs": cfg.num_envs, "parallel": cfg.parallel})
    summary = {"expert": state["expert_eval"], "offline": state["offline_eval"], "online": state["final_eval"]}
    line, numbers = compare_scores(summary, {"offline": state["offline_scores"], "online": state["final_scores"]},
                                   before="offline", after="online")
    run.print(f"eval normalized performance (mean +- standard error): {line or 'not evaluated'}; "
              f"{time.time() - run.t0:.0f} s")
    return {**state, **summary, **numbers, "episodes_simulated": phases.episodes}


if __name__ == "__main__":
    main(sys.argv[1:])
