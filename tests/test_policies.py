"""Saved policies: policy and encoder files, the expert, and a policy's acting env."""
import pytest
import numpy as np
import torch

from trakdis.modules import DTConfig, NormalizedEncoder, StateEncoder, make_dt_actor
from trakdis.policies import (PolicyHandle, load_encoder, load_policy, load_teacher, make_acting_env, save_encoder,
                              save_policy)
from trakdis.utils.checkpoint import CheckpointError, save_checkpoint


def tiny_actor(key="state"):
    cfg = DTConfig(embed_dim=16, n_layer=1, n_head=1, context_len=4, dropout=0.0).for_task(5, 2, horizon=10)
    return cfg, make_dt_actor(cfg, observation_key=key)


def test_policy_and_encoder_files(tmp_path):
    cfg, actor = tiny_actor()
    save_policy(tmp_path / "policy.pt", kind="teacher", task="ClothFoldDiagonalPinned", horizon=10, dt_config=cfg,
                actor=actor, observation_key="state", target_return=-1.0, rtg_scale=1.0)
    h = load_policy(tmp_path)  # a run directory works too
    assert h.kind == "teacher" and h.task == "ClothFoldDiagonalPinned" and h.horizon == 10 and h.encoder is None
    for a, b in zip(actor.parameters(), h.actor.parameters()):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="ClothFold"):
        load_policy(tmp_path / "policy.pt", task="ClothFold")
    assert load_policy("expert", task="ClothFold").kind == "expert"
    with pytest.raises(ValueError, match="--task"):
        load_policy("expert")
    enc = NormalizedEncoder(StateEncoder(5, channels=(4, 4, 4, 4), hidden_dim=8), torch.arange(5.0), torch.full((5,), 2.0))
    save_encoder(tmp_path / "encoder.pt", enc, task="ClothFold")
    enc2, data = load_encoder(tmp_path / "encoder.pt")
    px = torch.randint(0, 255, (2, 32, 32, 3), dtype=torch.uint8)
    assert torch.allclose(enc.eval()(px), enc2(px))
    with pytest.raises(CheckpointError, match="teacher"):
        load_encoder(tmp_path / "policy.pt")
    with pytest.raises(ValueError, match="is for ClothFold, not ClothFoldDiagonalUnpinned"):
        load_encoder(tmp_path, task="ClothFoldDiagonalUnpinned")
    assert load_teacher(tmp_path, task="ClothFoldDiagonalPinned", horizon=10).kind == "teacher"
    for kw in ({"task": "ClothFold"}, {"horizon": 5}):
        with pytest.raises(CheckpointError, match="expected a teacher"):
            load_teacher(tmp_path, **kw)
    save_policy(tmp_path / "student.pt", kind="student", task="ClothFold", horizon=10, dt_config=cfg, actor=actor,
                observation_key="state", target_return=-1.0, rtg_scale=1.0, encoder_file=data)
    with pytest.raises(CheckpointError, match="a student for ClothFold .*expected a teacher$"):
        load_teacher(tmp_path / "student.pt")
    save_checkpoint(tmp_path / "bad.pt", {"kind": "encoder", "task": "ClothFold", "dt_config": {}, "actor": {},
                                          "observation_key": "state"})
    with pytest.raises(CheckpointError, match="not a policy"):
        load_policy(tmp_path / "bad.pt")


