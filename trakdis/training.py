"""The update loops of the recipes: ``updater`` steps on sampled batches until a counter reaches
its total, with the log, checkpoint and ``--stop-after`` cadence written once
(:func:`train_updates`), the same for several candidates from independent initialisations of which
the best on a score is kept (:func:`train_candidates`), a round's updates (:func:`run_updates`), the
episodes each acting policy plays in a round of DAgger's mixture (:func:`mixture_shares`), one epoch's shuffled minibatches of a
dataset (:func:`shuffled_batches`), one epoch of plain optimiser steps on them (:func:`train_epoch`)
and a validation pass over a dataset in batches (:func:`eval_batches`).

    done = train_updates(run, updater, lambda: buffer.sample(64), state=state, total=1500,
                         log_every=50, checkpoint_every=500)
    if not done:        # --stop-after: checkpoint written, continue with --resume
        return
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence, TypeVar

import numpy as np
import torch
from tensordict import TensorDictBase
from torch import nn

from trakdis.optim import Updater, mean_metrics
from trakdis.utils.checkpoint import load_checkpoint, save_checkpoint
from trakdis.utils.phases import PhaseTimer
from trakdis.utils.progress import progress
from trakdis.utils.run import Run, RunState

__all__ = ["eval_batches", "mixture_shares", "run_updates", "shuffled_batches", "train_candidates", "train_epoch",
           "train_updates"]

T = TypeVar("T")


def train_updates(run: Run, updater: Updater, sample: Callable[[], TensorDictBase], *, state: RunState, total: int,
                  log_every: int, checkpoint_every: int, key: str = "updates", log_extra: Mapping[str, Any] | None = None,
                  on_log: Callable[[int], None] | None = None, on_update: Callable[[int], None] | None = None,
                  desc: str = "updates") -> bool:
    """Step ``updater`` on ``sample()`` until ``state[key]`` reaches ``total``.

    Every ``log_every`` updates (and at the last) the mean metrics since the previous row are logged
    (``train/*``, with ``log_extra``) and ``on_log(updates)`` is called; ``on_update(updates)`` after
    every update (an evaluation cadence); ``state.save()`` every ``checkpoint_every`` updates before
    the last. Returns False when the run's ``--stop-after`` stopped it (checkpoint written, message
    printed), True once ``total`` is reached."""
    history = []
    bar = progress(total=total, initial=min(state[key], total), desc=desc)
    while state[key] < total:
        if run.should_stop(state[key]):
            state.save()
            run.print(f"stopping after {state[key]} updates (--stop-after); continue with --resume")
            return False
        history.append(updater.step(sample()))
        state[key] += 1
        bar.update(1)
        u = state[key]
        if u % log_every == 0 or u == total:
            run.log(u, {**mean_metrics(history), **(log_extra or {})})
            history = []
            if on_log is not None:
                on_log(u)
        if on_update is not None:
            on_update(u)
        if u % checkpoint_every == 0 and u < total:
            state.save()
    bar.close()
    return True


def train_candidates(run: Run, updater: Updater, sample: Callable[[], TensorDictBase], *, state: RunState,
                     phases: PhaseTimer, candidates: int, total: int, fresh_state: Callable[[int], Mapping[str, Any]],
                     save_policy: Callable[[Path], Any], score: Callable[[Path, int], Callable[[], Sequence[float]]],
                     log_every: int, checkpoint_every: int, key: str = "updates", desc: str = "offline",
                     log_extra: Mapping[str, Any] | None = None, phase: str = "offline training") -> bool:
    """:func:`train_updates` for ``candidates`` models in turn, each ``total`` updates from its own
    initialisation, leaving ``updater`` with the one whose ``score`` is the highest (the first on ties).

    Candidate 0 trains from ``updater`` as it is (with ``candidates=1`` this is :func:`train_updates`
    inside ``phases.phase(phase)``, nothing more); candidate ``k >= 1`` from ``fresh_state(k)`` (the
    updater's ``state_dict`` for a new initialisation: model, optimiser and schedule). Candidate ``k``'s
    updates are counted from ``k * total`` in ``state[key]``, so that the log holds one curve per
    candidate in turn (``log_extra`` gains ``"candidate": k``). Each finished candidate's policy file
    (``save_policy(path)``) and updater state go to ``<run dir>/candidates/``, and ``score(path, k)``
    starts scoring it (a background process, on the core training leaves idle) and returns a function
    that waits for its per-episode scores. ``state`` holds ``"candidate"`` (the one in training) and
    ``"candidate_scores"`` (one mean per candidate, None until scored); a resumed run scores again what
    a kill left unscored. Returns False when ``--stop-after`` stopped it, True once one is kept
    (``state["candidate_kept"]``)."""
    if candidates < 1:
        raise ValueError(f"candidates must be >= 1, got {candidates}")
    if candidates == 1:
        with phases.phase(phase):
            return train_updates(run, updater, sample, state=state, total=total, log_every=log_every, key=key,
                                 checkpoint_every=checkpoint_every, log_extra=log_extra, desc=desc)
    directory = run.dir / "candidates"
    state.setdefault("candidate", 0)
    scores = state.setdefault("candidate_scores", [None] * candidates)
    if len(scores) != candidates:
        raise ValueError(f"this run was started with {len(scores)} candidates, not {candidates}")
    waits = {k: score(directory / f"policy_{k}.pt", k) for k in range(state["candidate"]) if scores[k] is None}
    while state["candidate"] < candidates:
        k = state["candidate"]
        with phases.phase(phase):
            if not train_updates(run, updater, sample, state=state, total=(k + 1) * total, log_every=log_every, key=key,
                                 checkpoint_every=checkpoint_every, log_extra={**(log_extra or {}), "candidate": k},
                                 desc=f"{desc} {k + 1}/{candidates}"):
                return False
            directory.mkdir(exist_ok=True)
            save_policy(directory / f"policy_{k}.pt")
            save_checkpoint(directory / f"updater_{k}.pt", {"updater": updater.state_dict()})
            waits[k] = score(directory / f"policy_{k}.pt", k)
            state["candidate"] = k + 1
            if k + 1 < candidates:
                updater.load_state_dict(fresh_state(k + 1))
            state.save()
    for k, wait in sorted(waits.items()):
        scores[k] = float(np.mean(wait()))
    if state.get("candidate_kept") is None:
        best = int(np.argmax(scores))
        updater.load_state_dict(load_checkpoint(directory / f"updater_{best}.pt", required=("updater",))["updater"])
        state["candidate_kept"] = best
        run.print(f"kept candidate {best + 1} of {candidates} ({scores[best]:.3f}; the others "
                  + ", ".join(f"{s:.3f}" for i, s in enumerate(scores) if i != best) + ")")
    state.save()
    return True


def run_updates(updater: Updater, sample: Callable[[], TensorDictBase], updates: int, *,
                desc: str = "updates") -> dict[str, float]:
    """``updates`` steps of ``updater`` on ``sample()`` (a progress bar named ``desc``): a round's updates.
    Returns their mean metrics (:func:`~trakdis.optim.mean_metrics`: ``train/*``)."""
    return mean_metrics([updater.step(sample()) for _ in progress(range(updates), desc=desc)])


def mixture_shares(episodes: int, round_index: int, rounds: int) -> list[int]:
    """DAgger's decaying mixture: ``[teacher, student]`` episodes of round ``round_index`` (from 0) of
    ``rounds``, the teacher's share ``1 - round_index / (rounds - 1)`` of ``episodes`` (rounded): all
    in the first round, none in the last."""
    beta = 1.0 - round_index / max(rounds - 1, 1)
    n_teacher = round(beta * episodes)
    return [n_teacher, episodes - n_teacher]


def shuffled_batches(data: TensorDictBase, batch_size: int, *, device: str | torch.device = "cpu",
                     desc: str = "epoch") -> Iterator[TensorDictBase]:
    """One epoch over ``data`` ``[N]``: minibatches of ``batch_size`` steps (the last one smaller) in
    an order drawn from torch's global RNG before the first batch, each moved to ``device``, with a
    progress bar named ``desc``."""
    order = torch.randperm(data.shape[0])
    for i in progress(range(0, data.shape[0], batch_size), desc=desc):
        yield data[order[i : i + batch_size]].to(device)


def train_epoch(loss_module: nn.Module, optimizer: torch.optim.Optimizer, data: TensorDictBase, batch_size: int, *,
                loss_key: str, metrics: Sequence[str], device: str | torch.device = "cpu",
                desc: str = "epoch") -> dict[str, float]:
    """One epoch over ``data`` ``[N]`` (:func:`shuffled_batches`): for each minibatch, ``loss_module(batch)``
    and a step of ``optimizer`` on its entry ``loss_key``. Returns the mean over the epoch's steps (each
    batch weighted by its size) of the loss output's entries ``metrics``."""
    totals, n = dict.fromkeys(metrics, 0.0), 0
    for batch in shuffled_batches(data, batch_size, device=device, desc=desc):
        out = loss_module(batch)
        optimizer.zero_grad(set_to_none=True)
        out[loss_key].backward()
        optimizer.step()
        for k in totals:
            totals[k] += float(out[k].detach()) * batch.shape[0]
        n += batch.shape[0]
    return {k: total / n for k, total in totals.items()}


def eval_batches(module: nn.Module, data: TensorDictBase, batch_size: int,
                 fn: Callable[[TensorDictBase], T] | None = None, *, device: str | torch.device = "cpu") -> list[T]:
    """``fn(batch)`` (default: ``module(batch)``) for the consecutive batches of ``batch_size`` steps of
    ``data`` ``[N]``, each moved to ``device``, without gradients and with ``module`` in eval mode
    (its train/eval mode is restored afterwards): a validation pass."""
    was_training = module.training
    module.eval()
    try:
        with torch.no_grad():
            return [(module if fn is None else fn)(data[i : i + batch_size].to(device))
                    for i in range(0, data.shape[0], batch_size)]
    finally:
        module.train(was_training)
