"""The privileged teacher: a Decision Transformer on the true reduced state, trained offline on
expert data and then fine-tuned online (Online DT, Zheng et al. 2022), as in TraKDis.

    python recipes/online_dt.py                       # ClothFold (time per phase: docs/recipes/online_dt.md)
    python recipes/online_dt.py --preset paper        # the paper's model and optimiser (slow on a CPU)
    python recipes/online_dt.py --resume              # continue the latest run after a kill

1. Expert data: ``--data.path DIR``, or ``datasets/<task>_<N>ep_h<horizon>_noise<s>_px32`` collected
   with the scripted expert (``--data.episodes N``, action noise ``--data.expert-noise``) if missing.
2. Offline pretraining: ``--offline-updates`` updates on windows of the trajectory buffer.
3. Online fine-tuning: ``--online-rounds`` rounds of [roll out ``--episodes-per-round`` episodes
   (``--exploration mean|sample``) with the return-to-go ``--exploration-rtg``, add them to the
   buffer (``--buffer-replacement``: a rollout replaces the lowest-return trajectory if it beats
   it, or the oldest one as in Online DT), ``--updates-per-round`` updates].
4. Evaluation (mean action, eval split, return-to-go ``--eval-rtg``, ``--eval-episodes`` episodes)
   after offline pretraining and at the end (and every ``--eval-every`` rounds if asked); the
   scripted expert plays the same episodes once, its scores cached in
   ``<data.root>/expert_scores/`` for later runs (``--no-expert-cache``: measure again).

Every batch of episodes (collection, evaluation, online rollouts) runs on ``--num-envs``
environments in worker processes (``ParallelEnv``; default: one per available core, at most 2).
The run ends with a table of the phases: wall and CPU seconds, episodes simulated.

Writes ``runs/online_dt/<name>/``: ``config.json``, ``log.csv``, ``curves.png``,
``checkpoint.pt`` (resume), ``policy_offline.pt`` and ``policy.pt`` (for evaluate.py/distill.py).
"""
from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Literal, Optional

import numpy as np
import torch

from trakdis.data import (DataConfig, default_dataset_path, ensure_dataset, episode_to_trajectory, load_trajectories,
                          make_buffer, partial_path, valid_mask)
from trakdis.envs import close_env, start_in_background
from trakdis.envs.specs import TaskName
from trakdis.evaluation import (BackgroundEvaluation, EpisodeResults, expert_score_key, expert_score_path,
                                paired_difference, read_expert_scores, run_episodes, standard_error, summarize,
                                write_expert_scores)
from trakdis.modules import DTConfig
from trakdis.optim import OptimConfig, mean_metrics
from trakdis.policies import PolicyHandle, load_policy, save_policy
from trakdis.transforms import StateNormalizer
from trakdis.utils.checkpoint import atomic_write_bytes, rng_state, set_rng_state
from trakdis.utils.phases import PhaseTimer, available_workers
from trakdis.utils.progress import progress
from trakdis.utils.run import Run, RunConfig


