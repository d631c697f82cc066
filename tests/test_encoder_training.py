"""The state encoder's training run (trakdis.encoder_training): its state, labels, validation and the epoch kept,
the student rounds' images beside the expert's, and the member kept by the weight copy's race."""
import math
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from trakdis.encoder_training import (StudentRounds, WeightCopyConfig, encoder_state, error_groups, keep_best_epoch,
                                      mask_unseen_labels, select_member, validation_errors)
from trakdis.modules import EncoderEnsemble
from trakdis.transforms import OutOfViewFill
from trakdis.utils.checkpoint import read_checkpoint
from trakdis.utils.run import Run, RunConfig


@dataclass
class Cfg(RunConfig):
    pass


def encoder_run(tmp_path, *argv):
    run = Run.start("toy", Cfg, ["--root", str(tmp_path), "--name", "e", "--no-progress", *argv])
    encoder = torch.nn.Linear(2, 2)
    optim = torch.optim.SGD(encoder.parameters(), lr=0.1)
    return run, encoder, encoder_state(run, encoder, optim)


def test_weight_copy_config_rounds_and_checks():
    assert not WeightCopyConfig().with_rounds and WeightCopyConfig().round_epochs == 0  # no --teacher
    cfg = WeightCopyConfig(teacher="t.pt", student_rounds=3, student_epochs=2)
    assert cfg.with_rounds and cfg.round_epochs == 6
    assert WeightCopyConfig(teacher="t.pt", student_rounds=0).round_epochs == 0
    with pytest.raises(ValueError, match="--select-chunk -1"):
        WeightCopyConfig(select_chunk=-1)
    with pytest.raises(ValueError, match="--student-episodes"):
        WeightCopyConfig(student_episodes=-1)
    with pytest.raises(ValueError, match=r"--student-rounds 2 >= 0 needs --student-episodes \(0\)"):
        WeightCopyConfig(teacher="t.pt", student_episodes=0).check_student_rounds()
    WeightCopyConfig(student_episodes=0).check_student_rounds()  # no --teacher: no rounds to play
    WeightCopyConfig(teacher="t.pt", student_rounds=0, student_epochs=0).check_student_rounds()


def test_encoder_state_counters_at_the_checkpoints_top_level(tmp_path):
    run, encoder, state = encoder_run(tmp_path)
    assert dict(state) == {"epoch": 0, "best": {"val_mae": math.inf, "state_dict": None, "epoch": -1},
                           "rounds_done": 0, "student_steps": None, "member_scores": {}}
    assert set(state.objects) == {"encoder", "optim"} and state.step_key == "epoch"
    state["epoch"] = 1
    state.save()
    saved = read_checkpoint(run.checkpoint_path)
    assert saved["epoch"] == 1 and "counters" not in saved and "encoder" in saved
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(state.objects["optim"], T_max=3)
    assert set(encoder_state(run, encoder, state.objects["optim"], schedule=schedule).objects) == {
        "encoder", "optim", "schedule"}


def test_keep_best_epoch_keeps_a_lower_error_or_always(tmp_path):
    run, encoder, state = encoder_run(tmp_path)
    errors = {"mae": 0.5, "corners_cm": 2.0, "pickers_cm": 1.0}
    state["epoch"] = 1
    assert keep_best_epoch(state, encoder, errors)
    assert state["best"]["val_mae"] == 0.5 and state["best"]["epoch"] == 1
    assert state["best"]["val_error_cm"] == {"corners_cm": 2.0, "pickers_cm": 1.0}
    kept, weight = state["best"]["state_dict"], encoder.weight.detach().clone()
    with torch.no_grad():
        encoder.weight.add_(1.0)
    assert torch.equal(kept["weight"], weight)  # a copy, not the live weights
    state["epoch"] = 2
    assert not keep_best_epoch(state, encoder, {**errors, "mae": 0.6}) and state["best"]["epoch"] == 1
    assert keep_best_epoch(state, encoder, {**errors, "mae": 0.6}, always=True) and state["best"]["epoch"] == 2
    state["epoch"] = 3
    assert keep_best_epoch(state, encoder, {**errors, "mae": 0.1}) and state["best"]["val_mae"] == 0.1


def test_validation_errors_in_eval_mode_and_without_validation_steps():
    encoder = torch.nn.Linear(2, 2, bias=False)
    with torch.no_grad():
        encoder.weight.copy_(torch.eye(2))
    loss = torch.nn.Sequential(encoder)  # the training loss: its mode is set
    data = TensorDict({"pixels": torch.ones(5, 2), "state": torch.zeros(5, 2)}, batch_size=[5])
    seen = []

    def error_cm(err):
        seen.append((err.shape, encoder.training))
        return {"mae": float(err.mean()), "corners_cm": 100 * float(err.mean())}

    assert validation_errors(loss, encoder, data, error_cm, batch_size=2) == {"mae": 1.0, "corners_cm": 100.0}
    assert loss.training and seen == [(torch.Size([5, 2]), True)]  # eval mode during the passes, then restored
    assert math.isnan(validation_errors(loss, encoder, None, error_cm)["mae"])
    assert error_groups({"mae": 1.0, "corners_cm": 1.234, "pickers_cm": 0.5}) == "corners 1.23 cm, pickers 0.50 cm"


