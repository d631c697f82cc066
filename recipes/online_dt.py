"""The privileged teacher: a Decision Transformer on the true reduced state, trained offline on
expert data and then fine-tuned online (Online DT, Zheng et al. 2022), as in TraKDis.

    python recipes/online_dt.py                       # ClothFold
    python recipes/online_dt.py --preset paper        # the paper's model and optimiser (slow on a CPU)
    python recipes/online_dt.py --resume              # continue the latest run after a kill

Steps, outputs (``runs/online_dt/<name>/``), options and measurements: docs/recipes/online_dt.md.
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from trakdis.data import DataConfig, offline_state_buffer
from trakdis.envs import task_spec
from trakdis.envs.specs import TaskName
from trakdis.evaluation import EvalProtocol, RunEnvs, compare_scores, run_episodes
from trakdis.modules import DTConfig, make_dt_actor
from trakdis.objectives import MaskedOnlineDTLoss
from trakdis.optim import OptimConfig
from trakdis.policies import PolicyHandle
from trakdis.training import run_updates, train_candidates
from trakdis.transforms import OutOfViewFill
from trakdis.utils.phases import available_workers
from trakdis.utils.run import Run, RunConfig, RunState, seed_everything

@dataclass
class OnlineDTConfig(OptimConfig, RunConfig):
    """Teacher: offline Decision Transformer pretraining on expert data, then online fine-tuning."""

    task: TaskName = "ClothFold"  # cloth task
    horizon: int = 100  # episode length
    data: DataConfig = field(default_factory=DataConfig)  # expert dataset
    model: DTConfig = field(default_factory=DTConfig)  # Decision Transformer
    min_lr_fraction: float = 0.1  # cosine decay of --lr to this fraction by the end of pretraining (1: constant)
    online_lr: float | None = None  # constant lr of the online phase (default: the last offline one)
    batch_size: int = 64  # windows per update
    lambda_entropy: float = 0.1  # entropy bonus weight (paper: 0.1); initial temperature with --learn-temperature
    learn_temperature: bool = False  # learn the entropy temperature toward a target entropy of -action_dim (Online DT)
    state_scale_floor: float = 1e-3  # lower bound (metres) of the state normaliser's per-dimension scale
    state_noise: float = 0.0  # std (metres) of Gaussian noise on the training windows' states (acting: exact)
    mask_unseen_pickers: bool = False  # train and act with a picker out of the 32x32 camera view as a fixed sentinel
    rtg_scale: float = 1.0  # return-to-go scale (rewards and targets are multiplied by it)
    buffer_capacity: int | None = None  # trajectories in the replay buffer (default: the offline dataset's number)
    buffer_replacement: Literal["oldest", "lowest_return"] = "lowest_return"
    """which trajectory a rollout replaces in a full buffer: the lowest-return one if it beats it, or the oldest"""
    early_windows: bool = True  # also sample windows that begin before an episode's first step (DT/ODT reference: no)
    offline_updates: int = 1500  # offline pretraining updates
    offline_candidates: int = 1  # offline teachers from independent initialisations; the best goes online
    selection_episodes: int = 20  # train-split episodes that score each offline candidate
    online_rounds: int = 8  # online rounds (roll out, add to the buffer, update)
    episodes_per_round: int = 8  # episodes rolled out per online round (train split; their actions: --exploration)
    updates_per_round: int = 150  # updates after each online rollout
    exploration_rtg: float | None = None  # initial return-to-go of the online rollouts (default: the evaluation's)
    offline_control: bool = False  # the online schedule without adding the rollouts to the buffer (the control)
    exploration: Literal["mean", "sample"] = "mean"  # the online rollouts' actions: the policy's mean, or samples
    eval_rtg: float | None = None  # initial return-to-go at evaluation (default: the offline data's best return)
    eval_episodes: int = 30  # evaluation episodes (eval split, the same configurations every time; 0: none)
    eval_every: int = 0  # also evaluate every N online rounds (0: only after pretraining and at the end)
    eval_expert: bool = True  # also evaluate the scripted expert on the evaluation episodes, for comparison
    expert_episodes: int = 10  # the expert on only the first N of them (its scores vary little: std ~0.04)
    expert_cache: bool = True  # reuse the expert's evaluation cached in <data.root>/expert_scores/
    background_eval: bool = True  # evaluate the expert and the offline teacher in a low-priority background process
    collect_pixels: bool = False  # also store the 32x32 images in the dataset this run collects (for train_encoder.py)
    num_envs: int = field(default_factory=available_workers)  # envs stepped together (default: the cores, at most 2)
    parallel: bool = True  # step them in worker processes (ParallelEnv; --no-parallel: in turn, the same numbers)
    collector: Literal["sync", "multi_sync"] = "sync"  # one Collector here, or a MultiSyncCollector of --num-envs
    log_every: int = 50  # log training metrics every N updates
    checkpoint_every: int = 500  # checkpoint every N offline updates (online: after every round)

    def __post_init__(self):  # checked while parsing, before the run directory exists
        for name in ("horizon", "offline_candidates", "selection_episodes", "expert_episodes"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')} {getattr(self, name)}: must be >= 1")


PRESETS = {
    "paper": {
        "model": dict(DTConfig.PAPER_SIZES),
        "optimizer": "lamb", "lr": 1e-4, "weight_decay": 1e-4, "warmup_steps": 10000, "batch_size": 256,
        "data": {"episodes": 8000}, "offline_updates": 5000, "online_rounds": 1500, "episodes_per_round": 1,
        "updates_per_round": 300, "buffer_capacity": 1000, "buffer_replacement": "oldest", "min_lr_fraction": 1.0,
        "eval_rtg": -1.0, "eval_episodes": 100, "expert_episodes": 100, "eval_every": 50,
    },
}


def main(argv=None) -> dict:
    run = Run.start("online_dt", OnlineDTConfig, argv, presets=PRESETS, description=__doc__)
    cfg = run.cfg
    spec = task_spec(cfg.task, horizon=cfg.horizon)
    dt_cfg = cfg.model.for_task(spec.state_dim, spec.action_dim, cfg.horizon)

    def build(seed: int | None = None):  # the DT, its loss and their optimiser; offline candidate k: seed + 1000 k
        if seed is not None:
            seed_everything(seed)
        actor = make_dt_actor(dt_cfg, observation_key="state", device=cfg.device)
        loss = MaskedOnlineDTLoss(actor, lambda_entropy=cfg.lambda_entropy, learn_temperature=cfg.learn_temperature,
                                  action_eps=dt_cfg.action_eps)
        return actor, cfg.make_updater(loss, decay_steps=cfg.offline_updates, min_lr_fraction=cfg.min_lr_fraction)

    actor, updater = build()
    run.print(f"{cfg.task}: DT with {sum(p.numel() for p in actor.parameters()) / 1e6:.2f}M parameters "
              f"({dt_cfg.embed_dim}x{dt_cfg.n_layer}, K={dt_cfg.context_len})")
    state = RunState(run, {"updates": 0, "rounds": 0, "offline_eval": None, "expert_eval": None, "best_return": None,
                           "normalizer": None, "buffer_capacity": cfg.buffer_capacity, "offline_scores": None},
                     step_key="updates", phases_key="phases", updater=updater)
    phases, offline_total = state.phases, cfg.offline_candidates * cfg.offline_updates
    # 1. the expert data in the replay buffer. The DT reads standardised states (buffer windows and acting; noisy
    # ones with --state-noise; out-of-view pickers masked with --mask-unseen-pickers); the data stay raw.
    buffer, normalizer = offline_state_buffer(
        state, cfg.data, phases=phases, task=cfg.task, horizon=cfg.horizon, seed=cfg.seed,
        context_len=cfg.model.context_len, rtg_scale=cfg.rtg_scale, min_scale=cfg.state_scale_floor,
        state_noise=cfg.state_noise, fill=OutOfViewFill.for_task(cfg.task) if cfg.mask_unseen_pickers else None,
        early_windows=cfg.early_windows, replacement=cfg.buffer_replacement, collect_pixels=cfg.collect_pixels,
        log=run.print, progress=cfg.progress)
    state.load()  # resumed: the updater and the buffer as checkpointed
    eval_rtg = cfg.eval_rtg if cfg.eval_rtg is not None else state["best_return"]
    explore_rtg = cfg.exploration_rtg if cfg.exploration_rtg is not None else eval_rtg
    handle = PolicyHandle("teacher", cfg.task, cfg.horizon, actor=actor, observation_key="state",
                          target_return=eval_rtg, rtg_scale=cfg.rtg_scale, normalizer=normalizer)
    evals = EvalProtocol(cfg.task, cfg.horizon, cfg.eval_episodes, cfg.num_envs, seed=cfg.seed + 10_000,
                         policy_seed=cfg.seed, collector=cfg.collector)
    eval_env = handle.make_env(num_envs=cfg.num_envs, split="eval", parallel=cfg.parallel) if cfg.eval_episodes else None
    explore_env = None if state["rounds"] >= cfg.online_rounds else handle.make_env(
        num_envs=cfg.num_envs, split="train", parallel=cfg.parallel, target_return=explore_rtg)
    sample = lambda: buffer.sample(cfg.batch_size).to(cfg.device)  # noqa: E731
    state.restore_rng()  # after building the envs, so the RNG streams continue exactly
    offline_res = None
    with RunEnvs(phases, eval_env, explore_env, evals=evals) as envs:  # closes them, cancels unfinished evaluations
        if cfg.eval_expert and state["expert_eval"] is None:  # 2. the scripted expert on the same episodes
            evals.expert_scores(run, eval_env, phases, cache_root=cfg.data.root, use_cache=cfg.expert_cache,
                                background=cfg.background_eval, episodes=cfg.expert_episodes,
                                on_scores=lambda s: state.update(expert_eval=float(np.mean(s))))
        # 3. offline pretraining (--offline-candidates N: N teachers in turn, each scored on train-split episodes in
        # the background, the best kept); the env workers start on the core that training leaves idle
        envs.start_workers(cfg.collector == "sync")  # multi_sync: these envs only describe the processes' envs
        if not train_candidates(
                run, updater, sample, state=state, phases=phases, candidates=cfg.offline_candidates,
                total=cfg.offline_updates, log_every=cfg.log_every, checkpoint_every=cfg.checkpoint_every,
                log_extra={"phase": 0}, fresh_state=lambda k: build(cfg.seed + 1000 * k)[1].state_dict(),
                save_policy=lambda path: handle.save(path, dt_cfg),
                score=lambda path, k: evals.scores_in_background(
                    run, path, phases, f"offline candidate {k + 1}", step=(k + 1) * cfg.offline_updates,
                    episodes=cfg.selection_episodes, seed=cfg.seed + 20_000)):
            return dict(state)
        envs.join_workers()
        if state["offline_eval"] is None:
            state.once("offline_policy_saved", lambda: handle.save(run.dir / "policy_offline.pt", dt_cfg))
            background = cfg.background_eval and state["rounds"] < cfg.online_rounds
            offline_res = evals.evaluate(run, handle, eval_env, phases, "offline teacher", step=state["updates"],
                                         tag="after offline pretraining", background_step=offline_total,
                                         background=run.dir / "policy_offline.pt" if background else None,
                                         on_scores=lambda s: state.update(offline_eval=float(s.mean()),
                                                                          offline_scores=s.tolist()))
            if offline_res is not None:
                state.save()
        # 4. online fine-tuning: roll out (train split), add to the buffer, update
        if state["rounds"] < cfg.online_rounds:
            run.print(f"online fine-tuning: {cfg.online_rounds} rounds x {cfg.episodes_per_round} episodes, "
                      f"exploration return-to-go {explore_rtg:.3f} (evaluation: {eval_rtg:.3f})")
            updater.set_constant_lr(cfg.online_lr if cfg.online_lr is not None else cfg.lr * cfg.min_lr_fraction)
            while state["rounds"] < cfg.online_rounds:
                with phases.phase("online rollouts", episodes=cfg.episodes_per_round, workers=cfg.num_envs):
                    res = run_episodes(explore_env, handle.make_policy(seed=cfg.seed), cfg.episodes_per_round,
                                       max_steps=cfg.horizon, deterministic=cfg.exploration == "mean",
                                       keep_episodes=True, desc="rollout", seed=cfg.seed + 1000 * (state["rounds"] + 1),
                                       collector=cfg.collector)
                actor.train()
                kept = buffer.add_episodes(res.episodes if not cfg.offline_control else (), keys=("state", "action"))
                state["rounds"] += 1
                with phases.phase("online updates"):
                    metrics = run_updates(updater, sample, cfg.updates_per_round, desc=f"round {state['rounds']}")
                state["updates"] += cfg.updates_per_round
                run.log(state["updates"], {**metrics, "phase": 1, "online/normalized_performance":
                                           float(res.final_performance.mean()), "online/return": float(res.returns.mean()),
                                           "online/round": state["rounds"], "online/kept": kept,
                                           "online/buffer_online_fraction": buffer.online_fraction})
                run.print(f"round {state['rounds']}/{cfg.online_rounds}: rollout normalized performance "
                          f"{res.final_performance.mean():.3f}, return {res.returns.mean():.3f} ({kept} kept; buffer "
                          f"{buffer.online_fraction:.0%} online), loss_nll {run.logger.last('train/loss_nll'):.3f}; {res.rate()}")
                if cfg.eval_every and state["rounds"] % cfg.eval_every == 0 and state["rounds"] < cfg.online_rounds:
                    evals.evaluate(run, handle, eval_env, phases, "mid-run", step=state["updates"],
                                   tag=f"after round {state['rounds']}")
                if state.save_and_should_stop(offline_total + cfg.online_rounds * cfg.updates_per_round, unit="update"):
                    return dict(state)
            envs.close(explore_env)  # its workers' cores go to the final evaluation
        res = offline_res if cfg.online_rounds == 0 and offline_res is not None else evals.evaluate(  # no update since
            run, handle, eval_env, phases, "final teacher", step=state["updates"], tag="after online fine-tuning")
        evals.finish_pending(run, phases)  # the offline teacher's and the expert's background evaluations
    final = None if res is None else res.final_performance  # --eval-episodes 0: not evaluated
    state.update(final_eval=None if final is None else float(final.mean()),
                 final_scores=None if final is None else final.tolist())
    with phases.phase("files and curves"):  # 5. save
        handle.save(run.dir / "policy.pt", dt_cfg)
        state.save()
        run.finish(columns=("train/loss_nll", "train/entropy", "online/normalized_performance",
                            "eval/normalized_performance", "eval_expert/normalized_performance"))
    phases.report(run.print, run.dir / "phases.json", total_wall=time.time() - run.t0, resumed=run.resuming,
                  extra={"num_envs": cfg.num_envs, "parallel": cfg.parallel})
    summary = {"expert": state["expert_eval"], "offline": state["offline_eval"], "online": state["final_eval"]}
    line, numbers = compare_scores(summary, {"offline": state["offline_scores"], "online": final},
                                   before="offline", after="online")
    run.print(f"eval normalized performance (mean +- standard error): {line or 'not evaluated'}; "
              f"{time.time() - run.t0:.0f} s")
    return {**state, **summary, **numbers, "episodes_simulated": phases.episodes}


if __name__ == "__main__":
    main(sys.argv[1:])