@dataclass
class OnlineDTConfig(OptimConfig, RunConfig):
    """Teacher: offline Decision Transformer pretraining on expert data, then online fine-tuning."""

    task: TaskName = "ClothFold"
    """cloth task"""
    horizon: int = 100
    """episode length"""
    data: DataConfig = field(default_factory=DataConfig)
    """expert dataset"""
    model: DTConfig = field(default_factory=DTConfig)
    """Decision Transformer"""
    min_lr_fraction: float = 0.1
    """the learning rate decays (cosine) from --lr to this fraction of it by the end of offline
    pretraining (1: constant after the warm-up, as in ODT)"""
    online_lr: Optional[float] = None
    """constant learning rate of the online phase (default: the last offline one, --lr x --min-lr-fraction)"""
    batch_size: int = 64
    """windows per update"""
    lambda_entropy: float = 0.1
    """entropy bonus weight (paper: 0.1); initial temperature with --learn-temperature"""
    learn_temperature: bool = False
    """learn the entropy temperature toward a target entropy of -action_dim (Online DT)"""
    state_scale_floor: float = 1e-3
    """lower bound (metres) of the state normaliser's per-dimension scale. A near-constant
    coordinate (a corner's height) divided by a tiny scale magnifies a small estimation error into
    many standard units; 0.02 (about one pixel of the 32x32 camera) was tried for the student and
    is not the default: on ClothFold it did not make the teacher robust to 1 cm of state noise
    (docs/recipes/distill.md)"""
    state_noise: float = 0.0
    """std (metres) of Gaussian noise added to the states of every training window (the acting
    state stays exact): a teacher that has seen imprecise states can be copied into a student that
    reads an image encoder's estimates (docs/recipes/distill.md)"""
    rtg_scale: float = 1.0
    """return-to-go scale (rewards and targets are multiplied by it)"""
    buffer_capacity: Optional[int] = None
    """trajectories in the replay buffer (default: as many as the offline dataset has, so every
    rollout competes with a demonstration; Online DT: 1000)"""
    buffer_replacement: Literal["oldest", "lowest_return"] = "lowest_return"
    """which trajectory a rollout replaces once the buffer is full: the lowest-return one, and only
    if the rollout's return is higher (rollouts worse than every stored trajectory are dropped), or
    the oldest (Online DT: the lowest-return offline ones go first, then first-in first-out)"""
    early_windows: bool = True
    """also sample windows that begin before an episode's first step, so its first K-1 steps are
    trained as often as the others (the DT/ODT reference: --no-early-windows)"""
    offline_updates: int = 1500
    """offline pretraining updates"""
    online_rounds: int = 8
    """online rounds (roll out, add to the buffer, update)"""
    episodes_per_round: int = 8
    """episodes rolled out per online round (sampled actions, train split)"""
    updates_per_round: int = 150
    """updates after each online rollout"""
    exploration_rtg: Optional[float] = None
    """initial return-to-go of the online rollouts (default: the evaluation target)"""
    offline_control: bool = False
    """run the online schedule (rollouts, updates, evaluations) but never add the rollouts to the
    buffer: the offline-only control with the same number of updates, to tell what the online
    data changed from what more training changed"""
    exploration: Literal["mean", "sample"] = "mean"
    """actions of the online rollouts: the policy's mean, or samples as in Online DT (on ClothFold,
    sampled rollouts scored ~0 while the mean scored ~0.4: one flipped grasp drops the cloth)"""
    eval_rtg: Optional[float] = None
    """initial return-to-go at evaluation (default: the best return of the offline data; the paper
    uses -1 on SoftGym's reward scale)"""
    eval_episodes: int = 30
    """evaluation episodes (eval split; the same configurations for every evaluation of a run, so the
    online gain is a paired difference; standard error of a teacher's score 0.05-0.08 at 30, printed
    with every score); the paper uses 100"""
    eval_every: int = 0
    """also evaluate every N online rounds (0: only after pretraining and at the end)"""
    eval_expert: bool = True
    """also evaluate the scripted expert on the evaluation episodes, for comparison"""
    expert_cache: bool = True
    """reuse the expert's evaluation cached in <data.root>/expert_scores/ (measured once per task,
    horizon, --eval-episodes, seed and --num-envs; the expert is deterministic); --no-expert-cache
    measures it again and replaces the cached file"""
    background_eval: bool = True
    """evaluate the scripted expert and the offline teacher in a background process at low priority,
    on the CPU time that training leaves idle (the same episodes and numbers; --no-background-eval:
    in turn, in this process)"""
    collect_pixels: bool = False
    """also store the 32x32 images in the dataset this run collects (pipeline.py: train_encoder.py
    reuses it); the teacher reads states only, and an existing dataset with images is used as it is"""
    num_envs: int = field(default_factory=available_workers)
    """environments stepped together (default: the available cores, at most 2); the evaluation
    episodes' configurations depend on it, so compare runs of the same count"""
    parallel: bool = True
    """step them in worker processes (ParallelEnv), one core each; --no-parallel: in turn in this
    process (SerialEnv; the same episodes and numbers)"""
    collector: Literal["sync", "multi_sync"] = "sync"
    """how evaluations and online rollouts step their --num-envs envs: one TorchRL Collector here
    (the envs in ParallelEnv workers, or in turn with --no-parallel), or a MultiSyncCollector of
    --num-envs processes, each with its own env and copy of the policy, started for every batch of
    episodes (the same configurations; docs/scaling.md)"""
    log_every: int = 50
    """log training metrics every N updates"""
    checkpoint_every: int = 500
    """checkpoint every N offline updates (online: after every round)"""

    def __post_init__(self):
        if self.horizon < 1:  # checked while parsing, before the run directory exists
            raise ValueError(f"--horizon {self.horizon}: the episode length must be >= 1")


