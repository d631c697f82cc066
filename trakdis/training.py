"""The update loops of the recipes: ``updater`` steps on sampled batches until a counter reaches
its total, with the log, checkpoint and ``--stop-after`` cadence written once
(:func:`train_updates`), rounds of rollouts and updates (Online DT, DAgger: :func:`train_rounds`),
an Online DT round's rollouts into the replay buffer (:func:`online_rollouts`; round by round:
:class:`OnlineRollouts`), a round's updates (:func:`run_updates`), the episodes each acting policy plays
in a round of DAgger's mixture (:func:`mixture_shares`), a replay buffer's batches (:func:`buffer_batches`),
one epoch's shuffled minibatches of a dataset (:func:`shuffled_batches`), one epoch of plain optimiser
steps on them (:func:`train_epoch`) and a validation pass over a dataset in batches
(:func:`eval_batches`), and the choice of a run's best snapshot on episodes the final evaluation never
plays (:class:`SnapshotSelection`, its options :class:`SelectionConfig`).

    done = train_updates(run, updater, buffer_batches(buffer, 64), state=state, total=1500,
                         log_every=50, checkpoint_every=500)
    if not done:        # --stop-after: checkpoint written, continue with --resume
        return
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Mapping, Sequence, TypeVar

import numpy as np
import torch
from tensordict import TensorDictBase
from torch import nn

from trakdis.envs import task_defaults
from trakdis.evaluation import CollectorName, paired_difference, run_episodes
from trakdis.optim import Updater, mean_metrics
from trakdis.utils.limits import check_options
from trakdis.utils.phases import PhaseTimer
from trakdis.utils.progress import progress
from trakdis.utils.run import Run, RunState

__all__ = ["OnlineRollouts", "SelectionConfig", "SnapshotSelection", "buffer_batches", "eval_batches", "mixture_shares",
           "online_rollouts", "run_updates", "shuffled_batches", "train_epoch", "train_rounds", "train_updates"]

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


def train_rounds(run: Run, updater: Updater, sample: Callable[[], TensorDictBase], *, state: RunState, rounds: int,
                 updates_per_round: int, roll_out: Callable[[int], tuple[Mapping[str, Any], str]],
                 model: nn.Module | None = None, selection: SnapshotSelection | None = None,
                 evaluate: Callable[[int], Any] | None = None, eval_every: int = 0, phases: PhaseTimer | None = None,
                 phase: str = "updates", log_extra: Mapping[str, Any] | None = None, loss_key: str = "train/loss",
                 key: str = "rounds", step_key: str = "updates", stop_key: str | None = None) -> bool:
    """Rounds of (roll out, update), as Online DT's fine-tuning and DAgger's distillation run them,
    until ``state[key]`` reaches ``rounds``.

    Round ``r`` (from 0): ``roll_out(r)`` plays the round's episodes into the buffer that ``sample``
    reads and returns ``(metrics, line)``: what to log and a text for the printed line (either may
    be empty); then ``updates_per_round`` steps of ``updater`` (``model`` in train mode; the phase
    ``phase`` of ``phases`` when given) advance ``state[step_key]``. Each round logs one row at
    ``state[step_key]`` (the updates' mean ``train/*``, ``log_extra``, then ``metrics``) and prints
    ``"round <r+1>/<rounds>: <line>, <loss_key's name> <value>"``; after every round but the last,
    ``selection.after_round(r + 1)`` (a :class:`SnapshotSelection`'s snapshot every ``selection.every``
    rounds), then ``evaluate(r + 1)`` every ``eval_every`` rounds. A checkpoint after every round;
    ``--stop-after`` counts ``state[stop_key]`` (default ``key``). Returns False when it stopped the run, True once ``rounds``
    are done."""
    stop_key = key if stop_key is None else stop_key
    while state[key] < rounds:
        metrics, line = roll_out(state[key])
        if model is not None:
            model.train()
        with phases.phase(phase) if phases is not None else contextlib.nullcontext():
            train = run_updates(updater, sample, updates_per_round, desc=f"round {state[key] + 1}")
        state[key] += 1
        state[step_key] += updates_per_round
        run.log(state[step_key], {**train, **(log_extra or {}), **metrics})
        run.print(f"round {state[key]}/{rounds}: " + ", ".join(
            [*([line] if line else []), f"{loss_key.split('/')[-1]} {run.logger.last(loss_key):.4f}"]))
        if selection is not None and state[key] < rounds:
            selection.after_round(state[key])
        if evaluate is not None and eval_every and state[key] % eval_every == 0 and state[key] < rounds:
            evaluate(state[key])
        total = rounds if stop_key == key else state[stop_key] + (rounds - state[key]) * updates_per_round
        if state.save_and_should_stop(total, key=stop_key, unit="round" if stop_key == key else "update"):
            return False
    return True


def online_rollouts(env: Any, handle: Any, buffer: Any, episodes: int, *, horizon: int, seed: int,
                    policy_seed: int | None = None, deterministic: bool = True, add: bool = True,
                    collector: CollectorName = "sync", phases: PhaseTimer | None = None, workers: int = 1,
                    prefix: str = "online", extra: Mapping[str, Any] | None = None,
                    label: Callable[[TensorDictBase], TensorDictBase] | None = None) -> tuple[dict[str, Any], str]:
    """One round of Online DT's data collection, a :func:`train_rounds` ``roll_out``: ``episodes``
    episodes of ``handle``'s policy (a :class:`~trakdis.policies.PolicyHandle`; mean actions if
    ``deterministic``) in ``env`` (reseeded with ``seed``), as the phase ``"<prefix> rollouts"`` of
    ``phases`` (on ``workers`` processes), the entries ``buffer`` stores added to it (a
    :class:`~trakdis.data.TrajectoryReplayBuffer`; ``add=False``: the offline-only control), after
    ``label(episode)`` if given (e.g. :func:`~trakdis.data.expert_targets`, DAgger). Returns
    the metrics to log (``<prefix>/normalized_performance``, ``/return``, ``extra``, ``/kept``,
    ``/buffer_online_fraction``) and a line for the round's printout."""
    timed = phases is not None
    with phases.phase(f"{prefix} rollouts", episodes=episodes, workers=workers) if timed else contextlib.nullcontext():
        res = run_episodes(env, handle.make_policy(seed=policy_seed), episodes, max_steps=horizon,
                           deterministic=deterministic, keep_episodes=True, desc="rollout", seed=seed, collector=collector)
    episodes = res.episodes if add else ()
    if label is not None:
        episodes = [label(ep) for ep in episodes]
    kept = buffer.add_episodes(episodes, keys=buffer.keys)
    score, ret = float(res.final_performance.mean()), float(res.returns.mean())
    metrics = {f"{prefix}/normalized_performance": score, f"{prefix}/return": ret, **(extra or {}),
               f"{prefix}/kept": kept, f"{prefix}/buffer_online_fraction": buffer.online_fraction}
    return metrics, (f"rollout normalized performance {score:.3f}, return {ret:.3f} ({kept} kept; buffer "
                     f"{buffer.online_fraction:.0%} online; {res.rate()})")


