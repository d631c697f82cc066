"""Evaluate a saved policy (the scripted expert, a teacher or a student) on the eval split.

    python recipes/evaluate.py --policy expert --task ClothFold
    python recipes/evaluate.py --policy runs/online_dt/<name>          # teacher (policy.pt inside)
    python recipes/evaluate.py --policy runs/distill/<name> --noise-levels 0 1e-5 1e-4 1e-3

Runs ``--trials`` episodes (default 100, the paper's count) per acting-noise level (``--noise-levels``) and writes to
``runs/evaluate/<name>/``: ``episodes.csv`` (one row per episode, with where each picker first closed
and whether its corner was lifted: ``trakdis.evaluation.grasp_report``; for a student, the encoder's error
per state group on the states it visited), ``summary.csv`` and
``summary.md`` (mean, std, 25/50/75th percentiles of the normalized performance at the episode's
end) and ``videos/`` (a few extra episodes: large render side by side with the agent's 32x32 view).
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass, replace
from typing import ClassVar, Literal, Optional

import pandas as pd

from trakdis.envs import close_env, task_spec
from trakdis.envs.specs import TaskName
from trakdis.evaluation import CollectorName, episode_frames, grasp_report, run_episodes, summarize, summarize_grasps, write_summary_table
from trakdis.policies import load_policy
from trakdis.utils.limits import MAX_HORIZON, MAX_PARAMS, cap_workers, check_option, check_options
from trakdis.utils.run import Run, RunConfig
from trakdis.utils.video import write_video


@dataclass
class EvaluateConfig(RunConfig):
    """Evaluate a policy: N trials on the eval split, summary table and videos."""

    policy: str = "expert"
    """'expert' (scripted expert) or a policy file / run directory holding policy.pt"""
    task: Optional[TaskName] = None
    """task (required for the expert; a policy file knows its own)"""
    trials: int = 100
    """episodes per noise level (--noise-levels)"""
    first_episode: int = 0
    """play the episodes from this one on (a multiple of --num-envs; noise-free levels only): a part of a longer
    evaluation, its episodes those of the whole one (trakdis.evaluation.chunks joins the parts)"""
    split: Literal["train", "eval"] = "eval"
    """configuration pool of the episodes"""
    horizon: Optional[int] = None
    """episode length (default: the policy's, 100)"""
    noise_levels: tuple[float, ...] = (0.0,)
    """acting noise: Gaussian noise std added to the (estimated) state the policy reads; several values -> one row
    each (the ``state_noise`` column of the tables)"""
    expert_noise: float = 0.0
    """action noise of the scripted expert"""
    target_return: Optional[float] = None
    """initial return-to-go of a DT policy (default: the one saved with it)"""
    hold_radius: Optional[float] = None
    """a student's held-corner radius in metres (PickerOdometry; default: the one saved with it, 0: off); needs a
    student with picker odometry"""
    num_envs: int = 2
    """environments stepped together (batched rollouts)"""
    parallel: bool = False
    """step them in subprocesses (ParallelEnv) instead of in turn (SerialEnv)"""
    collector: CollectorName = "sync"
    """one TorchRL Collector over those envs, a MultiSyncCollector of --num-envs processes, or a RayCollector of
    --num-envs Ray actors (pip install -e ".[ray]"; the cluster of RAY_ADDRESS, else a local Ray)"""
    videos: int = 2
    """extra episodes recorded as videos (0: none)"""
    video_size: int = 192
    """side of the large render in the videos"""
    fps: float = 10.0
    """video frame rate"""
    max_params: int = MAX_PARAMS
    """refuse a policy file whose models have more parameters than this (trakdis.utils.limits; raise it for a
    larger policy you trust)"""
    SAVED_AS: ClassVar[dict] = {"state_noise": "noise_levels"}  # the option's earlier name (--state-noise)

    def __post_init__(self):
        # checked while the command line is parsed, before the run directory exists
        if not self.noise_levels:
            raise ValueError("--noise-levels needs at least one noise level")
        bad = [s for s in self.noise_levels if not (math.isfinite(s) and s >= 0)]
        if bad:
            raise ValueError(f"--noise-levels {bad[0]!r}: every noise level must be a finite std >= 0 "
                             f"(got {list(self.noise_levels)})")
        if self.horizon is not None and self.horizon < 1:
            raise ValueError(f"--horizon {self.horizon}: the episode length must be >= 1 (none: the policy's own)")
        check_options(self, sizes=("trials", "num_envs", "video_size", "max_params"), counts=("videos", "first_episode"),
                      positive=("fps",), nonnegative=("expert_noise",))
        if self.first_episode and (self.first_episode % self.num_envs or any(self.noise_levels)):
            raise ValueError(f"--first-episode {self.first_episode}: a multiple of --num-envs ({self.num_envs}), at "
                             f"noise level 0 only (got {list(self.noise_levels)})")
        if self.horizon is not None:
            check_option("horizon", self.horizon, le=MAX_HORIZON, integer=True)
        if self.hold_radius is not None:
            check_option("hold_radius", self.hold_radius, ge=0, lt=1)
        super().__post_init__()


def main(argv=None) -> pd.DataFrame:
    run = Run.start("evaluate", EvaluateConfig, argv, description=__doc__)
    cfg = run.cfg
    handle = load_policy(cfg.policy, task=cfg.task, horizon=cfg.horizon, expert_noise=cfg.expert_noise, device=cfg.device,
                         max_params=cfg.max_params)
    if cfg.hold_radius is not None:  # the held corner is part of the picker odometry (trakdis.transforms)
        if not (handle.picker_odometry and handle.encoder is not None):
            raise SystemExit(f"--hold-radius {cfg.hold_radius}: {cfg.policy} is no student with picker odometry")
        handle = replace(handle, hold_radius=cfg.hold_radius)
    # no env without an episode (of the whole evaluation, for a part of one: the same envs play the same episodes)
    num_envs = cap_workers(cfg.num_envs, cfg.first_episode + cfg.trials, unit="trials", warn=run.print)
    spec = task_spec(handle.task, horizon=handle.horizon)
    name = handle.kind if handle.kind == "expert" else f"{handle.kind} ({handle.source})"
    run.print(f"evaluating {name} on {handle.task} ({cfg.split} split), {cfg.trials} trials x "
              f"noise levels {list(cfg.noise_levels)}")
    rows, summaries = [], []
    for i, sigma in enumerate(cfg.noise_levels):
        env = handle.make_env(num_envs=num_envs, split=cfg.split, state_noise=sigma, noise_seed=cfg.seed + 7919,
                              parallel=cfg.parallel, target_return=cfg.target_return)
        grasps, errors = [], []  # where each episode's pickers first closed (trakdis.evaluation.grasps)

        def on_episode(ep):
            grasps.append(grasp_report(handle.task, ep))
            if handle.uses_pixels and "state_estimate" in ep.keys():  # the encoder's error on the states visited
                err = spec.state_error_cm((ep["state_estimate"] - ep["state"]).abs())
                errors.append({f"encoder_{k}": v for k, v in err.items() if k != "mae"})

        try:  # the same configurations for every noise level (and every policy evaluated with this seed)
            res = run_episodes(env, handle.make_policy(seed=cfg.seed), cfg.trials, max_steps=handle.horizon,
                               desc=f"sigma={sigma:g}", seed=cfg.seed, on_episode=on_episode,
                               skip_batches=cfg.first_episode // num_envs, collector=cfg.collector)
        finally:
            close_env(env)
        for k in range(len(res.final_performance)):
            rows.append({"state_noise": sigma, "episode": cfg.first_episode + k, "final_normalized_performance": res.final_performance[k],
                         "return": res.returns[k], "length": int(res.lengths[k]), "sim_unstable": bool(res.unstable[k]),
                         **(grasps[k] or {}), **(errors[k] if errors else {})})
        s = summarize(res.final_performance)
        summaries.append({"task": handle.task, "policy": handle.kind, "state_noise": sigma, **s,
                          "unstable": int(res.unstable.sum())})
        run.log(i, {"eval/state_noise": sigma, "eval/normalized_performance": s["mean"], "eval/std": s["std"]})
        run.print(f"sigma={sigma:g}: normalized performance {s['mean']:.3f} +- {s['std']:.3f} "
                  f"(p25 {s['p25']:.3f}, p50 {s['p50']:.3f}, p75 {s['p75']:.3f}; {s['n']} trials)")
        if all(g is not None for g in grasps):
            run.print(f"sigma={sigma:g}: {summarize_grasps(handle.task, grasps)}")
        if errors:
            run.print(f"sigma={sigma:g}: encoder error on the visited states (mean over episodes): " + ", ".join(
                f"{k.removeprefix('encoder_').removesuffix('_cm')} {sum(e[k] for e in errors) / len(errors):.2f} cm"
                for k in errors[0]))
    pd.DataFrame(rows).to_csv(run.dir / "episodes.csv", index=False)
    frame = write_summary_table(summaries, run.dir / "summary.csv", run.dir / "summary.md",
                                columns=("task", "policy", "state_noise", "n", "mean", "std", "p25", "p50", "p75"))
    if cfg.videos > 0:
        env = handle.make_env(num_envs=1, split=cfg.split, state_noise=cfg.noise_levels[0],
                              target_return=cfg.target_return, video_size=cfg.video_size)
        try:
            res = run_episodes(env, handle.make_policy(seed=cfg.seed), cfg.videos, max_steps=handle.horizon,
                               keep_episodes=True, desc="videos", seed=cfg.seed + 100_000)
        finally:
            close_env(env)
        for k, ep in enumerate(res.episodes):
            path = write_video(run.dir / "videos" / f"{handle.task}_{handle.kind}_{k}.mp4",
                               episode_frames(ep, label=handle.kind), fps=cfg.fps)
            run.print(f"video: {path} (final normalized performance {res.final_performance[k]:.3f})")
    run.finish()
    print(open(run.dir / "summary.md").read())
    return frame


if __name__ == "__main__":
    main(sys.argv[1:])