PRESETS = {
    "paper": {
        "model": dict(DTConfig.PAPER_SIZES),
        "optimizer": "lamb", "lr": 1e-4, "weight_decay": 1e-4, "warmup_steps": 10000, "batch_size": 256,
        "data": {"episodes": 8000}, "offline_updates": 5000, "online_rounds": 1500, "episodes_per_round": 1,
        "updates_per_round": 300, "buffer_capacity": 1000, "buffer_replacement": "oldest", "min_lr_fraction": 1.0,
        "eval_rtg": -1.0, "eval_episodes": 100, "eval_every": 50,
    },
}


def evaluate(run: Run, handle: PolicyHandle, env, cfg: OnlineDTConfig, step: int, tag: str) -> EpisodeResults:
    actor = handle.actor
    was_training = actor.training if actor is not None else False
    # Every evaluation replays the same eval-split configurations (same seed): scores are comparable,
    # and the online gain is a paired difference.
    res = run_episodes(env, handle.make_policy(seed=cfg.seed), cfg.eval_episodes, max_steps=cfg.horizon,
                       desc=f"eval ({tag})", seed=cfg.seed + 10_000, collector=cfg.collector)
    if actor is not None:
        actor.train(was_training)
    log_scores(run, step, "eval" if handle.kind != "expert" else "eval_expert", tag, res.final_performance,
               res.returns, detail=res.rate())
    return res


def log_scores(run: Run, step: int, prefix: str, tag: str, scores, returns, detail: str = "") -> None:
    s = summarize(scores)
    run.log(step, {f"{prefix}/normalized_performance": s["mean"], f"{prefix}/std": s["std"],
                   f"{prefix}/return": float(np.mean(returns))})
    run.print(f"{tag}: normalized performance {s['mean']:.3f} +- {s['std']:.3f} (std; standard error "
              f"{standard_error(scores):.3f}; return {np.mean(returns):.3f}, {s['n']} eval episodes)"
              + (f"; {detail}" if detail else ""))


def background_evaluation(spec, cfg: OnlineDTConfig, phases: PhaseTimer, what: str) -> BackgroundEvaluation:
    """``evaluate`` of the policy file ``spec`` in a background process (the same episodes)."""
    job = BackgroundEvaluation(spec, task=cfg.task, horizon=cfg.horizon, num_episodes=cfg.eval_episodes,
                               num_envs=cfg.num_envs, env_seed=cfg.seed + 10_000, policy_seed=cfg.seed)
    phases.exclude(job.pid)
    return job


def finish_background(run: Run, job: BackgroundEvaluation, phases: PhaseTimer, cfg: OnlineDTConfig, what: str,
                      step: int, prefix: str, tag: str) -> EpisodeResults:
    """Wait for a background evaluation, book its time and log its scores at ``step``."""
    with phases.phase(f"waiting for the background evaluation ({what})"):
        res = job.result()  # its CPU seconds join RUSAGE_CHILDREN here: booked to its own row at once
        phases.add_background(f"evaluation ({what}, background)", job.pid, episodes=cfg.eval_episodes,
                              wall=job.wall_seconds, cpu=job.cpu_seconds, workers=1)
    log_scores(run, step, prefix, tag, res.final_performance, res.returns,
               detail=f"{cfg.eval_episodes} episodes in {job.wall_seconds:.0f} s in a background process")
    return res


