"""A run's evaluation protocol: which episodes every evaluation of a run plays, and how their scores
reach the run's CSV log and output (written once for every recipe).

    evals = EvalProtocol("ClothFold", horizon=100, episodes=30, num_envs=2, seed=10_000, policy_seed=0)
    res = evals.run(run, handle, env, step=1500, tag="after offline pretraining")   # logs eval/*
    expert = evals.expert_baseline(run, env, phases, cache_root="datasets")          # cached, or measured
    job = evals.in_background("runs/x/policy_offline.pt", phases)                    # beside training
    res = evals.finish_background(run, job, phases, "offline teacher", step=1500, tag="...")

A recipe that evaluates now or beside training, as its options say, lets the protocol keep the
background jobs and finish them at the end; :class:`RunEnvs` owns the envs and those jobs::

    with RunEnvs(phases, eval_env, explore_env, evals=evals) as envs:     # closed/cancelled on exit
        evals.expert_scores(run, eval_env, phases, cache_root="datasets", background=True, on_scores=...)
        envs.start_workers()                                               # beside training
        ...                                                                # train
        envs.join_workers()
        evals.evaluate(run, handle, eval_env, phases, "offline teacher", step=1500, tag="...",
                       background="runs/x/policy_offline.pt", on_scores=...)
        ...
        evals.finish_pending(run, phases)                                  # logs, calls on_scores

Every evaluation replays the same configurations (the same ``seed``): a run's scores are
comparable, and the difference of two policies' scores is a paired one.
"""
from __future__ import annotations

import contextlib
import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import nn

from trakdis.envs import close_env, start_in_background
from trakdis.policies import load_policy
from trakdis.utils.limits import cap_workers, check_option
from trakdis.utils.phases import PhaseTimer, available_workers

from .background import BackgroundEvaluation
from .episodes import CollectorName, EpisodeResults, paired_difference, run_episodes, standard_error, summarize
from .expert_scores import expert_score_key, expert_score_path, read_expert_scores, write_expert_scores

__all__ = ["EvalConfig", "EvalProtocol", "RunEnvs", "compare_scores", "log_scores"]


def log_scores(run: Any, step: int, prefix: str, tag: str, scores: Sequence[float] | np.ndarray,
               returns: Sequence[float] | np.ndarray | None = None, *, detail: str = "", note: str = "",
               extra: dict[str, float] | None = None, split: str = "eval") -> dict[str, float]:
    """Log ``<prefix>/normalized_performance`` and ``<prefix>/std`` (and ``<prefix>/return``, the
    mean of ``returns``, when given; and ``extra``) at ``step`` in ``run``'s log, and print one line.

    With ``returns`` the line reads ``"<tag>: normalized performance m +- s (std; standard error e;
    return r, n eval episodes); <detail>"``; without, ``"<tag>: normalized performance m +- s (n eval
    episodes<note>)"`` (``split`` names the episodes). ``run`` is a :class:`~trakdis.utils.run.Run`
    (``log``, ``print``)."""
    s = summarize(scores)
    metrics = {f"{prefix}/normalized_performance": s["mean"], f"{prefix}/std": s["std"]}
    if returns is not None:
        metrics[f"{prefix}/return"] = float(np.mean(returns))
    metrics.update(extra or {})
    run.log(step, metrics)
    if returns is not None:
        run.print(f"{tag}: normalized performance {s['mean']:.3f} +- {s['std']:.3f} (std; standard error "
                  f"{standard_error(scores):.3f}; return {np.mean(returns):.3f}, {s['n']} {split} episodes)"
                  + (f"; {detail}" if detail else ""))
    else:
        run.print(f"{tag}: normalized performance {s['mean']:.3f} +- {s['std']:.3f} ({s['n']} {split} episodes{note})")
    return metrics