@dataclass
class OnlineRollouts:
    """A :func:`train_rounds` ``roll_out`` of Online DT (and of its DAgger variant, ``label``): round ``r``
    plays :func:`online_rollouts` of ``handle`` in ``env`` into ``buffer`` with these arguments, the
    episodes' configurations reseeded with ``seed + 1000 (r + 1)`` (each round's its own, the same on
    every run of this seed) and ``online/round`` = ``r + 1`` logged beside the round's metrics."""

    env: Any
    handle: Any
    buffer: Any
    episodes: int
    horizon: int
    seed: int
    policy_seed: int | None = None
    deterministic: bool = True
    add: bool = True
    collector: CollectorName = "sync"
    phases: PhaseTimer | None = None
    workers: int = 1
    label: Callable[[TensorDictBase], TensorDictBase] | None = None

    def __call__(self, r: int) -> tuple[dict[str, Any], str]:
        return online_rollouts(self.env, self.handle, self.buffer, self.episodes, horizon=self.horizon,
                               seed=self.seed + 1000 * (r + 1), policy_seed=self.policy_seed,
                               deterministic=self.deterministic, add=self.add, collector=self.collector,
                               phases=self.phases, workers=self.workers, extra={"online/round": r + 1}, label=self.label)


def buffer_batches(buffer: Any, batch_size: int, device: str | torch.device = "cpu") -> Callable[[], TensorDictBase]:
    """The ``sample`` of :func:`train_updates` and :func:`train_rounds`: each call draws ``batch_size``
    windows from ``buffer`` (``buffer.sample``) and moves them to ``device``."""
    return functools.partial(_sample_batch, buffer, batch_size, device)