def expert_baseline(run: Run, env, cfg: OnlineDTConfig, phases: PhaseTimer) -> np.ndarray | BackgroundEvaluation:
    """The scripted expert's scores on the evaluation episodes: from the cache next to the datasets,
    or measured (in a background process with --background-eval, whose results the caller caches;
    else on ``env``, the teacher's evaluation env: the expert ignores its return-to-go) and cached."""
    key = expert_score_key(task=cfg.task, split="eval", horizon=cfg.horizon, episodes=cfg.eval_episodes,
                           seed=cfg.seed + 10_000, num_envs=cfg.num_envs)
    path = expert_score_path(cfg.data.root, key)
    cached = read_expert_scores(path, key) if cfg.expert_cache else None
    if cached is not None:
        scores, returns = cached
        log_scores(run, 0, "eval_expert", "scripted expert", scores, returns,
                   detail=f"measured once, cached in {path}")
        return scores
    if cfg.background_eval:
        job = background_evaluation("expert", cfg, phases, "scripted expert")
        job.cache_path, job.cache_key = path, key
        return job
    expert = load_policy("expert", task=cfg.task, horizon=cfg.horizon)
    with phases.phase("expert evaluation", episodes=cfg.eval_episodes, workers=cfg.num_envs):
        res = evaluate(run, expert, env, cfg, 0, "scripted expert")
    write_expert_scores(path, key, res.final_performance, returns=res.returns, seconds=res.seconds)
    run.print(f"scripted expert's scores cached in {path} (later runs of this configuration reuse them)")
    return res.final_performance


def _episodes_done(partial) -> int:
    """Episodes an interrupted collection already wrote (0 if its progress file is unreadable)."""
    try:
        return int(json.loads((partial / "progress.json").read_text())["episodes_done"])
    except (OSError, ValueError, KeyError, TypeError):
        return 0