def compare_scores(means: dict[str, float | None], scores: dict[str, Any], *, before: str, after: str) -> tuple[str, dict]:
    """One line of mean scores (``"expert 0.830, offline 0.533 +- 0.104, online 0.727 +- 0.047; online
    - offline +0.194 +- 0.118 (paired: the same 30 eval episodes)"``) and its numbers: ``gain``,
    ``gain_se`` (the paired difference ``after - before``, None without both score arrays) and
    ``<name>_se`` (standard error; None without scores) for each name of ``scores``. ``means``: name -> mean (None: left
    out); ``scores``: name -> per-episode scores of the same episodes (None: unknown)."""
    ses = {k: None if v is None else standard_error(np.asarray(v, dtype=np.float64)) for k, v in scores.items()}
    gain = gain_se = None
    if scores.get(before) is not None and scores.get(after) is not None:
        gain, gain_se = paired_difference(np.asarray(scores[before], dtype=np.float64), scores[after])
    line = ", ".join(f"{k} {v:.3f}" + (f" +- {ses[k]:.3f}" if ses.get(k) is not None else "") for k, v in means.items()
                     if v is not None)
    if gain is not None:
        line += (f"; {after} - {before} {gain:+.3f} +- {gain_se:.3f} (paired: the same "
                 f"{len(scores[after])} eval episodes)")
    return line, {"gain": gain, "gain_se": gain_se, **{f"{k}_se": v for k, v in ses.items()}}