def test_mask_unseen_labels_masks_training_and_validation_states():
    fill = OutOfViewFill.for_task("ClothFold")
    states = torch.zeros(4, 18)
    states[:, 12:15] = 5.0  # a picker far out of view
    train, val = TensorDict({"state": states.clone()}, [4]), TensorDict({"state": states.clone()}, [4])
    lines = []
    mask_unseen_labels(fill, train, val, log=lines.append)
    assert torch.equal(train["state"], fill.mask(states)) and torch.equal(val["state"], fill.mask(states))
    assert not torch.equal(train["state"], states) and lines[0].startswith("--mask-unseen-pickers: ")
    mask_unseen_labels(fill, train, None)  # no validation steps
    untouched = TensorDict({"state": states.clone()}, [4])
    mask_unseen_labels(None, untouched, None, log=lines.append)
    assert torch.equal(untouched["state"], states) and len(lines) == 1


def test_student_rounds_join_the_expert_steps_after_the_first_epochs(tmp_path, monkeypatch):
    """Rounds after epoch 2, then every 3 epochs; each round's steps join the earlier ones (plain tensors in the
    state), its seed the round's index past ``seed``; no teacher: never due."""
    import trakdis.encoder_training as encoder_training

    played = []

    def rollout_steps(teacher, encoder, *, episodes, image_size, seed, label_fill, parallel):
        played.append((teacher, encoder, episodes, image_size, seed, label_fill, parallel))
        steps = TensorDict({"pixels": torch.full((episodes, 1), float(seed)), "state": torch.zeros(episodes, 1)},
                           [episodes])
        return steps, {"normalized_performance": 0.5, "corners_cm": 1.0, "pickers_cm": 2.0, "mae": 0.1}

    monkeypatch.setattr(encoder_training, "student_rollout_steps", rollout_steps)
    run, encoder, state = encoder_run(tmp_path)
    rounds = StudentRounds(state, "teacher", rounds=2, episodes=3, first_epoch=2, epochs_per_round=3, seed=5000,
                           image_size=16, label_fill="fill", parallel=True)
    expert = TensorDict({"pixels": torch.zeros(4, 1), "state": torch.ones(4, 1)}, [4])
    due = []
    for epoch in range(8):
        state["epoch"] = epoch
        due.append(rounds.due())
        if due[-1]:
            rounds.play(encoder, run)
    assert due == [False, False, True, False, False, True, False, False] and state["rounds_done"] == 2
    assert [p[4] for p in played] == [5000, 5001] and played[0][5:] == ("fill", True) and played[0][2:4] == (3, 16)
    assert isinstance(state["student_steps"], dict) and state["student_steps"]["pixels"].shape == (6, 1)
    data = rounds.training_data(expert)
    assert data.batch_size == (10,) and torch.equal(data["pixels"][4:, 0], torch.tensor([5000.0] * 3 + [5001.0] * 3))
    assert run.logger.frame()["student/normalized_performance"].notna().sum() == 2
    assert StudentRounds.counters() == {"rounds_done": 0, "student_steps": None}
    idle = StudentRounds(state, None, rounds=2, episodes=3, first_epoch=2, epochs_per_round=3, seed=0)
    state["epoch"] = 8
    assert not idle.due() and idle.training_data(expert).batch_size == (10,)  # the steps of the rounds already played
    cfg = WeightCopyConfig(student_rounds=2, student_episodes=3, student_epochs=3)
    assert cfg.student_rounds_of(state, "teacher", first_epoch=2, seed=0).teacher is None  # no --teacher
    with_teacher = WeightCopyConfig(teacher="t.pt", student_episodes=3).student_rounds_of(state, "teacher", first_epoch=2,
                                                                                           seed=0)
    assert (with_teacher.teacher, with_teacher.episodes, with_teacher.epochs_per_round) == ("teacher", 3, 5)


def test_select_member_keeps_the_best_of_those_that_played_all_and_races_once(tmp_path, monkeypatch):
    import trakdis.encoder_training as encoder_training

    races = []

    def race(teacher, members, *, episodes, seed, chunk, parallel, on_chunk):
        races.append((teacher, len(members), episodes, seed, chunk, parallel, [m.state_mirror for m in members]))
        on_chunk({0: [0.9], 1: [0.5], 2: [0.6]}, [0, 2])
        return {0: np.array([0.9]), 1: np.array([0.5, 0.4]), 2: np.array([0.6, 0.7])}  # 0 stopped early

    monkeypatch.setattr(encoder_training, "weight_copy_race", race)
    run, _, state = encoder_run(tmp_path)
    encoder = EncoderEnsemble([torch.nn.Linear(2, 2) for _ in range(3)])
    mirror = ([0], [-1.0])
    state["epoch"] = 4
    assert select_member(run, state, "teacher", encoder, episodes=2, seed=9000, chunk=1, state_mirror=mirror) == 2
    assert races == [("teacher", 3, 2, 9000, 1, False, [mirror] * 3)]
    assert state["member_scores"] == {0: [0.9], 1: [0.5, 0.4], 2: [0.6, 0.7]}
    assert read_checkpoint(run.checkpoint_path)["member_scores"] == state["member_scores"]  # saved at once
    assert select_member(run, state, "teacher", encoder, episodes=2, seed=9000) == 2 and len(races) == 1  # not again
    frame = run.logger.frame()
    assert frame.loc[frame["step"] == 4, "select/member2_normalized_performance"].item() == pytest.approx(0.65)