def _sample_batch(buffer: Any, batch_size: int, device: str | torch.device) -> TensorDictBase:
    return buffer.sample(batch_size).to(device)


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


class SnapshotSelection:
    """Model selection among a run's snapshots (early stopping; DAgger's "return the best policy on
    validation", Ross et al. 2011): :meth:`consider` scores ``module`` as it is now with
    ``score(step)`` (per-episode scores of episodes that the final evaluation never plays, e.g. the
    train split's, the same configurations for every snapshot) and keeps a copy of its weights when
    they beat the snapshot kept so far by more than ``margin`` standard errors of the paired
    difference. Otherwise the earlier snapshot stays: the first one, a run's starting point (the
    weight copy), is kept unless a later one is measurably better, so noise alone does not trade it
    for a worse one. :meth:`restore` loads the kept weights back.

    The record lives in ``state[key]`` (``{"scores": {step: [per-episode scores]}, "best": step,
    "state_dict": ...}``), so a checkpoint holds it: a resumed run neither scores a snapshot twice
    nor forgets the kept one.

        selection = SnapshotSelection(student, lambda step: evals.run(...).final_performance, state)
        selection.consider(0)            # the weight copy
        ...                              # every few rounds: selection.consider(round)
        kept = selection.restore()       # the step whose weights are now loaded

    A recipe's rounds (both recipes' early stopping: :meth:`on_episodes`, :meth:`after_round`, :meth:`finish`):

        selection = SnapshotSelection.on_episodes(run, handle, evals, train_env, state, episodes=30, every=4)
        selection.consider(0)            # before the first round
        ...                              # after round r: selection.after_round(r) (train_rounds' selection)
        kept = selection.finish(rounds, run.print)

    ``score`` None: a selection with nothing to score (:attr:`active` False; :meth:`on_episodes` without an
    env): it considers no snapshot and :meth:`finish` keeps the last round's weights; its record is made all
    the same, so a run's state and :meth:`summary` do not depend on it.
    """

    def __init__(self, module: nn.Module, score: Callable[[int], Sequence[float]] | None, state: dict, *,
                 margin: float = 1.0, every: int = 1, name: str = "snapshot", key: str = "selection"):
        if every < 1:
            raise ValueError(f"every must be >= 1 (rounds between the scored snapshots), got {every}")
        self.module, self.score, self.state, self.margin, self.key = module, score, state, margin, key
        self.every, self.name = every, name
        state.setdefault(key, {"scores": {}, "best": None, "state_dict": None})

    @classmethod
    def on_episodes(cls, run: Run, handle: Any, protocol: Any, env: Any, state: dict, *, episodes: int,
                    module: nn.Module | None = None, every: int = 1, margin: float = 1.0, name: str = "policy",
                    split: str = "train", seed_offset: int = 10_000, step_key: str = "updates") -> SnapshotSelection:
        """Score ``handle`` (a :class:`~trakdis.policies.PolicyHandle` acting with ``module``, default its
        actor) on ``episodes`` episodes of ``env`` (configurations of ``split`` that the final evaluation never
        plays) with ``protocol`` (an :class:`~trakdis.evaluation.EvalProtocol`) reseeded ``seed_offset`` past its
        own seed, the same episodes for every snapshot; each logged as ``selection/`` at ``state[step_key]``.
        ``env`` None (no selection episodes, or no rounds): an inactive selection (see the class)."""
        module = handle.actor if module is None else module
        if env is None:
            return cls(module, None, state, margin=margin, every=every, name=name)
        picks = dataclasses.replace(protocol, episodes=episodes, seed=protocol.seed + seed_offset)

        def score(r: int) -> Sequence[float]:
            return picks.run(run, handle, env, step=state[step_key], tag=f"selection: {name} after round {r}",
                             prefix="selection", keep_mode=module, split=split).final_performance
        return cls(module, score, state, margin=margin, every=every, name=name)

    @property
    def record(self) -> dict:
        return self.state[self.key]

    @property
    def active(self) -> bool:
        """Whether there is anything to score the snapshots with."""
        return self.score is not None

    def means(self) -> dict[int, float]:
        """The mean score of every snapshot considered, by step."""
        return {step: float(np.mean(s)) for step, s in self.record["scores"].items()}

    def consider(self, step: int) -> float | None:
        """Score the module's weights at ``step`` (once per step), keep them if they beat the kept
        snapshot (see the class); returns their mean score (None: an inactive selection)."""
        if not self.active:
            return None
        rec = self.record
        if step not in rec["scores"]:
            rec["scores"][step] = [float(x) for x in np.asarray(self.score(step), dtype=np.float64).reshape(-1)]
            better = rec["best"] is None
            if not better:
                gain, se = paired_difference(rec["scores"][rec["best"]], rec["scores"][step])
                better = gain > 0 and gain > self.margin * se
            if better:
                rec["best"] = step
                rec["state_dict"] = {k: v.detach().clone() for k, v in self.module.state_dict().items()}
        return float(np.mean(rec["scores"][step]))

    def restore(self) -> int | None:
        """Load the kept snapshot's weights into the module; returns its step (None: nothing considered)."""
        rec = self.record
        if rec["state_dict"] is not None:
            self.module.load_state_dict(rec["state_dict"])
        return rec["best"]

    def after_round(self, r: int) -> None:
        """Score the snapshot after round ``r`` when ``r`` is a multiple of ``every``."""
        if r % self.every == 0:
            self.consider(r)

    def finish(self, rounds: int, log: Callable[[str], None] = print) -> int | None:
        """Score the snapshot after the last round (``rounds``), restore the kept one and log which; returns its
        round (an inactive selection: ``rounds``, the weights as they are)."""
        if not self.active:
            return rounds
        self.consider(rounds)
        kept = self.restore()
        log(f"selection: the {self.name} after round {kept} is kept (train-split scores by round: "
            + ", ".join(f"{r} {v:.3f}" for r, v in self.means().items()) + ")")
        return kept

    def summary(self) -> dict:
        """``selected_round`` and ``selection_scores`` (mean by round), for a saved policy's extras."""
        return {"selected_round": self.record["best"], "selection_scores": self.means()}