@dataclass
class EvalProtocol:
    """The evaluation episodes of a run: ``episodes`` episodes of ``task`` (eval split, ``horizon``
    steps, mean actions) on ``num_envs`` environments reseeded with ``seed`` before each
    evaluation; the acting policy is made with ``policy_seed``."""

    task: str
    horizon: int
    episodes: int
    num_envs: int = 1
    seed: int = 10_000
    policy_seed: int | None = None
    log_returns: bool = True
    """log and print the mean return beside the scores (:func:`log_scores` with ``returns``)"""
    collector: str = "sync"
    """how :func:`~trakdis.evaluation.run_episodes` steps the envs (``"sync"``, ``"multi_sync"`` or ``"ray"``)"""
    _pending: list = field(default_factory=list, init=False, repr=False, compare=False)

    def run(self, run: Any, handle: Any, env: Any, *, step: int, tag: str, prefix: str = "eval",
            keep_mode: nn.Module | None = None, state_error_cm: Callable[[Any], dict] | None = None,
            desc: str | None = None, episodes: int | None = None, split: str = "eval") -> EpisodeResults:
        """Play the episodes of ``handle`` (a :class:`~trakdis.policies.PolicyHandle`) in ``env`` and
        log them (:func:`log_scores`; ``split``: the pool of ``env``'s configurations, as the line
        names them); ``episodes``: only the first so many (default: all).
        ``keep_mode``: a module whose train/eval mode is restored afterwards (default: the handle's
        actor). ``state_error_cm`` (a task spec's): also log the encoder's error on the visited
        states, ``<prefix>/encoder_<group>``, for a policy reading images."""
        keep_mode = handle.actor if keep_mode is None else keep_mode
        was_training = keep_mode.training if keep_mode is not None else False
        errors = state_error_cm is not None and handle.uses_pixels
        episodes = self.episodes if episodes is None else episodes
        res = run_episodes(env, handle.make_policy(seed=self.policy_seed), episodes, max_steps=self.horizon,
                           desc=desc if desc is not None else f"eval ({tag})", seed=self.seed, keep_episodes=errors,
                           collector=self.collector)
        if keep_mode is not None:
            keep_mode.train(was_training)
        extra, note = {}, ""
        if errors:
            err = torch.cat([(ep["state_estimate"] - ep["state"]).abs() for ep in res.episodes])
            extra = {f"{prefix}/encoder_{k}": v for k, v in state_error_cm(err).items()}
            note = (f"; encoder error corners {extra[f'{prefix}/encoder_corners_cm']:.2f} cm, pickers "
                    f"{extra[f'{prefix}/encoder_pickers_cm']:.2f} cm")
        log_scores(run, step, prefix, tag, res.final_performance, res.returns if self.log_returns else None,
                   detail=res.rate(), note=note, extra=extra, split=split)
        return res

    def run_snapshot(self, run: Any, handle: Any, *, step: int, tag: str, prefix: str = "eval", parallel: bool = False,
                     keep_mode: nn.Module | None = None, state_error_cm: Callable[[Any], dict] | None = None,
                     desc: str = "eval") -> EpisodeResults:
        """:meth:`run` on a fresh env that runs a frozen copy of ``handle.encoder`` if it has one (an
        image policy in training: the env's ``EncoderTransform`` freezes what it is given, and a
        ``ParallelEnv`` would pickle it), closed afterwards."""
        encoder = None if handle.encoder is None else copy.deepcopy(handle.encoder).eval()
        snapshot = dataclasses.replace(handle, encoder=encoder)
        env = snapshot.make_env(num_envs=self.num_envs, split="eval", parallel=parallel)
        try:
            return self.run(run, snapshot, env, step=step, tag=tag, prefix=prefix, keep_mode=keep_mode,
                            state_error_cm=state_error_cm, desc=desc)
        finally:
            close_env(env)

    # ------------------------------------------------------------------ background evaluations
    def in_background(self, spec: str | Path, phases: PhaseTimer, episodes: int | None = None, *,
                      seed: int | None = None, split: str = "eval") -> BackgroundEvaluation:
        """These episodes (the first ``episodes`` of them) of the policy file ``spec`` (or ``"expert"``)
        in a background process at low priority, left out of ``phases`` until :meth:`finish_background`
        books it; ``seed`` and ``split`` (default: this protocol's) for other episodes."""
        episodes = self.episodes if episodes is None else episodes
        job = BackgroundEvaluation(spec, task=self.task, horizon=self.horizon, num_episodes=episodes,
                                   num_envs=self.num_envs, env_seed=self.seed if seed is None else seed,
                                   policy_seed=self.policy_seed, split=split)
        phases.exclude(job.pid)
        return job

    def finish_background(self, run: Any, job: BackgroundEvaluation, phases: PhaseTimer, what: str, *, step: int,
                          tag: str, prefix: str = "eval") -> EpisodeResults:
        """Wait for ``job``, book its time in ``phases`` and log its scores at ``step``; a job of
        :meth:`expert_baseline` also writes the expert's score cache."""
        with phases.phase(f"waiting for the background evaluation ({what})"):
            res = job.result()  # its CPU seconds join RUSAGE_CHILDREN here: booked to its own row at once
            phases.add_background(f"evaluation ({what}, background)", job.pid, episodes=job.num_episodes,
                                  wall=job.wall_seconds, cpu=job.cpu_seconds, workers=1)
        log_scores(run, step, prefix, tag, res.final_performance, res.returns,
                   detail=f"{job.num_episodes} episodes in {job.wall_seconds:.0f} s in a background process",
                   split=job.split)
        if getattr(job, "cache_path", None) is not None:
            self._cache(run, job.cache_path, job.cache_key, res)
        return res

    def scores_in_background(self, run: Any, spec: str | Path, phases: PhaseTimer, what: str, *, step: int,
                             episodes: int, seed: int, split: str = "train",
                             prefix: str = "selection") -> Callable[[], np.ndarray]:
        """``episodes`` episodes of the policy file ``spec`` on ``split`` (reseeded with ``seed``, not
        this protocol's) in a background process; returns a function that waits for them,
        books and logs them (:meth:`finish_background`, ``<prefix>/*`` at ``step``) and returns the
        per-episode scores. For choosing among policies on episodes the evaluation never plays."""
        job = self.in_background(spec, phases, episodes, seed=seed, split=split)
        return lambda: self.finish_background(run, job, phases, what, step=step, tag=what,
                                              prefix=prefix).final_performance

    def evaluate(self, run: Any, handle: Any, env: Any, phases: PhaseTimer, what: str, *, step: int, tag: str,
                 background: str | Path | None = None, background_step: int | None = None,
                 on_scores: Callable[[np.ndarray], Any] | None = None) -> EpisodeResults | None:
        """:meth:`run` as the phase ``"evaluation (<what>)"`` of ``phases``; ``on_scores`` receives the
        per-episode scores. With ``background`` (the policy's file), the episodes run in a background
        process instead (:meth:`in_background`; returns None) and :meth:`finish_pending` logs them
        at ``background_step`` (default: ``step``) and calls ``on_scores``. A protocol of 0 episodes
        evaluates nothing (returns None; ``on_scores`` is not called)."""
        if self.episodes == 0:
            return None
        if background is not None:
            job = self.in_background(background, phases)
            self._pending.append((job, what, step if background_step is None else background_step, tag, "eval", on_scores))
            return None
        with phases.phase(f"evaluation ({what})", episodes=self.episodes, workers=self.num_envs):
            res = self.run(run, handle, env, step=step, tag=tag)
        if on_scores is not None:
            on_scores(res.final_performance)
        return res

    def finish_pending(self, run: Any, phases: PhaseTimer) -> None:
        """:meth:`finish_background` for the jobs of :meth:`evaluate` and :meth:`expert_scores` still
        pending, the latest first, each followed by its ``on_scores``."""
        while self._pending:
            job, what, step, tag, prefix, on_scores = self._pending.pop()
            res = self.finish_background(run, job, phases, what, step=step, tag=tag, prefix=prefix)
            if on_scores is not None:
                on_scores(res.final_performance)

    def cancel_pending(self) -> None:
        """Stop the pending background jobs (their scores are lost)."""
        while self._pending:
            job = self._pending.pop()[0]
            if not job.done():
                job.cancel()

    # ------------------------------------------------------------------ the scripted expert
    def expert_scores(self, run: Any, env: Any, phases: PhaseTimer, *, cache_root: str | Path, use_cache: bool = True,
                      background: bool = False, episodes: int | None = None,
                      on_scores: Callable[[np.ndarray], Any] | None = None) -> None:
        """:meth:`expert_baseline`, its scores passed to ``on_scores``: now, or (measured in the
        background) by :meth:`finish_pending`; nothing for 0 episodes."""
        if min(self.episodes, self.episodes if episodes is None else episodes) == 0:
            return
        scores = self.expert_baseline(run, env, phases, cache_root=cache_root, use_cache=use_cache, background=background,
                                      episodes=episodes)
        if isinstance(scores, BackgroundEvaluation):
            self._pending.append((scores, "scripted expert", 0, "scripted expert", "eval_expert", on_scores))
        elif on_scores is not None:
            on_scores(scores)

    def expert_baseline(self, run: Any, env: Any, phases: PhaseTimer, *, cache_root: str | Path,
                        use_cache: bool = True, background: bool = False,
                        episodes: int | None = None) -> np.ndarray | BackgroundEvaluation:
        """The scripted expert's scores on these episodes (the first ``episodes`` of them: the same
        configurations as the first ``episodes`` of every evaluation), logged under ``eval_expert/``
        at step 0: read from the cache under ``cache_root`` (``use_cache``), or measured and cached.
        Measured with ``background``: returns a :class:`BackgroundEvaluation` for
        :meth:`finish_background` (which caches it); else on ``env`` (a DT policy's eval env: the
        expert ignores its return-to-go)."""
        episodes = self.episodes if episodes is None else min(episodes, self.episodes)
        key = expert_score_key(task=self.task, split="eval", horizon=self.horizon, episodes=episodes,
                               seed=self.seed, num_envs=self.num_envs)
        path = expert_score_path(cache_root, key)
        cached = read_expert_scores(path, key) if use_cache else None
        if cached is not None:
            scores, returns = cached
            log_scores(run, 0, "eval_expert", "scripted expert", scores, returns,
                       detail=f"measured once, cached in {path}")
            return scores
        if background:
            job = self.in_background("expert", phases, episodes=episodes)
            job.cache_path, job.cache_key = path, key
            return job
        expert = load_policy("expert", task=self.task, horizon=self.horizon)
        with phases.phase("expert evaluation", episodes=episodes, workers=self.num_envs):
            res = self.run(run, expert, env, step=0, tag="scripted expert", prefix="eval_expert", episodes=episodes)
        self._cache(run, path, key, res)
        return res.final_performance

    @staticmethod
    def _cache(run: Any, path: Path, key: dict, res: EpisodeResults) -> None:
        write_expert_scores(path, key, res.final_performance, returns=res.returns, seconds=res.seconds)
        run.print(f"scripted expert's scores cached in {path} (later runs of this configuration reuse them)")