def main(argv=None) -> dict:
    run = Run.start("online_dt", OnlineDTConfig, argv, presets=PRESETS, description=__doc__)
    cfg = run.cfg
    from trakdis.envs import task_spec
    from trakdis.modules import make_dt_actor
    from trakdis.objectives import MaskedOnlineDTLoss

    spec = task_spec(cfg.task, horizon=cfg.horizon)
    dt_cfg = cfg.model.for_task(spec.state_dim, spec.action_dim, cfg.horizon)
    actor = make_dt_actor(dt_cfg, observation_key="state", device=cfg.device)
    loss = MaskedOnlineDTLoss(actor, lambda_entropy=cfg.lambda_entropy, learn_temperature=cfg.learn_temperature,
                  action_eps=dt_cfg.action_eps)
    updater = cfg.make_updater(loss, decay_steps=cfg.offline_updates, min_lr_fraction=cfg.min_lr_fraction)
    n_params = sum(p.numel() for p in actor.parameters())
    run.print(f"{cfg.task}: DT with {n_params / 1e6:.2f}M parameters ({dt_cfg.embed_dim}x{dt_cfg.n_layer}, K={dt_cfg.context_len})")

    counters = {"updates": 0, "rounds": 0, "offline_eval": None, "expert_eval": None, "best_return": None,
                "normalizer": None, "buffer_capacity": cfg.buffer_capacity, "offline_scores": None, "phases": {}}
    state = run.resume_state()
    if state is not None:
        counters.update(state["counters"])
        trajectories = lengths = None
    phases = PhaseTimer(counters["phases"])
    if state is None:
        pixels = cfg.collect_pixels or (default_dataset_path(cfg.data, task=cfg.task, horizon=cfg.horizon,
                                                             pixels=True) / "meta.json").exists()
        path = default_dataset_path(cfg.data, task=cfg.task, horizon=cfg.horizon, pixels=pixels)
        before = 0 if not partial_path(path).exists() else _episodes_done(partial_path(path))
        with phases.phase("dataset collection", workers=cfg.data.num_envs) as rec:
            collecting = not (path / "meta.json").exists()
            dataset = ensure_dataset(cfg.data, task=cfg.task, horizon=cfg.horizon, seed=cfg.seed, pixels=pixels,
                                     log=run.print, progress=cfg.progress)
            if collecting:
                rec["episodes"] += cfg.data.episodes - before
        if collecting:
            n, secs = cfg.data.episodes - before, rec["wall"]
            run.print(f"collected {n} episodes in {secs:.1f} s, {cfg.data.num_envs} workers: "
                      f"{n / max(secs, 1e-9):.2f} episodes/s, {n * cfg.horizon / max(secs, 1e-9) / cfg.data.num_envs:.1f} "
                      f"steps/s per worker")
        trajectories, lengths = load_trajectories(dataset, keys=("state", "action", "reward", "normalized_performance"))
        trajectories = trajectories.to_tensordict()
        valid = valid_mask(lengths, trajectories.shape[1])
        counters["normalizer"] = StateNormalizer.fit(trajectories["state"][valid],
                                                      min_scale=cfg.state_scale_floor).state_dict()
        rets = trajectories["reward"].sum(dim=(-2, -1))
        final = trajectories["normalized_performance"][torch.arange(len(lengths)), lengths - 1]
        run.print(f"offline data: {trajectories.shape[0]} episodes from {dataset}; return {rets.mean():.3f} "
                  f"(best {rets.max():.3f}); final normalized performance {final.mean():.3f}")
        counters["best_return"] = float(rets.max())
        if counters["buffer_capacity"] is None:
            counters["buffer_capacity"] = int(trajectories.shape[0])
    # The DT reads standardised states (buffer windows and acting); data and envs stay raw.
    normalizer = StateNormalizer.from_state_dict(counters["normalizer"])
    transform = normalizer
    if cfg.state_noise > 0:  # in state units, before standardisation
        from trakdis.transforms import StateNoise

        noise = StateNoise(cfg.state_noise, in_keys=["state"], seed=cfg.seed + 7919)

        def transform(td):
            return normalizer(noise(td))
    buffer = make_buffer(counters["buffer_capacity"], cfg.model.context_len, cfg.horizon, cfg.rtg_scale, keys=("state",),
                         seed=cfg.seed, transform=transform, early_windows=cfg.early_windows,
                         replacement=cfg.buffer_replacement)
    if state is not None:
        updater.load_state_dict(state["updater"])
        buffer.load_state_dict(state["buffer"])
    else:
        buffer.load_offline(trajectories, lengths)

    def checkpoint():
        counters["phases"] = phases.state_dict()
        run.save_checkpoint({"updater": updater.state_dict(), "buffer": buffer.state_dict(),
                             "counters": counters, "rng": rng_state()}, step=counters["updates"])

    def policy_file(path, kind="teacher"):
        save_policy(path, kind=kind, task=cfg.task, horizon=cfg.horizon, dt_config=dt_cfg, actor=actor,
                    observation_key="state", target_return=eval_rtg, rtg_scale=cfg.rtg_scale, normalizer=normalizer)

    eval_rtg = cfg.eval_rtg if cfg.eval_rtg is not None else counters["best_return"]
    handle = PolicyHandle("teacher", cfg.task, cfg.horizon, actor=actor, observation_key="state",
                          target_return=eval_rtg, rtg_scale=cfg.rtg_scale, normalizer=normalizer)
    explore_rtg = cfg.exploration_rtg if cfg.exploration_rtg is not None else eval_rtg
    eval_env = handle.make_env(num_envs=cfg.num_envs, split="eval", parallel=cfg.parallel)
    explore_env = None
    if counters["rounds"] < cfg.online_rounds:
        explore_env = handle.make_env(num_envs=cfg.num_envs, split="train", parallel=cfg.parallel,
                                      target_return=explore_rtg)
    if state is not None:  # after building the envs, so the RNG streams continue exactly
        set_rng_state(state["rng"])
    starting = offline_res = expert_job = offline_job = None
    try:
        # ---------------------------------------------------------------- expert baseline
        if cfg.eval_expert and counters["expert_eval"] is None:
            expert = expert_baseline(run, eval_env, cfg, phases)
            if isinstance(expert, BackgroundEvaluation):
                expert_job = expert
            else:
                counters["expert_eval"] = float(np.mean(expert))

        # ---------------------------------------------------------------- offline pretraining
        history = []
        bar = progress(total=cfg.offline_updates, initial=min(counters["updates"], cfg.offline_updates), desc="offline")
        # the env workers start (spawn, imports) on the core that training leaves idle
        # (with --collector multi_sync these envs only describe the processes' envs: never started)
        starting = start_in_background(*([eval_env, *([explore_env] if explore_env is not None else [])]
                                         if cfg.collector == "sync" else []))
        with phases.phase("offline training"):
            while counters["updates"] < cfg.offline_updates:
                if run.should_stop(counters["updates"]):
                    checkpoint()
                    run.print(f"stopping after {counters['updates']} updates (--stop-after); continue with --resume")
                    return counters
                history.append(updater.step(buffer.sample(cfg.batch_size).to(cfg.device)))
                counters["updates"] += 1
                bar.update(1)
                u = counters["updates"]
                if u % cfg.log_every == 0 or u == cfg.offline_updates:
                    run.log(u, {**mean_metrics(history), "phase": 0})
                    history = []
                if u % cfg.checkpoint_every == 0 and u < cfg.offline_updates:
                    checkpoint()
        bar.close()
        with phases.phase("env worker start (after training)"):  # what training did not hide
            starting.join()
        if counters["offline_eval"] is None:
            if not counters.get("offline_policy_saved"):  # once: a resumed run's actor has moved on
                policy_file(run.dir / "policy_offline.pt")
                counters["offline_policy_saved"] = True
                checkpoint()
            if cfg.background_eval and counters["rounds"] < cfg.online_rounds:
                offline_job = background_evaluation(run.dir / "policy_offline.pt", cfg, phases, "offline teacher")
            else:
                with phases.phase("evaluation (offline teacher)", episodes=cfg.eval_episodes, workers=cfg.num_envs):
                    res = offline_res = evaluate(run, handle, eval_env, cfg, counters["updates"],
                                                 "after offline pretraining")
                counters["offline_eval"] = float(res.final_performance.mean())
                counters["offline_scores"] = res.final_performance.tolist()
                checkpoint()

        # ---------------------------------------------------------------- online fine-tuning
        if counters["rounds"] < cfg.online_rounds:
            run.print(f"online fine-tuning: {cfg.online_rounds} rounds x {cfg.episodes_per_round} episodes, "
                      f"exploration return-to-go {explore_rtg:.3f} (evaluation: {eval_rtg:.3f})")
            updater.set_constant_lr(cfg.online_lr if cfg.online_lr is not None else cfg.lr * cfg.min_lr_fraction)
            try:
                while counters["rounds"] < cfg.online_rounds:
                    with phases.phase("online rollouts", episodes=cfg.episodes_per_round, workers=cfg.num_envs):
                        res = run_episodes(explore_env, handle.make_policy(seed=cfg.seed), cfg.episodes_per_round,
                                           max_steps=cfg.horizon, deterministic=cfg.exploration == "mean",
                                           keep_episodes=True, desc="rollout",
                                           seed=cfg.seed + 1000 * (counters["rounds"] + 1), collector=cfg.collector)
                    actor.train()
                    kept = sum(buffer.add_trajectory(episode_to_trajectory(ep, keys=("state", "action"))) >= 0
                               for ep in (res.episodes if not cfg.offline_control else ()))
                    counters["rounds"] += 1
                    with phases.phase("online updates"):
                        history = [updater.step(buffer.sample(cfg.batch_size).to(cfg.device)) for _ in
                                   progress(range(cfg.updates_per_round), desc=f"round {counters['rounds']}")]
                    counters["updates"] += cfg.updates_per_round
                    run.log(counters["updates"], {**mean_metrics(history), "phase": 1,
                                                  "online/normalized_performance": float(res.final_performance.mean()),
                                                  "online/return": float(res.returns.mean()),
                                                  "online/round": counters["rounds"], "online/kept": kept,
                                                  "online/buffer_online_fraction": buffer.online_fraction})
                    run.print(f"round {counters['rounds']}/{cfg.online_rounds}: rollout normalized performance "
                              f"{res.final_performance.mean():.3f}, return {res.returns.mean():.3f} "
                              f"({kept} kept; buffer {buffer.online_fraction:.0%} online), "
                              f"loss_nll {run.logger.last('train/loss_nll'):.3f}; {res.rate()}")
                    if cfg.eval_every and counters["rounds"] % cfg.eval_every == 0 and counters["rounds"] < cfg.online_rounds:
                        with phases.phase("evaluation (mid-run)", episodes=cfg.eval_episodes, workers=cfg.num_envs):
                            evaluate(run, handle, eval_env, cfg, counters["updates"], f"after round {counters['rounds']}")
                    checkpoint()
                    if run.should_stop(counters["updates"]):
                        run.print(f"stopping after {counters['updates']} updates (--stop-after); continue with --resume")
                        return counters
            finally:
                close_env(explore_env)
                explore_env = None

        if cfg.online_rounds == 0 and offline_res is not None:
            res = offline_res  # no update since: the same policy on the same episodes
        else:
            with phases.phase("evaluation (final teacher)", episodes=cfg.eval_episodes, workers=cfg.num_envs):
                res = evaluate(run, handle, eval_env, cfg, counters["updates"], "after online fine-tuning")
        if offline_job is not None:
            off = finish_background(run, offline_job, phases, cfg, "offline teacher", cfg.offline_updates,
                                    "eval", "after offline pretraining")
            counters["offline_eval"] = float(off.final_performance.mean())
            counters["offline_scores"] = off.final_performance.tolist()
        if expert_job is not None:
            off = finish_background(run, expert_job, phases, cfg, "scripted expert", 0, "eval_expert", "scripted expert")
            write_expert_scores(expert_job.cache_path, expert_job.cache_key, off.final_performance,
                                returns=off.returns, seconds=off.seconds)
            run.print(f"scripted expert's scores cached in {expert_job.cache_path} (later runs of this configuration "
                      f"reuse them)")
            counters["expert_eval"] = float(np.mean(off.final_performance))
    finally:
        for job in (expert_job, offline_job):
            if job is not None and not job.done():
                job.cancel()
        with phases.phase("env worker shutdown"):
            try:
                if starting is not None:  # never hides an error in flight; raises its own otherwise
                    starting.join(raise_error=sys.exc_info()[1] is None)
            finally:
                for env in (eval_env, explore_env):
                    if env is not None:
                        close_env(env)
    final, final_scores = float(res.final_performance.mean()), res.final_performance
    counters["final_eval"] = final
    with phases.phase("files and curves"):
        policy_file(run.dir / "policy.pt")
        checkpoint()
        run.finish(columns=[c for c in ("train/loss_nll", "train/entropy", "online/normalized_performance",
                                        "eval/normalized_performance", "eval_expert/normalized_performance")
                            if c in run.logger.frame().columns])
    summary = {"expert": counters["expert_eval"], "offline": counters["offline_eval"], "online": final}
    ses = {"online": standard_error(final_scores)}
    gain = gain_se = None
    if counters["offline_scores"] is not None:  # None: resumed from a checkpoint of an earlier trakdis
        offline_scores = np.asarray(counters["offline_scores"], dtype=np.float64)
        gain, gain_se = paired_difference(offline_scores, final_scores)
        ses["offline"] = standard_error(offline_scores)
    run.print(f"phases ({'resumed run: earlier parts included; ' if run.resuming else ''}wall and CPU seconds, "
              f"CPU of this process and its env workers):\n" + phases.table(total_wall=time.time() - run.t0))
    phases_file = {"phases": phases.state_dict(), "episodes_simulated": phases.episodes,
                   "wall_seconds_this_process": time.time() - run.t0, "num_envs": cfg.num_envs, "parallel": cfg.parallel,
                   "loadavg": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}
    atomic_write_bytes(run.dir / "phases.json", (json.dumps(phases_file, indent=1) + "\n").encode())
    run.print(f"episodes simulated: {phases.episodes} ("
              + ", ".join(f"{k} {r['episodes']}" for k, r in phases.records.items() if r["episodes"]) + ")")
    run.print("eval normalized performance (mean +- standard error): "
              + ", ".join(f"{k} {v:.3f}" + (f" +- {ses[k]:.3f}" if k in ses else "") for k, v in summary.items()
                          if v is not None)
              + (f"; online - offline {gain:+.3f} +- {gain_se:.3f} (paired: the same {cfg.eval_episodes} eval "
                 f"episodes)" if gain is not None else "") + f"; {time.time() - run.t0:.0f} s")
    return {**counters, **summary, "gain": gain, "gain_se": gain_se, "offline_se": ses.get("offline"),
            "online_se": ses["online"], "episodes_simulated": phases.episodes}


if __name__ == "__main__":
    main(sys.argv[1:])
