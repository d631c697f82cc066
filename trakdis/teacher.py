"""The privileged teacher's run (``online_dt.py``): the options of its online phase and the rollouts they
make (:class:`OnlinePhaseConfig`: rounds of rollouts into the replay buffer, learnt with the actions they
executed, Online DT, or with the scripted expert's, DAgger), its resume state (:func:`teacher_state`), and
the evaluations it compares on the same eval episodes (:class:`TeacherEvaluations`, options
:class:`TeacherEvalConfig`: the scripted expert, the policy after offline pretraining and the final one),
recorded in that state so that a resumed run plays none of them twice.

    state = teacher_state(run, updater)
    evaluations = TeacherEvaluations(run, protocol, handle, env, state)
    evaluations.expert(cache_root="datasets")
    ...                                    # offline pretraining
    evaluations.offline(run.dir / "policy_offline.pt", dt_config, background=True)
    ...                                    # online rounds (train_rounds(..., evaluate=evaluations.after_round))
    evaluations.final(kept, rounds)
    numbers, line = evaluations.summary()
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ClassVar, Literal

import numpy as np

from trakdis.data import expert_targets
from trakdis.evaluation import CollectorName, compare_scores
from trakdis.training import OnlineRollouts
from trakdis.utils.limits import check_options
from trakdis.utils.phases import PhaseTimer
from trakdis.utils.run import Run, RunState

__all__ = ["OnlinePhaseConfig", "TeacherEvalConfig", "TeacherEvaluations", "teacher_state"]


@dataclass
class OnlinePhaseConfig:
    """The online phase of a teacher (a base of ``online_dt.py``'s config dataclass, so the flags stay
    ``--online-rounds``, ``--online-labels``, ...): rounds of rollouts added to the replay buffer and
    updates on it, and what the policy learns on its rollouts."""

    online_lr: float | None = None  # constant lr of the online phase (default: the last offline one)
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

    def __post_init__(self):  # while parsing (tyro), before the run directory exists
        check_options(self, counts=("online_rounds", "episodes_per_round", "updates_per_round"),
                      positive=("online_lr",))
        parent = getattr(super(), "__post_init__", None)
        if parent is not None:
            parent()

    @property
    def action_target(self) -> str | None:
        """The entry the loss learns instead of the executed ``"action"``: ``"expert_action"`` with DAgger's
        labels (stored beside the executed action; the demonstrations' is their own), None with Online DT's."""
        return "expert_action" if self.online_labels == "expert" else None

    @property
    def rollout_capacity(self) -> int:
        """Room for rollouts beside the dataset in a buffer of the dataset's capacity: DAgger keeps every rollout
        (``--online-rounds`` x ``--episodes-per-round``); Online DT's replace the dataset's trajectories (0)."""
        return self.online_rounds * self.episodes_per_round if self.action_target else 0

    def rollouts(self, env: Any, handle: Any, buffer: Any, *, task: str, horizon: int, seed: int,
                 close_radius: float | None = None, collector: CollectorName = "sync", phases: PhaseTimer | None = None,
                 workers: int = 1) -> OnlineRollouts:
        """The online rounds' ``roll_out`` (:class:`~trakdis.training.OnlineRollouts`): ``--episodes-per-round``
        episodes of ``handle`` in ``env`` (reseeded per round from ``seed``; the policy's seed ``seed``), their
        mean actions or samples (``--exploration``), added to ``buffer`` unless ``--offline-control``; with
        DAgger's labels each episode first gets the scripted expert's actions
        (:func:`~trakdis.data.expert_targets`, ``close_radius``: the dataset's expert's)."""
        label = None if self.action_target is None else functools.partial(
            expert_targets, task=task, out_key=self.action_target, close_radius=close_radius)
        return OnlineRollouts(env, handle, buffer, self.episodes_per_round, horizon=horizon, seed=seed,
                              policy_seed=seed, deterministic=self.exploration == "mean", add=not self.offline_control,
                              collector=collector, phases=phases, workers=workers, label=label)


@dataclass
class TeacherEvalConfig:
    """What a teacher run evaluates beside its evaluation episodes' options (``EvalConfig``; a base of
    ``online_dt.py``'s config dataclass, so the flags stay ``--eval-rtg``, ``--expert-episodes``, ...): the
    policy's return-to-go there, and the scripted expert on the same episodes (:class:`TeacherEvaluations`)."""

    eval_rtg: float | None = None  # initial return-to-go at evaluation (default: the offline data's best return)
    expert_episodes: int = 10  # the scripted expert on the first N evaluation episodes, for comparison (0: none)
    expert_cache: bool = True  # reuse the expert's evaluation cached in <data.root>/expert_scores/
    background_eval: bool = True  # evaluate the expert and the offline teacher in a low-priority background process

    def __post_init__(self):  # while parsing (tyro), before the run directory exists
        if self.expert_episodes < 0:
            raise ValueError(f"--expert-episodes {self.expert_episodes}: must be >= 0")
        parent = getattr(super(), "__post_init__", None)
        if parent is not None:
            parent()


def teacher_state(run: Run, updater: Any, *, buffer_capacity: int | None = None) -> RunState:
    """The resume state of a teacher run: its counters ``updates`` (the step) and ``rounds``, those of its
    replay buffer (``best_return``, ``normalizer``, ``buffer_capacity``: set by
    :func:`~trakdis.data.offline_state_buffer`, which registers the buffer), the recorded evaluations
    (:meth:`TeacherEvaluations.counters`) and its phase timer (``state.phases``), with ``updater``'s state."""
    return RunState(run, {"updates": 0, "rounds": 0, "best_return": None, "normalizer": None,
                          **TeacherEvaluations.counters(), "buffer_capacity": buffer_capacity},
                    step_key="updates", phases_key="phases", updater=updater)


class TeacherEvaluations:
    """The evaluations a teacher run compares, all on the eval episodes of ``protocol`` (an
    :class:`~trakdis.evaluation.EvalProtocol`) in ``env``, each timed as a phase of ``state.phases``:
    the scripted expert's (:meth:`expert`), the policy's (``handle``, a
    :class:`~trakdis.policies.PolicyHandle`) after offline pretraining (:meth:`offline`), every few
    online rounds (:meth:`after_round`) and at the end (:meth:`final`). The per-episode scores of the
    expert, the offline and the final policy live in ``state`` (a :class:`~trakdis.utils.run.RunState`
    holding :meth:`counters`: ``<name>_eval``, their mean, and ``<name>_scores``), so a checkpoint holds
    them: a resumed run plays none of them again. Logged at ``state[state.step_key]``."""

    NAMES: ClassVar[tuple[str, ...]] = ("expert", "offline", "final")

    def __init__(self, run: Run, protocol: Any, handle: Any, env: Any, state: RunState):
        self.run, self.protocol, self.handle, self.env, self.state = run, protocol, handle, env, state

    @classmethod
    def counters(cls) -> dict[str, None]:
        """The state's entries of the recorded evaluations, none done yet."""
        return dict.fromkeys(f"{name}_{entry}" for name in cls.NAMES for entry in ("eval", "scores"))

    def record(self, name: str) -> Callable[[np.ndarray], None]:
        """An ``on_scores`` callback that stores per-episode scores as ``<name>_eval`` and ``<name>_scores``."""
        return functools.partial(self._record, name)

    def _record(self, name: str, scores: np.ndarray) -> None:
        self.state.update({f"{name}_eval": float(scores.mean()), f"{name}_scores": scores.tolist()})

    def _evaluate(self, what: str, tag: str, **kwargs: Any) -> Any:
        return self.protocol.evaluate(self.run, self.handle, self.env, self.state.phases, what,
                                      step=self.state[self.state.step_key], tag=tag, **kwargs)

    def expert(self, *, cache_root: str | Path, use_cache: bool = True, background: bool = False,
               episodes: int | None = None) -> None:
        """The scripted expert on the first ``episodes`` of the eval episodes, unless recorded
        (:meth:`~trakdis.evaluation.EvalProtocol.expert_scores`: its cache under ``cache_root``, or measured
        now or, with ``background``, in a background process that :meth:`final` waits for)."""
        if self.state["expert_eval"] is None:
            self.protocol.expert_scores(self.run, self.env, self.state.phases, cache_root=cache_root, use_cache=use_cache,
                                        background=background, episodes=episodes, on_scores=self.record("expert"))

    def offline(self, path: str | Path, dt_config: Any, *, background: bool = False) -> None:
        """The policy after offline pretraining, unless recorded: saved once to ``path`` (``policy_offline.pt``),
        then evaluated now (the state saved with its scores) or, with ``background``, from that file in a
        background process while the online phase runs (:meth:`final` waits for it)."""
        if self.state["offline_eval"] is not None:
            return
        self.state.once("offline_policy_saved", functools.partial(self.handle.save, path, dt_config))
        if self._evaluate("offline teacher", "after offline pretraining", on_scores=self.record("offline"),
                          background=path if background else None) is not None:
            self.state.save()

    def after_round(self, r: int) -> None:
        """The policy after online round ``r`` (:func:`~trakdis.training.train_rounds`' ``evaluate``), logged, not
        recorded."""
        self._evaluate("mid-run", f"after round {r}")

    def final(self, kept: int, rounds: int) -> None:
        """The final policy, the snapshot of round ``kept`` of ``rounds`` (0: the offline policy, whose evaluation
        then stands); then the background evaluations still pending (:meth:`expert`, :meth:`offline`)."""
        if kept > 0:
            self._evaluate("final teacher", "after online fine-tuning" + (f" (round {kept}, kept)" if kept < rounds else ""),
                           on_scores=self.record("final"))
        self.protocol.finish_pending(self.run, self.state.phases)
        if kept == 0:
            self.state.update(final_eval=self.state["offline_eval"], final_scores=self.state["offline_scores"])

    def summary(self) -> tuple[dict[str, Any], str]:
        """``(numbers, line)``: the mean scores ``expert``, ``offline`` and ``online`` (the final policy's) and the
        paired online - offline gain (:func:`~trakdis.evaluation.compare_scores`), and their printed line."""
        means = {"expert": self.state["expert_eval"], "offline": self.state["offline_eval"],
                 "online": self.state["final_eval"]}
        line, numbers = compare_scores(means, {"offline": self.state["offline_scores"],
                                               "online": self.state["final_scores"]}, before="offline", after="online")
        return {**means, **numbers}, line