@dataclass
class EvalConfig:
    """Evaluation and env options of a recipe that evaluates a policy and rolls episodes out (a base
    of its config dataclass, so the flags stay ``--eval-episodes``, ``--num-envs``, ...; a recipe
    redeclares a field to change its default)."""

    eval_episodes: int = 30
    """evaluation episodes (eval split, the same configurations every time; 0: none)"""
    eval_every: int = 0
    """also evaluate every N rounds (0: only before the rounds and at the end)"""
    num_envs: int = field(default_factory=available_workers)
    """envs stepped together, for evaluations and rollouts (default: the cores, at most 2)"""
    parallel: bool = True
    """step them in worker processes (ParallelEnv; --no-parallel: in turn, the same numbers)"""
    collector: CollectorName = "sync"
    """one TorchRL Collector over the batched env, a MultiSyncCollector of --num-envs processes, or a RayCollector
    of --num-envs Ray actors (pip install -e ".[ray]"; the cluster of RAY_ADDRESS, else a local Ray)"""

    def __post_init__(self):  # while parsing (tyro), before the run directory exists
        check_option("eval_episodes", self.eval_episodes, ge=0, integer=True)
        check_option("eval_every", self.eval_every, ge=0, integer=True)
        check_option("num_envs", self.num_envs, ge=1, integer=True)
        # no more envs (worker processes with --parallel) than cores: the recipes' episode counts vary by use
        self.num_envs = cap_workers(self.num_envs, self.num_envs, unit="envs")
        parent = getattr(super(), "__post_init__", None)
        if parent is not None:
            parent()

    def eval_protocol(self, task: str, horizon: int, *, seed: int, **kwargs: Any) -> EvalProtocol:
        """The run's :class:`EvalProtocol`: these episodes, reseeded with ``seed + 10_000`` (the eval
        configurations of every recipe run with ``--seed seed``); ``kwargs``: its other fields."""
        return EvalProtocol(task, horizon, self.eval_episodes, self.num_envs, seed=seed + 10_000,
                            collector=self.collector, **kwargs)

    def make_env(self, handle: Any, split: str = "eval", **kwargs: Any) -> Any:
        """``handle``'s batched env of ``split`` with these options (``kwargs``: the other arguments of
        :meth:`~trakdis.policies.PolicyHandle.make_env`); for the eval split, None when
        ``eval_episodes`` is 0 (nothing to evaluate)."""
        if split == "eval" and not self.eval_episodes:
            return None
        return handle.make_env(num_envs=self.num_envs, split=split, parallel=self.parallel, **kwargs)


