"""The teacher's run (trakdis.teacher): the options of its online phase and the rollouts they make, its resume state,
and the evaluations it compares, recorded in that state."""
import functools
from dataclasses import dataclass

import numpy as np
import pytest

from quadratic_loss import Quadratic
from trakdis.data import expert_targets
from trakdis.optim import Updater
from trakdis.teacher import OnlinePhaseConfig, TeacherEvalConfig, TeacherEvaluations, teacher_state
from trakdis.training import OnlineRollouts
from trakdis.utils.checkpoint import read_checkpoint
from trakdis.utils.run import Run, RunConfig


@dataclass
class Cfg(RunConfig):
    pass


def test_online_phase_labels_capacity_and_checks():
    dagger, online_dt = OnlinePhaseConfig(online_rounds=3, episodes_per_round=4), OnlinePhaseConfig(online_labels="executed")
    assert dagger.action_target == "expert_action" and dagger.rollout_capacity == 12  # DAgger keeps every rollout
    assert online_dt.action_target is None and online_dt.rollout_capacity == 0
    for bad in ({"online_rounds": -1}, {"updates_per_round": -1}, {"online_lr": 0.0}):
        with pytest.raises(ValueError, match=f"--{next(iter(bad)).replace('_', '-')}"):
            OnlinePhaseConfig(**bad)
    assert OnlinePhaseConfig.SAVED_WITHOUT == {"online_labels": "executed"}  # a run saved before the option


def test_online_phase_rollouts_label_with_the_expert_only_with_dagger():
    cfg = OnlinePhaseConfig(episodes_per_round=3, exploration="sample", offline_control=True)
    roll_out = cfg.rollouts("env", "handle", "buffer", task="ClothFold", horizon=6, seed=7, close_radius=0.01,
                            collector="sync", workers=2)
    assert isinstance(roll_out, OnlineRollouts)
    assert (roll_out.env, roll_out.handle, roll_out.buffer, roll_out.episodes, roll_out.horizon) == \
        ("env", "handle", "buffer", 3, 6)
    assert (roll_out.seed, roll_out.policy_seed, roll_out.deterministic, roll_out.add, roll_out.workers) == \
        (7, 7, False, False, 2)
    assert isinstance(roll_out.label, functools.partial) and roll_out.label.func is expert_targets
    assert roll_out.label.keywords == {"task": "ClothFold", "out_key": "expert_action", "close_radius": 0.01}
    executed = OnlinePhaseConfig(online_labels="executed").rollouts("env", "handle", "buffer", task="ClothFold",
                                                                    horizon=6, seed=7)
    assert executed.label is None and executed.deterministic and executed.add


def test_teacher_eval_config_refuses_negative_expert_episodes():
    assert TeacherEvalConfig().expert_episodes == 10
    with pytest.raises(ValueError, match=r"--expert-episodes -1: must be >= 0"):
        TeacherEvalConfig(expert_episodes=-1)


class Protocol:
    """The part of EvalProtocol that TeacherEvaluations uses: scores 0.1 x (calls so far), background jobs pending."""

    def __init__(self):
        self.calls, self.pending = [], []

    def scores(self):
        return np.full(2, 0.1 * len(self.calls)) + np.array([0.0, 0.02])

    def expert_scores(self, run, env, phases, *, cache_root, use_cache, background, episodes, on_scores):
        self.calls.append(("expert", cache_root, use_cache, background, episodes))
        on_scores(self.scores())

    def evaluate(self, run, handle, env, phases, what, *, step, tag, on_scores=None, background=None):
        self.calls.append((what, step, tag, background))
        if background is not None:
            self.pending.append((on_scores, self.scores()))
            return None
        if on_scores is not None:
            on_scores(self.scores())
        return "results"

    def finish_pending(self, run, phases):
        while self.pending:
            on_scores, scores = self.pending.pop()
            on_scores(scores)


class Handle:
    def __init__(self):
        self.saved = []

    def save(self, path, dt_config):
        self.saved.append((path, dt_config))


