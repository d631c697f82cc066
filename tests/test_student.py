"""The student of a teacher and an encoder (trakdis.student): made, checked, rolled out and raced."""
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tiny_policies import tiny_actor, tiny_teacher_and_encoder

from trakdis.modules import NormalizedEncoder, StateEncoder
from trakdis.policies import load_policy, save_encoder, save_policy
from trakdis.student import (check_unseen_picker_mask, load_teacher_and_encoder, student_rollout_steps,
                             weight_copied_student, weight_copy_race, weight_copy_scores)
from trakdis.transforms import OutOfViewFill, normalizer_parts, state_normalizer


def same_fill(a: OutOfViewFill, b: OutOfViewFill) -> bool:
    return (a.image_size == b.image_size and a.starts == b.starts and torch.equal(a.camera_matrix, b.camera_matrix)
            and torch.equal(a.fill, b.fill))


def test_weight_copied_student_is_the_teachers_dt_on_the_estimate(tmp_path):
    cfg, actor = tiny_actor()
    norm = state_normalizer(torch.zeros(5), torch.full((5,), 2.0))
    save_policy(tmp_path / "policy.pt", kind="teacher", task="ClothFoldDiagonalPinned", horizon=10, dt_config=cfg,
                actor=actor, observation_key="state", target_return=-0.5, rtg_scale=2.0, normalizer=norm)
    teacher = load_policy(tmp_path)
    encoder = torch.nn.Identity()
    student, dt_cfg = weight_copied_student(teacher, encoder, normalizer_keys=("state", "state_estimate"))
    assert dt_cfg == cfg and student.kind == "student" and student.encoder is encoder
    assert student.observation_key == "state_estimate" and student.target_return == -0.5 and student.rtg_scale == 2.0
    student_norm, _ = normalizer_parts(student.normalizer)
    assert student_norm.in_keys == ["state", "state_estimate"] and torch.equal(student_norm.scale, norm.scale)
    for a, b in zip(teacher.actor.parameters(), student.actor.parameters()):
        assert torch.equal(a, b)
    fresh, _ = weight_copied_student(teacher, encoder, weight_copy=False, proprio_dims=(3, 4))
    assert fresh.proprio_dims == (3, 4) and normalizer_parts(fresh.normalizer)[0].in_keys == ["state_estimate"]
    assert not all(torch.equal(a, b) for a, b in zip(teacher.actor.parameters(), fresh.actor.parameters()))


def test_student_rollout_steps(tmp_path):
    from trakdis.envs import task_spec

    spec = task_spec("ClothFold")
    teacher, encoder = tiny_teacher_and_encoder(tmp_path, horizon=2)
    steps, metrics = student_rollout_steps(teacher, encoder, episodes=2, seed=0)
    assert set(steps.keys()) == {"pixels", "state"} and steps.batch_size == (4,)  # 2 episodes x 2 steps
    assert steps["pixels"].shape[1:] == (32, 32, 3) and steps["state"].shape[1:] == (spec.state_dim,)
    assert set(metrics) == {"normalized_performance", "corners_cm", "pickers_cm", "mae"}
    assert encoder.training  # the rollouts used a copy: the caller's encoder keeps its mode
    fill = OutOfViewFill.for_task("ClothFold")  # the labels of train_encoder.py --mask-unseen-pickers
    masked, _ = student_rollout_steps(teacher, encoder, episodes=2, seed=0, label_fill=fill)
    assert torch.equal(masked["pixels"], steps["pixels"]) and torch.equal(masked["state"], fill.mask(steps["state"]))