class RunEnvs:
    """The envs of a run's evaluations and rollouts (``None`` s are skipped), and the background jobs
    pending in ``evals``, owned for a ``with`` block: :meth:`start_workers` starts their worker
    processes in a thread (beside training), :meth:`join_workers` waits for them as the phase ``"env
    worker start (after training)"``, :meth:`close` closes one early; on exit the pending jobs are
    cancelled and the envs closed, in order, as the phase ``"env worker shutdown"`` (a failed start is
    raised there unless another error is in flight). ``phases`` None: a run that times no phases."""

    def __init__(self, phases: PhaseTimer | None, *envs: Any, evals: EvalProtocol | None = None):
        self.phases, self.evals = phases, evals
        self.envs = [env for env in envs if env is not None]
        self._starting = None

    def _phase(self, name: str) -> Any:
        return contextlib.nullcontext() if self.phases is None else self.phases.phase(name)

    def start_workers(self, start: bool = True) -> None:
        """Start the envs' workers in a thread (``start=False``: none, e.g. envs that only describe
        a collector's; :meth:`join_workers` is still timed)."""
        self._starting = start_in_background(*(self.envs if start else ()))

    def join_workers(self) -> None:
        """Wait for :meth:`start_workers` (what training did not hide), raising a failure."""
        with self._phase("env worker start (after training)"):
            self._starting.join()

    def close(self, env: Any) -> None:
        """Close ``env`` now (if owned)."""
        if any(owned is env for owned in self.envs):
            self.envs = [owned for owned in self.envs if owned is not env]
            close_env(env)

    def __enter__(self) -> "RunEnvs":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self.evals is not None:
            self.evals.cancel_pending()
        with self._phase("env worker shutdown"):
            try:
                if self._starting is not None:  # never hides an error in flight; raises its own otherwise
                    self._starting.join(raise_error=exc is None)
            finally:
                for env in self.envs:
                    close_env(env)