def test_image_networks_of_another_rendering_are_refused(tmp_path, monkeypatch):
    import trakdis.envs.model
    from trakdis.envs import render_version
    from trakdis.utils.checkpoint import load_checkpoint

    task = "ClothFoldDiagonalUnpinned"
    enc = NormalizedEncoder(StateEncoder(15, channels=(4, 4, 4, 4), hidden_dim=8), torch.zeros(15), torch.ones(15))
    save_encoder(tmp_path / "encoder.pt", enc, task=task)
    _, data = load_encoder(tmp_path / "encoder.pt", task=task)  # today's rendering: loads
    assert data["render_version"] == render_version(task)
    cfg, actor = tiny_actor("state_estimate")
    save_policy(tmp_path / "student.pt", kind="student", task=task, horizon=10, dt_config=cfg, actor=actor,
                observation_key="state_estimate", target_return=-1.0, rtg_scale=1.0, encoder_file=data)
    assert load_policy(tmp_path / "student.pt").encoder is not None
    # an encoder file from before the unpinned fold's wider camera (no version recorded: version 2)
    old = {k: v for k, v in load_checkpoint(tmp_path / "encoder.pt").items() if k != "render_version"}
    save_checkpoint(tmp_path / "old.pt", old)
    with pytest.raises(CheckpointError, match=f"old.pt: .*rendering version 2; this trakdis renders {task} at version 3"):
        load_encoder(tmp_path / "old.pt")
    # the task's rendering changes after the files were written: encoder and student are both refused
    monkeypatch.setitem(trakdis.envs.model.RENDER_VERSIONS, task, render_version(task) + 1)
    with pytest.raises(CheckpointError, match="encoder.pt: .*version 3; this trakdis renders .* at version 4"):
        load_encoder(tmp_path / "encoder.pt")
    with pytest.raises(CheckpointError, match=r"student.pt \(its encoder\): .*version 3"):
        load_policy(tmp_path / "student.pt")


def test_bad_state_noise_and_horizon_are_refused(tmp_path):
    for sigma in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="state_noise must be a finite std >= 0"):
            make_acting_env("ClothFold", state_noise=sigma)
    cfg, actor = tiny_actor()
    save_policy(tmp_path / "policy.pt", kind="teacher", task="ClothFold", horizon=10, dt_config=cfg,
                actor=actor, observation_key="state", target_return=-1.0, rtg_scale=1.0)
    for spec in (tmp_path, "expert"):
        with pytest.raises(ValueError, match="horizon must be >= 1"):
            load_policy(spec, task="ClothFold", horizon=0)
    assert load_policy(tmp_path).horizon == 10 and load_policy(tmp_path, horizon=3).horizon == 3


def test_weight_copied_student_is_the_teachers_dt_on_the_estimate(tmp_path):
    from trakdis.policies import weight_copied_student
    from trakdis.transforms import StateNormalizer

    cfg, actor = tiny_actor()
    norm = StateNormalizer(torch.zeros(5), torch.full((5,), 2.0))
    save_policy(tmp_path / "policy.pt", kind="teacher", task="ClothFoldDiagonalPinned", horizon=10, dt_config=cfg,
                actor=actor, observation_key="state", target_return=-0.5, rtg_scale=2.0, normalizer=norm)
    teacher = load_policy(tmp_path)
    encoder = torch.nn.Identity()
    student, dt_cfg = weight_copied_student(teacher, encoder, normalizer_keys=("state", "state_estimate"))
    assert dt_cfg == cfg and student.kind == "student" and student.encoder is encoder
    assert student.observation_key == "state_estimate" and student.target_return == -0.5 and student.rtg_scale == 2.0
    assert student.normalizer.keys == ("state", "state_estimate") and torch.equal(student.normalizer.scale, norm.scale)
    for a, b in zip(teacher.actor.parameters(), student.actor.parameters()):
        assert torch.equal(a, b)
    fresh, _ = weight_copied_student(teacher, encoder, weight_copy=False, proprio_dims=(3, 4))
    assert fresh.proprio_dims == (3, 4) and fresh.normalizer.keys == ("state_estimate",)
    assert not all(torch.equal(a, b) for a, b in zip(teacher.actor.parameters(), fresh.actor.parameters()))


def test_handle_save_writes_what_save_policy_writes(tmp_path):
    from trakdis.transforms import StateNormalizer
    from trakdis.utils.checkpoint import load_checkpoint

    cfg, actor = tiny_actor("state_estimate")
    norm = StateNormalizer(torch.zeros(5), torch.full((5,), 2.0), keys=("state", "state_estimate"))
    fields = dict(kind="student", task="ClothFold", horizon=10, actor=actor, observation_key="state_estimate",
                  target_return=-0.5, rtg_scale=2.0, normalizer=norm, env_kwargs={"picker_size": 0.03})
    extra = {"encoder_file": {"task": "ClothFold"}, "extra": {"weight_copy": False}}
    save_policy(tmp_path / "a.pt", dt_config=cfg, **fields, **extra)
    PolicyHandle(**fields).save(tmp_path / "b.pt", cfg, **extra)
    a, b = load_checkpoint(tmp_path / "a.pt"), load_checkpoint(tmp_path / "b.pt")
    assert a.keys() == b.keys() and b["weight_copy"] is False and b["env_kwargs"] == {"picker_size": 0.03}
    for k in a:
        if k in ("actor", "normalizer"):
            assert a[k].keys() == b[k].keys() and all(same(a[k][n], b[k][n]) for n in a[k]), k
        else:
            assert a[k] == b[k], k