def teacher_run(tmp_path, *argv):
    run = Run.start("toy", Cfg, ["--root", str(tmp_path), "--name", "t", "--no-progress", *argv])
    updater = Updater(Quadratic(), optimizer="adam", lr=1e-2)
    return run, teacher_state(run, updater, buffer_capacity=12)


def test_teacher_state_holds_the_counters_the_recorded_evaluations_and_the_phases(tmp_path):
    run, state = teacher_run(tmp_path)
    assert dict(state) == {"updates": 0, "rounds": 0, "best_return": None, "normalizer": None,
                           **TeacherEvaluations.counters(), "buffer_capacity": 12, "phases": {}}
    assert set(TeacherEvaluations.counters()) == {f"{name}_{entry}" for name in ("expert", "offline", "final")
                                                  for entry in ("eval", "scores")}
    assert state.step_key == "updates" and state.phases is not None and set(state.objects) == {"updater"}


@pytest.mark.parametrize("kept", [2, 1, 0])
def test_teacher_evaluations_record_compare_and_are_not_played_again(tmp_path, kept):
    """The expert's, the offline policy's (saved once, in the background) and the final scores recorded in the
    state; the final one of the round kept (0: the offline policy's stands); a resumed run plays none again."""
    run, state = teacher_run(tmp_path)
    protocol, handle = Protocol(), Handle()
    evaluations = TeacherEvaluations(run, protocol, handle, "env", state)
    evaluations.expert(cache_root="datasets", background=True, episodes=1)
    state["updates"] = 6
    evaluations.offline(tmp_path / "policy_offline.pt", "dt-config", background=True)
    evaluations.after_round(1)
    evaluations.final(kept, 2)
    assert handle.saved == [(tmp_path / "policy_offline.pt", "dt-config")] and state["offline_policy_saved"]
    assert protocol.calls[:3] == [("expert", "datasets", True, True, 1),
                                  ("offline teacher", 6, "after offline pretraining", tmp_path / "policy_offline.pt"),
                                  ("mid-run", 6, "after round 1", None)]
    tags = {2: "after online fine-tuning", 1: "after online fine-tuning (round 1, kept)"}
    assert protocol.calls[3:] == ([("final teacher", 6, tags[kept], None)] if kept else [])
    assert state["expert_scores"] == pytest.approx([0.1, 0.12]) and state["expert_eval"] == pytest.approx(0.11)
    assert state["offline_scores"] == pytest.approx([0.2, 0.22])  # from the background job, once final waited for it
    if kept:
        assert state["final_scores"] == pytest.approx([0.4, 0.42])
    else:
        assert state["final_scores"] == state["offline_scores"] and state["final_eval"] == state["offline_eval"]
    numbers, line = evaluations.summary()
    assert numbers["expert"] == state["expert_eval"] and numbers["online"] == state["final_eval"]
    assert numbers["offline"] == state["offline_eval"] and numbers["gain"] == pytest.approx(0.2 if kept else 0.0)
    assert line.startswith("expert 0.110, offline 0.210")
    again = TeacherEvaluations(run, Protocol(), Handle(), "env", state)  # the recorded evaluations are not played
    again.expert(cache_root="datasets")
    again.offline(tmp_path / "policy_offline.pt", "dt-config")
    assert again.protocol.calls == [] and again.handle.saved == []


def test_the_offline_evaluation_in_this_process_saves_the_state(tmp_path):
    run, state = teacher_run(tmp_path)
    evaluations = TeacherEvaluations(run, Protocol(), Handle(), "env", state)
    evaluations.offline(tmp_path / "policy_offline.pt", "dt-config")
    assert state["offline_eval"] is not None
    saved = read_checkpoint(run.checkpoint_path, numpy_arrays=True)["counters"]  # checkpointed with its scores
    assert saved["offline_eval"] == state["offline_eval"] and saved["offline_scores"] == state["offline_scores"]