@dataclass
class SelectionConfig:
    """The early-stopping options of a recipe with rounds (a base of its config dataclass, so the flags
    stay ``--select-episodes``, ``--select-every``, ``--select-margin``; a recipe redeclares a field to
    change its default): the episodes, cadence and margin of its :class:`SnapshotSelection`
    (:meth:`SnapshotSelection.on_episodes`)."""

    select_episodes: int = 0
    """early stopping: train-split episodes that the run's starting point and its snapshot every --select-every
    rounds (and after the last) play; the one kept beats the earlier ones by --select-margin standard errors
    (0: the last)"""
    select_every: int = 4  # rounds between the snapshots --select-episodes compares
    select_margin: float = 1.0  # standard errors of the paired difference a later snapshot must win by

    def __post_init__(self):  # while parsing (tyro), before the run directory exists
        check_options(self, sizes=("select_every",), counts=("select_episodes",), nonnegative=("select_margin",))
        parent = getattr(super(), "__post_init__", None)
        if parent is not None:
            parent()

    def resolved_select_episodes(self, task: str) -> int:
        """``--select-episodes``, or where a recipe lets it be unset (None), the task's
        ``TaskDefaults.select_episodes``."""
        return task_defaults(task).select_episodes if self.select_episodes is None else self.select_episodes