def test_weight_copy_episodes_in_worker_processes_are_the_serial_ones(tmp_path):
    """``parallel=True`` (``train_encoder.py --parallel``): the same episodes, stepped in 2 worker processes."""

    teacher, encoder = tiny_teacher_and_encoder(tmp_path, horizon=3, encoder_scale=0.1)
    serial, metrics = student_rollout_steps(teacher, encoder, episodes=2, seed=3)
    parallel, metrics_parallel = student_rollout_steps(teacher, encoder, episodes=2, seed=3, parallel=True)
    assert torch.equal(serial["pixels"], parallel["pixels"]) and torch.equal(serial["state"], parallel["state"])
    assert metrics == metrics_parallel
    scores = weight_copy_scores(teacher, encoder, episodes=2, seed=3, parallel=True)  # the same episodes' scores
    assert scores.shape == (2,) and scores.mean() == pytest.approx(metrics["normalized_performance"], rel=1e-12)


def test_weight_copy_race_plays_the_weight_copy_episodes_and_stops_the_clearly_worse(tmp_path):
    """Each encoder's scores are the first episodes of its weight_copy_scores (all of them for those that
    finish the race); one that falls behind the leader by more than the margin plays no more."""
    import copy

    from trakdis.evaluation import race_survivors

    torch.manual_seed(3)  # a tiny teacher whose actions follow its (estimated) state
    teacher, encoder = tiny_teacher_and_encoder(tmp_path, horizon=3, encoder_scale=0.1)
    other = copy.deepcopy(encoder)
    with torch.no_grad():
        for p in other.parameters():
            p.mul_(-3.0)  # other estimates, other actions
    encoders = [encoder, other, copy.deepcopy(encoder)]
    full = [weight_copy_scores(teacher, e, episodes=4, seed=3) for e in encoders]
    reports = []
    raced = weight_copy_race(teacher, encoders, episodes=4, seed=3, chunk=2,
                             on_chunk=lambda scores, alive: reports.append(({k: len(v) for k, v in scores.items()},
                                                                            alive)))
    for k, scores in raced.items():
        np.testing.assert_array_equal(scores, full[k][: len(scores)])
    np.testing.assert_array_equal(full[0], full[2])  # the same weights: tied, both play on or both stop
    alive = race_survivors({k: v[:2] for k, v in enumerate(full)})
    assert alive == [0, 2] and [len(raced[k]) for k in range(3)] == [4, 2, 4]  # "other" far behind after 2
    assert reports == [({0: 2, 1: 2, 2: 2}, alive), ({k: len(v) for k, v in raced.items()}, alive)]
    in_workers = weight_copy_race(teacher, encoders, episodes=4, seed=3, chunk=2, parallel=True)  # 2 processes each
    assert all(np.array_equal(in_workers[k], raced[k]) for k in raced)
    # no racing: every encoder plays every episode, at once
    plain = weight_copy_race(teacher, encoders[:2], episodes=4, seed=3, chunk=0)
    assert [len(v) for v in plain.values()] == [4, 4] and np.array_equal(plain[1], full[1])


def test_load_teacher_and_encoder_finds_the_latest_runs_and_checks_the_mask(tmp_path):
    cfg, actor = tiny_actor()
    enc = NormalizedEncoder(StateEncoder(15, channels=(4, 4, 4, 4), hidden_dim=8), torch.zeros(15), torch.ones(15))
    with pytest.raises(FileNotFoundError, match="--teacher"):
        load_teacher_and_encoder("latest", "latest", root=tmp_path)
    for recipe, name in (("online_dt", "t"), ("train_encoder", "e")):
        (tmp_path / recipe / name).mkdir(parents=True)
        (tmp_path / recipe / name / "config.json").write_text("{}")
    save_policy(tmp_path / "online_dt" / "t" / "policy.pt", kind="teacher", task="ClothFoldDiagonalPinned", horizon=10,
                dt_config=cfg, actor=actor, observation_key="state", target_return=-1.0, rtg_scale=1.0,
                normalizer=state_normalizer(torch.zeros(15), torch.ones(15)))
    with pytest.raises(FileNotFoundError, match="--encoder"):
        load_teacher_and_encoder("latest", "latest", root=tmp_path)
    save_encoder(tmp_path / "train_encoder" / "e" / "encoder.pt", enc, task="ClothFoldDiagonalPinned")
    teacher, encoder, encoder_file, encoder_path = load_teacher_and_encoder("latest", "latest", root=tmp_path)
    assert teacher.kind == "teacher" and teacher.source == str(tmp_path / "online_dt" / "t" / "policy.pt")
    assert encoder_path == tmp_path / "train_encoder" / "e" / "encoder.pt" and encoder_file["task"] == teacher.task
    assert isinstance(encoder, NormalizedEncoder)
    save_encoder(tmp_path / "masked.pt", enc, task="ClothFoldDiagonalPinned",
                 extra={"mask_unseen_pickers": True,
                        "out_of_view_fill": OutOfViewFill.for_task("ClothFoldDiagonalPinned").to_dict()})
    with pytest.raises(ValueError, match="--mask-unseen-pickers"):  # a plain teacher, a masked encoder
        load_teacher_and_encoder(tmp_path / "online_dt" / "t", tmp_path / "masked.pt", root=tmp_path)
    save_encoder(tmp_path / "other.pt", enc, task="ClothFoldDiagonalUnpinned")
    with pytest.raises(ValueError, match="not ClothFoldDiagonalPinned"):  # an encoder of another task
        load_teacher_and_encoder("latest", tmp_path / "other.pt", root=tmp_path)


