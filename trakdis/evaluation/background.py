"""Evaluate a saved policy in a background process that uses only idle CPU.

A recipe that alternates simulation on every core with training on one core leaves a core idle
whenever it trains. :class:`BackgroundEvaluation` plays a policy's evaluation episodes in a
separate process at a lower scheduling priority (``nice``), so that they fill that idle time
instead of adding to the run's wall time, and hands back the same
:class:`~trakdis.evaluation.EpisodeResults` numbers an in-process evaluation would give:
the episodes run in a ``SerialEnv`` of ``num_envs`` environments, which plays the same
configurations as a ``ParallelEnv`` of ``num_envs`` workers with the same ``seed``.

    job = BackgroundEvaluation("expert", task="ClothFold", horizon=100, num_episodes=30,
                               num_envs=2, env_seed=10_000, policy_seed=0)
    ...                     # train meanwhile
    results = job.result()  # waits; raises the worker's error if it failed
"""
from __future__ import annotations

import multiprocessing as mp
import os
import resource
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np
import torch

from trakdis.envs import close_env
from trakdis.policies import load_policy

from .episodes import EpisodeResults, run_episodes

__all__ = ["BackgroundEvaluation"]


def _cpu_seconds() -> float:
    """CPU seconds of this process and its finished children."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _worker(conn, spec: str, kwargs: dict[str, Any]) -> None:
    t0 = time.perf_counter()
    try:
        if kwargs["nice"]:
            os.nice(kwargs["nice"])
        torch.set_num_threads(1)
        handle = load_policy(spec, task=kwargs["task"], horizon=kwargs["horizon"])
        env = handle.make_env(num_envs=kwargs["num_envs"], split=kwargs["split"], parallel=False)
        try:
            res = run_episodes(env, handle.make_policy(seed=kwargs["policy_seed"]), kwargs["num_episodes"],
                               max_steps=handle.horizon, desc=None, seed=kwargs["env_seed"])
        finally:
            close_env(env)
        conn.send({"final_performance": res.final_performance, "returns": res.returns, "lengths": res.lengths,
                   "unstable": res.unstable, "seconds": time.perf_counter() - t0, "cpu": _cpu_seconds()})
    except BaseException as err:  # noqa: BLE001 - handed to the parent, which raises it
        conn.send({"error": f"{type(err).__name__}: {err}\n{traceback.format_exc()}"})
    finally:
        conn.close()


# Not torchrl.collectors.Evaluator(backend="process") (TorchRL 0.14, collectors/_evaluator.py): it
# hands back aggregated float metrics (``metrics_fn -> dict[str, float]``), not the per-episode
# scores that the paired online gain and the expert-score cache need, and has no priority setting.
class BackgroundEvaluation:
    """Play ``num_episodes`` evaluation episodes of a saved policy in a spawned process.

    Args:
        spec: ``"expert"`` or the path of a policy file (what ``load_policy`` reads).
        task, horizon: the task and episode length.
        num_episodes: episodes to play.
        num_envs: environments stepped together (``SerialEnv``: the configurations of an in-process
            evaluation with a ``ParallelEnv`` of as many workers).
        env_seed, policy_seed: the ``seed`` of ``run_episodes`` and of ``make_policy``.
        split: ``"eval"`` or ``"train"``.
        nice: how much lower the process's scheduling priority is (0: the same; 10: it mostly gets
            the CPU time the foreground leaves idle).

    The results come back through a pipe; :meth:`result` waits for them. :attr:`cpu_seconds` and
    :attr:`wall_seconds` are the worker's own (for a recipe's phase table), once it has finished.
    """

    def __init__(self, spec: str | Path, *, task: str, horizon: int, num_episodes: int, num_envs: int = 1,
                 env_seed: int | None = None, policy_seed: int | None = None, split: str = "eval", nice: int = 10):
        if num_episodes < 1:
            raise ValueError(f"num_episodes must be >= 1, got {num_episodes}")
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.spec, self.num_episodes, self.split = str(spec), int(num_episodes), split
        if self.spec != "expert" and not Path(spec).exists():
            raise FileNotFoundError(f"background evaluation: no policy file {self.spec}")
        kwargs = dict(task=task, horizon=horizon, num_episodes=self.num_episodes, num_envs=int(num_envs),
                      env_seed=env_seed, policy_seed=policy_seed, split=split, nice=int(nice))
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_worker, args=(child, self.spec, kwargs), daemon=True,
                                 name=f"background evaluation of {self.spec}")
        self._proc.start()
        child.close()
        self._results = None
        self.cpu_seconds = self.wall_seconds = 0.0

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    def done(self) -> bool:
        """Whether the results are ready (without waiting)."""
        return self._results is not None or self._conn.poll()

    def result(self):
        """The :class:`~trakdis.evaluation.EpisodeResults` (waits for the worker)."""
        if self._results is None:
            try:
                msg = self._conn.recv()
            except EOFError:
                self._proc.join()
                raise RuntimeError(f"the background evaluation of {self.spec} died (exit code "
                                   f"{self._proc.exitcode}) before sending its results") from None
            self._proc.join()
            if "error" in msg:
                raise RuntimeError(f"the background evaluation of {self.spec} failed:\n{msg['error']}")
            self.cpu_seconds, self.wall_seconds = float(msg["cpu"]), float(msg["seconds"])
            self._results = EpisodeResults(
                final_performance=np.asarray(msg["final_performance"]), returns=np.asarray(msg["returns"]),
                lengths=np.asarray(msg["lengths"]), unstable=np.asarray(msg["unstable"]), episodes=[],
                seconds=self.wall_seconds, num_envs=1)
        return self._results

    def cancel(self) -> None:
        """Stop the worker (no results)."""
        if self._proc.is_alive():
            self._proc.terminate()
        self._proc.join()
        self._conn.close()

    def __del__(self):
        proc = getattr(self, "_proc", None)
        if proc is not None and proc.is_alive():
            proc.terminate()