def same(x, y) -> bool:
    return torch.equal(x, y) if torch.is_tensor(x) else x == y


def tiny_teacher_and_encoder(tmp_path, *, horizon: int, encoder_scale: float = 1.0):
    """A tiny untrained ClothFold teacher saved under ``tmp_path`` (loaded) and a tiny encoder."""
    from trakdis.envs import task_spec

    spec = task_spec("ClothFold")
    cfg = DTConfig(embed_dim=16, n_layer=1, n_head=1, context_len=4, dropout=0.0).for_task(spec.state_dim,
                                                                                          spec.action_dim, horizon=horizon)
    save_policy(tmp_path / "policy.pt", kind="teacher", task="ClothFold", horizon=horizon, dt_config=cfg,
                actor=make_dt_actor(cfg, observation_key="state"), observation_key="state", target_return=-1.0,
                rtg_scale=1.0)
    encoder = NormalizedEncoder(StateEncoder(spec.state_dim, channels=(4, 4, 4, 4), hidden_dim=8),
                                torch.zeros(spec.state_dim), torch.full((spec.state_dim,), encoder_scale))
    return load_teacher(tmp_path), encoder


def test_student_rollout_steps(tmp_path):
    from trakdis.envs import task_spec
    from trakdis.policies import student_rollout_steps

    spec = task_spec("ClothFold")
    teacher, encoder = tiny_teacher_and_encoder(tmp_path, horizon=2)
    steps, metrics = student_rollout_steps(teacher, encoder, episodes=2, seed=0)
    assert set(steps.keys()) == {"pixels", "state"} and steps.batch_size == (4,)  # 2 episodes x 2 steps
    assert steps["pixels"].shape[1:] == (32, 32, 3) and steps["state"].shape[1:] == (spec.state_dim,)
    assert set(metrics) == {"normalized_performance", "corners_cm", "pickers_cm", "mae"}
    assert encoder.training  # the rollouts used a copy: the caller's encoder keeps its mode
    from trakdis.transforms import OutOfViewFill

    fill = OutOfViewFill.for_task("ClothFold")  # the labels of train_encoder.py --mask-unseen-pickers
    masked, _ = student_rollout_steps(teacher, encoder, episodes=2, seed=0, label_fill=fill)
    assert torch.equal(masked["pixels"], steps["pixels"]) and torch.equal(masked["state"], fill.mask(steps["state"]))