def test_masked_teacher_passes_its_fill_to_the_student_and_a_mismatched_encoder_is_refused(tmp_path):
    """--mask-unseen-pickers: the teacher file's normaliser carries the fill, the weight-copied
    student's normaliser keeps it; teacher and encoder must both be masked or neither."""
    cfg, actor = tiny_actor()
    fill = OutOfViewFill.for_task("ClothFoldDiagonalPinned")
    for name, f in (("masked", fill), ("plain", None)):
        save_policy(tmp_path / f"{name}.pt", kind="teacher", task="ClothFoldDiagonalPinned", horizon=10, dt_config=cfg,
                    actor=actor, observation_key="state", target_return=-0.5, rtg_scale=1.0,
                    normalizer=state_normalizer(torch.zeros(15), torch.ones(15), fill=f))
    masked, plain = load_policy(tmp_path / "masked.pt"), load_policy(tmp_path / "plain.pt")
    assert same_fill(normalizer_parts(masked.normalizer)[1], fill) and normalizer_parts(plain.normalizer)[1] is None
    student, _ = weight_copied_student(masked, torch.nn.Identity(), normalizer_keys=("state", "state_estimate"))
    student_norm, student_fill = normalizer_parts(student.normalizer)
    assert same_fill(student_fill, fill) and student_norm.in_keys == ["state", "state_estimate"]
    x = torch.zeros(2, 15)
    x[1, 12:] = torch.tensor([0.0, 0.0, 0.3])  # out of view: the student reads the sentinel, like the teacher
    read = student.normalizer(TensorDict({"state_estimate": x}, batch_size=[2]))["state_estimate"]
    assert read[1, 12:].tolist() == pytest.approx([0.0, 0.0, 0.4])
    enc_masked = {"mask_unseen_pickers": True, "out_of_view_fill": fill.to_dict()}
    assert check_unseen_picker_mask(masked, enc_masked, encoder_source="enc.pt") is True
    assert check_unseen_picker_mask(plain, {}, encoder_source="enc.pt") is False  # earlier encoder files
    for teacher, enc in ((masked, {}), (plain, enc_masked), (masked, {"mask_unseen_pickers": False})):
        with pytest.raises(ValueError, match=rf"teacher {teacher.source} .*encoder enc\.pt .*--mask-unseen-pickers"):
            check_unseen_picker_mask(teacher, enc, encoder_source="enc.pt")
    other = {"mask_unseen_pickers": True,
             "out_of_view_fill": OutOfViewFill.for_task("ClothFoldDiagonalPinned", image_size=64).to_dict()}
    with pytest.raises(ValueError, match="different masks"):
        check_unseen_picker_mask(masked, other, encoder_source="enc.pt")
