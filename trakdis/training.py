"""The update loops of the recipes: ``updater`` steps on sampled batches until a counter reaches
its total, with the log, checkpoint and ``--stop-after`` cadence written once
(:func:`train_updates`), one epoch's shuffled minibatches of a dataset (:func:`shuffled_batches`) and
a validation pass over a dataset in batches (:func:`eval_batches`).

    done = train_updates(run, updater, lambda: buffer.sample(64), state=state, total=1500,
                         log_every=50, checkpoint_every=500)
    if not done:        # --stop-after: checkpoint written, continue with --resume
        return
"""
from __future__ import annotations

from typing import Any, Callable, Iterator, Mapping, TypeVar

import torch
from tensordict import TensorDictBase
from torch import nn

from trakdis.optim import Updater, mean_metrics
from trakdis.utils.progress import progress
from trakdis.utils.run import Run, RunState

__all__ = ["eval_batches", "shuffled_batches", "train_updates"]

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


def shuffled_batches(data: TensorDictBase, batch_size: int, *, device: str | torch.device = "cpu",
                     desc: str = "epoch") -> Iterator[TensorDictBase]:
    """One epoch over ``data`` ``[N]``: minibatches of ``batch_size`` steps (the last one smaller) in
    an order drawn from torch's global RNG before the first batch, each moved to ``device``, with a
    progress bar named ``desc``."""
    order = torch.randperm(data.shape[0])
    for i in progress(range(0, data.shape[0], batch_size), desc=desc):
        yield data[order[i : i + batch_size]].to(device)


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