def test_weight_copy_episodes_in_worker_processes_are_the_serial_ones(tmp_path):
    """``parallel=True`` (``train_encoder.py --parallel``): the same episodes, stepped in 2 worker processes."""
    from trakdis.policies import student_rollout_steps, weight_copy_scores

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
    from trakdis.policies import weight_copy_race, weight_copy_scores

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
    from trakdis.policies import load_teacher_and_encoder
    from trakdis.transforms import OutOfViewFill, StateNormalizer

    cfg, actor = tiny_actor()
    enc = NormalizedEncoder(StateEncoder(15, channels=(4, 4, 4, 4), hidden_dim=8), torch.zeros(15), torch.ones(15))
    with pytest.raises(FileNotFoundError, match="--teacher"):
        load_teacher_and_encoder("latest", "latest", root=tmp_path)
    for recipe, name in (("online_dt", "t"), ("train_encoder", "e")):
        (tmp_path / recipe / name).mkdir(parents=True)
        (tmp_path / recipe / name / "config.json").write_text("{}")
    save_policy(tmp_path / "online_dt" / "t" / "policy.pt", kind="teacher", task="ClothFoldDiagonalPinned", horizon=10,
                dt_config=cfg, actor=actor, observation_key="state", target_return=-1.0, rtg_scale=1.0,
                normalizer=StateNormalizer(torch.zeros(15), torch.ones(15)))
    with pytest.raises(FileNotFoundError, match="--encoder"):
        load_teacher_and_encoder("latest", "latest", root=tmp_path)
    save_encoder(tmp_path / "train_encoder" / "e" / "encoder.pt", enc, task="ClothFoldDiagonalPinned")
    teacher, encoder, encoder_file, encoder_path = load_teacher_and_encoder("latest", "latest", root=tmp_path)
    assert teacher.kind == "teacher" and teacher.source == str(tmp_path / "online_dt" / "t" / "policy.pt")
    assert encoder_path == tmp_path / "train_encoder" / "e" / "encoder.pt" and encoder_file["task"] == teacher.task
    assert isinstance(encoder, NormalizedEncoder)
    save_encoder(tmp_path / "masked.pt", enc, task="ClothFoldDiagonalPinned",
                 extra={"mask_unseen_pickers": True,
                        "out_of_view_fill": OutOfViewFill.for_task("ClothFoldDiagonalPinned").state_dict()})
    with pytest.raises(ValueError, match="--mask-unseen-pickers"):  # a plain teacher, a masked encoder
        load_teacher_and_encoder(tmp_path / "online_dt" / "t", tmp_path / "masked.pt", root=tmp_path)
    save_encoder(tmp_path / "other.pt", enc, task="ClothFoldDiagonalUnpinned")
    with pytest.raises(ValueError, match="not ClothFoldDiagonalPinned"):  # an encoder of another task
        load_teacher_and_encoder("latest", tmp_path / "other.pt", root=tmp_path)


def test_masked_teacher_passes_its_fill_to_the_student_and_a_mismatched_encoder_is_refused(tmp_path):
    """--mask-unseen-pickers: the teacher file's normaliser carries the fill, the weight-copied
    student's normaliser keeps it; teacher and encoder must both be masked or neither."""
    from trakdis.policies import check_unseen_picker_mask, weight_copied_student
    from trakdis.transforms import OutOfViewFill, StateNormalizer

    cfg, actor = tiny_actor()
    fill = OutOfViewFill.for_task("ClothFoldDiagonalPinned")
    for name, f in (("masked", fill), ("plain", None)):
        save_policy(tmp_path / f"{name}.pt", kind="teacher", task="ClothFoldDiagonalPinned", horizon=10, dt_config=cfg,
                    actor=actor, observation_key="state", target_return=-0.5, rtg_scale=1.0,
                    normalizer=StateNormalizer(torch.zeros(15), torch.ones(15), fill=f))
    masked, plain = load_policy(tmp_path / "masked.pt"), load_policy(tmp_path / "plain.pt")
    assert masked.normalizer.fill == fill and plain.normalizer.fill is None
    student, _ = weight_copied_student(masked, torch.nn.Identity(), normalizer_keys=("state", "state_estimate"))
    assert student.normalizer.fill == fill and student.normalizer.keys == ("state", "state_estimate")
    x = torch.zeros(2, 15)
    x[1, 12:] = torch.tensor([0.0, 0.0, 0.3])  # out of view: the student reads the sentinel, like the teacher
    assert student.normalizer.normalize(x)[1, 12:].tolist() == pytest.approx([0.0, 0.0, 0.4])
    enc_masked = {"mask_unseen_pickers": True, "out_of_view_fill": fill.state_dict()}
    assert check_unseen_picker_mask(masked, enc_masked, encoder_source="enc.pt") is True
    assert check_unseen_picker_mask(plain, {}, encoder_source="enc.pt") is False  # earlier encoder files
    for teacher, enc in ((masked, {}), (plain, enc_masked), (masked, {"mask_unseen_pickers": False})):
        with pytest.raises(ValueError, match=rf"teacher {teacher.source} .*encoder enc\.pt .*--mask-unseen-pickers"):
            check_unseen_picker_mask(teacher, enc, encoder_source="enc.pt")
    other = {"mask_unseen_pickers": True,
             "out_of_view_fill": OutOfViewFill.for_task("ClothFoldDiagonalPinned", image_size=64).state_dict()}
    with pytest.raises(ValueError, match="different masks"):
        check_unseen_picker_mask(masked, other, encoder_source="enc.pt")
