"""Batched environments: ``SerialEnv``/``ParallelEnv`` of :func:`~trakdis.envs.make_env` instances,
a ``ParallelEnv`` that waits for its workers without taking a core from them, closing them without
TorchRL's side effect on the thread count, and starting their worker processes in the background.
"""
from __future__ import annotations

import functools
import sys
import threading
import time
import warnings
from typing import Any, Mapping

import torch
from torchrl.envs import ParallelEnv, SerialEnv

from trakdis.envs.torchrl_env import make_env

__all__ = ["SleepWaitParallelEnv", "close_env", "make_batched_env", "start_in_background"]


class SleepWaitParallelEnv(ParallelEnv):
    """TorchRL's ``ParallelEnv`` with shared-memory buffers, whose main process sleeps while it waits
    for the workers instead of spinning.

    Own code because TorchRL 0.14's two modes both cost a small machine CPU time at every step
    (``torchrl/envs/batched_envs.py``): with ``use_buffers=True`` ``_wait_for_workers`` spin-polls the
    workers' shared done flags and keeps a core busy that the workers need when there are no more
    cores than workers; with ``use_buffers=False`` every step pickles the tensordicts through the
    pipes (a socket and a file descriptor per tensor, on both sides). This keeps the shared buffers
    and TorchRL's flags, and checks them every ``poll_interval`` seconds (default 0.5 ms, against
    tens of milliseconds per cloth step). Arguments and results are ``ParallelEnv``'s; the default
    is ``use_buffers=True`` (with ``False`` TorchRL's own pipe wait, which blocks, is used).
    """

    def __init__(self, *args, poll_interval: float = 5e-4, **kwargs):
        if poll_interval <= 0:
            raise ValueError(f"poll_interval must be > 0 seconds, got {poll_interval}")
        kwargs.setdefault("use_buffers", True)
        super().__init__(*args, **kwargs)
        self.poll_interval = float(poll_interval)

    def _wait_for_workers(self, workers_range) -> None:
        if not self._use_buffers:
            return super()._wait_for_workers(workers_range)
        flags, index = self._shm_done_flags, self._worker_indices
        workers = list(workers_range)
        deadline = time.monotonic() + self.BATCHED_PIPE_TIMEOUT
        polls = 0
        while not all(flags[index[i]] for i in workers):
            time.sleep(self.poll_interval)
            polls += 1
            if polls % 200 == 0:  # about every 0.1 s: a dead worker or a timeout, as TorchRL checks them
                for i in workers:
                    if not flags[index[i]] and not self._workers[i].is_alive():
                        try:
                            self._shutdown_workers()
                        finally:
                            raise RuntimeError(f"Cannot proceed, worker {i} dead.")
                if time.monotonic() > deadline:
                    raise RuntimeError(
                        f"Failed to run all workers within the {self.BATCHED_PIPE_TIMEOUT} sec time limit. This "
                        "threshold can be increased via the BATCHED_PIPE_TIMEOUT env variable.")
        for i in workers:
            flags[index[i]] = 0


def close_env(env) -> None:
    """``env.close()`` without TorchRL's side effect on the thread count, safe in a ``finally``.

    TorchRL 0.14's ``BatchedEnvBase.close`` (``SerialEnv``/``ParallelEnv``) raises torch's intra-op
    thread count to ``min(initial, current + num_workers)``, even for a ``SerialEnv`` that never
    lowered it. Measured here: with 1 thread requested and a 2-env ``SerialEnv`` closed, the next
    DT updates ran ~10x slower on a loaded 2-core machine (OpenMP threads spinning in libgomp).

    Closing never hides the error that led to it: an env that is already closed, or never started
    (TorchRL starts batched envs at their first reset, and ``close()`` on one raises "trying to
    close a closed environment"), is skipped; and when ``close()`` fails while another exception is
    propagating (``close_env`` in a ``finally``), its failure is only warned about, so the original
    exception, Ctrl-C included, is the one raised.
    """
    if getattr(env, "is_closed", False):
        return
    in_flight = sys.exc_info()[1]
    threads = torch.get_num_threads()
    try:
        env.close()
    except Exception as err:
        if in_flight is None:
            raise
        warnings.warn(f"close_env: closing {type(env).__name__} failed ({type(err).__name__}: {err}) while "
                      f"{type(in_flight).__name__} was being raised; raising that one", RuntimeWarning, stacklevel=2)
    finally:
        torch.set_num_threads(threads)


class start_in_background:
    """Start the worker processes of ``ParallelEnv`` s (bare or inside a ``TransformedEnv``) in a
    thread, while this process goes on with something else, e.g. training on its own core.

    TorchRL starts a ``ParallelEnv``'s workers lazily, at its first reset, and then waits for each
    to import torch, TorchRL and MuJoCo (spawned processes: about 6 CPU seconds a worker here). This
    calls TorchRL's own ``start()`` earlier, from a thread (TorchRL has no non-blocking start); the
    envs are otherwise untouched. ``join()`` (also on exit of a ``with`` block) waits for it and
    re-raises a failure; call it before using or closing the envs."""

    def __init__(self, *envs):
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._start, args=(envs,), name="trakdis-env-start", daemon=True)
        self._thread.start()

    def _start(self, envs) -> None:
        try:
            for env in envs:
                base = getattr(env, "base_env", env)
                if isinstance(base, ParallelEnv) and base.is_closed:
                    base.start()
        except BaseException as err:  # re-raised by join(), in the caller's thread
            self.error = err

    def join(self, raise_error: bool = True) -> None:
        self._thread.join()
        if self.error is not None and raise_error:
            err, self.error = self.error, None
            raise err

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.join()


def make_batched_env(task: str, *, num_envs: int = 1, parallel: bool = False, seed: int | None = None,
                     split: str = "train", from_pixels: bool = False, image_size: int = 32,
                     env_kwargs: Mapping[str, Any] | None = None):
    """``SerialEnv``/``ParallelEnv`` of ``num_envs`` :func:`trakdis.envs.make_env` instances (batch ``[num_envs]``)."""
    if num_envs < 1:
        raise ValueError(f"num_envs must be >= 1, got {num_envs}")
    factory = functools.partial(make_env, task, from_pixels=from_pixels, image_size=image_size, split=split,
                                **dict(env_kwargs or {}))
    cls = SleepWaitParallelEnv if parallel and num_envs > 1 else SerialEnv
    # spawn: forking a process that already holds a GL context hangs its children
    kwargs = {"mp_start_method": "spawn"} if cls is SleepWaitParallelEnv else {}
    env = cls(num_envs, factory, **kwargs)
    if seed is not None:
        env.set_seed(seed)
    return env
