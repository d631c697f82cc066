"""The student of a teacher and an encoder (trakdis.student): made, checked, rolled out and raced; its distillation's
options and the parts they make, the rollouts of DAgger's mixture, the run's state and its evaluations."""
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


# --------------------------------------------------------------------------- distillation (distill.py)
def test_student_config_checks_its_options():
    from trakdis.student import StudentConfig

    for kwargs, message in (({"episodes_per_round": 0, "expert_data": False}, "--episodes-per-round 0: distillation"),
                            ({"expert_coef": -1.0}, r"--expert-coef -1\.0: must be >= 0"),
                            ({"expert_coef": float("nan")}, "--expert-coef nan"),
                            ({"expert_coef": 1.0, "episodes_per_round": 2}, "the expert's actions exist on the expert"),
                            ({"estimate_noise": -1.0}, "--estimate-noise"), ({"kl_coef": -1.0}, "--kl-coef")):
        with pytest.raises(ValueError, match=message):
            StudentConfig(**kwargs)
    from trakdis.data import DataConfig

    with pytest.raises(ValueError, match="integrates the executed actions"):
        StudentConfig(picker_odometry="on", data=DataConfig(action_labels="expert"))
    StudentConfig(episodes_per_round=0, expert_data=False, distill=False)  # No-Distill: the expert data's own actions


def test_student_config_derived_options():
    from trakdis.data import DataConfig
    from trakdis.envs import task_defaults, task_spec
    from trakdis.student import StudentConfig

    cfg = StudentConfig()
    assert cfg.odometry and cfg.expert_actions and cfg.relabel_return_to_go and cfg.proprio_dims("ClothFold") == ()
    assert cfg.resolved_expert_coef("ClothFold") == task_defaults("ClothFold").expert_coef
    assert StudentConfig(expert_coef=0.25).resolved_expert_coef("ClothFold") == 0.25
    rollouts = StudentConfig(episodes_per_round=2, expert_data=False)
    assert not rollouts.expert_actions and rollouts.resolved_expert_coef("ClothFold") == 0.0
    assert not rollouts.relabel_return_to_go and StudentConfig(episodes_per_round=2, expert_data=False,
                                                               return_to_go="hindsight").relabel_return_to_go
    assert not StudentConfig(data=DataConfig(action_labels="expert")).odometry  # auto: no executed actions
    proprio = StudentConfig(proprio_pickers=True, picker_odometry="on")
    pickers = task_spec("ClothFold").state_groups["pickers"]
    assert not proprio.odometry and proprio.proprio_dims("ClothFold") == tuple(range(pickers.start, pickers.stop))


def test_student_config_makes_the_student_its_loss_and_the_acting_policies(tmp_path):
    from trakdis.modules import find_dt_actor
    from trakdis.objectives import DTDistillationLoss, MaskedOnlineDTLoss
    from trakdis.student import StudentConfig

    teacher, encoder = tiny_teacher_and_encoder(tmp_path, horizon=2)
    cfg = StudentConfig(proprio_pickers=True, episodes_per_round=2, act="mixed", kl_coef=0.5)
    student, dt_cfg = cfg.make_student(teacher, encoder)
    assert student.kind == "student" and student.encoder is encoder and student.proprio_dims == cfg.proprio_dims("ClothFold")
    assert not student.picker_odometry and dt_cfg == find_dt_actor(teacher.actor).config  # --proprio-pickers: no fusion
    for a, b in zip(teacher.actor.parameters(), student.actor.parameters()):  # --weight-copy
        assert torch.equal(a, b)
    loss = cfg.make_loss(student.actor, teacher.actor, action_eps=dt_cfg.action_eps, expert_coef=0.0)
    assert isinstance(loss, DTDistillationLoss)
    no_distill = StudentConfig(distill=False, expert_data=True)
    assert type(no_distill.make_loss(student.actor, teacher.actor, action_eps=dt_cfg.action_eps)) is MaskedOnlineDTLoss
    teacher_acting, student_acting = cfg.acting_policies(teacher, student, encoder)
    assert teacher_acting.kind == "teacher" and teacher_acting.encoder is encoder and student_acting is student
    assert teacher_acting.picker_odometry == cfg.odometry
    assert [h.kind for h in StudentConfig(episodes_per_round=2).acting_policies(teacher, student, encoder)] == ["teacher"]
    assert StudentConfig(episodes_per_round=2, act="student").acting_policies(teacher, student, encoder) == [student]
    assert StudentConfig().acting_policies(teacher, student, encoder) == []  # the expert data only: no rollouts
    assert StudentConfig(distill=False, episodes_per_round=2).acting_policies(teacher, student, encoder) == []


@pytest.mark.parametrize("distill,expert_data,odometry", [(True, True, "on"), (False, True, "off"), (True, False, "off")])
def test_student_config_loads_the_expert_data_through_the_encoder(tmp_path, monkeypatch, distill, expert_data, odometry):
    import trakdis.student as student_module
    from trakdis.student import StudentConfig
    from trakdis.transforms import PickerOdometry

    teacher, encoder = tiny_teacher_and_encoder(tmp_path, horizon=2)
    data = TensorDict({"state_estimate": torch.rand(3, 2, 18), "action": torch.rand(3, 2, 8) * 2 - 1,
                       "reward": torch.zeros(3, 2, 1), "state": torch.rand(3, 2, 18)}, batch_size=[3, 2])
    calls, lines = [], []

    def load(cfg, enc, *, task, horizon, seed, keys, log, progress):
        calls.append((enc, task, horizon, seed, keys))
        return data.clone(), torch.tensor([2, 2, 1]), tmp_path / "dataset"

    class Buffer:
        loaded = None

        def load_offline(self, episodes, lengths):
            self.loaded = (episodes, lengths)

    monkeypatch.setattr(student_module, "load_encoded_dataset", load)
    cfg = StudentConfig(distill=distill, expert_data=expert_data, episodes_per_round=2, picker_odometry=odometry)
    buffer = Buffer()
    cfg.load_expert_data(buffer, encoder, teacher, seed=4, log=lines.append)
    if distill and not expert_data:  # rollouts only
        assert calls == [] and buffer.loaded is None and lines == []
        return
    keys = ("action", "reward", "state") if distill else ("action", "reward")
    assert calls == [(encoder, "ClothFold", 2, 4, keys)] and torch.equal(buffer.loaded[1], torch.tensor([2, 2, 1]))
    expected = data["state_estimate"]
    if cfg.odometry:  # the picker estimates fused with the recorded actions, as the student reads them when acting
        expected = PickerOdometry.for_task("ClothFold", teacher.env_kwargs).filter(data["state_estimate"], data["action"])
    assert torch.equal(buffer.loaded[0]["state_estimate"], expected)
    assert lines == [f"{'--expert-data' if distill else '--no-distill'}: 3 expert episodes from {tmp_path / 'dataset'}"]


def test_dagger_rollouts_share_each_round_between_the_acting_policies(monkeypatch):
    """--act mixed: DAgger's decaying mixture (the teacher's share 1 - r / (rounds - 1)); each policy's episodes
    reseeded with seed + 1000 (r + 1) + 100 i, added to the buffer, their scores logged."""
    import trakdis.student as student_module
    from trakdis.student import DAggerRollouts

    played = []

    def run_episodes(env, policy, n, **kwargs):
        played.append((env, policy, n, kwargs["seed"], kwargs["deterministic"], kwargs["max_steps"]))
        return type("Results", (), {"episodes": [f"{env} episode"] * n, "final_performance": torch.full((n,), 0.5)})

    class Handle:
        def __init__(self, kind):
            self.kind = kind

        def make_policy(self):
            return f"{self.kind} policy"

    class Buffer:
        def __init__(self):
            self.added = []

        def add_episodes(self, episodes, keys):
            self.added.append((len(episodes), keys))

    monkeypatch.setattr(student_module, "run_episodes", run_episodes)
    buffer = Buffer()
    roll_out = DAggerRollouts([Handle("teacher"), Handle("student")], ["teacher env", "student env"], buffer,
                              episodes=4, rounds=3, horizon=6, seed=1, mixed=True)
    assert roll_out(0) == ({"rollout/teacher_normalized_performance": 0.5, "round": 1}, "rollout (teacher) 0.500")
    metrics, line = roll_out(1)
    assert metrics == {"rollout/teacher_normalized_performance": 0.5, "rollout/student_normalized_performance": 0.5,
                       "round": 2} and line == "rollout (teacher) 0.500, rollout (student) 0.500"
    roll_out(2)
    assert played == [("teacher env", "teacher policy", 4, 1001, True, 6), ("teacher env", "teacher policy", 2, 2001, True, 6),
                      ("student env", "student policy", 2, 2101, True, 6), ("student env", "student policy", 4, 3101, True, 6)]
    assert [n for n, _ in buffer.added] == [4, 2, 2, 4]
    assert buffer.added[0][1] == ("state", "state_estimate", "action", "return_to_go")
    teacher_only = DAggerRollouts([Handle("teacher")], ["env"], Buffer(), episodes=2, rounds=3, horizon=6, seed=1)
    assert teacher_only(2)[0] == {"rollout/teacher_normalized_performance": 0.5, "round": 3}
    assert DAggerRollouts([], [], Buffer(), episodes=0, rounds=3, horizon=6, seed=1)(0) == ({"round": 1}, "")


class EvalProtocol:
    """The part of EvalProtocol that StudentEvaluations uses: the mean score 0.1 x (evaluations so far)."""

    def __init__(self, episodes=2):
        self.episodes, self.calls = episodes, []

    def _results(self):
        mean = 0.1 * len(self.calls)
        return type("Results", (), {"summary": lambda self: {"mean": mean}})()

    def run(self, run, handle, env, **kwargs):
        results = self._results()
        self.calls.append(kwargs)
        return results

    def run_snapshot(self, run, handle, **kwargs):
        results = self._results()
        self.calls.append({"snapshot": handle, **kwargs})
        return results


def distill_run(tmp_path, name="s"):
    from dataclasses import dataclass as _dataclass

    from quadratic_loss import Quadratic
    from trakdis.optim import Updater
    from trakdis.student import distill_state
    from trakdis.utils.run import Run, RunConfig

    @_dataclass
    class Cfg(RunConfig):
        pass

    run = Run.start("toy", Cfg, ["--root", str(tmp_path), "--name", name, "--no-progress"])
    return run, distill_state(run, Updater(Quadratic(), optimizer="adam", lr=1e-2), torch.nn.Linear(1, 1))


@pytest.mark.parametrize("kept", [None, 2, 0, 1, "1 not on the curve"])
def test_student_evaluations_by_round_and_the_kept_snapshots_score(tmp_path, kept):
    """The student before training, after the rounds (every eval_every) and at the end; with a selection that kept
    an earlier round, that round's evaluation on the curve (logged again as eval_kept/) or a fresh one."""
    from trakdis.student import StudentEvaluations

    run, state = distill_run(tmp_path)
    assert dict(state) == {"rounds": 0, "updates": 0, "initial_eval": None, "teacher_eval": None, "round_evals": {}}
    assert set(state.objects) == {"updater", "buffer"} and state.step_key == "updates"
    protocol = EvalProtocol()
    handle = type("Handle", (), {"actor": torch.nn.Linear(1, 1), "task": "ClothFold"})()
    evaluations = StudentEvaluations(run, protocol, handle, "env", state)
    evaluations.teacher("teacher", parallel=True)
    evaluations.initial()
    evaluations.initial()  # once
    state["updates"] = 4
    if kept != "1 not on the curve":
        evaluations.after_round(1)
    state["updates"] = 8
    best = 1 if kept == "1 not on the curve" else kept
    selection = None if kept is None else type("Selection", (), {"finish": lambda self, rounds, log: best})()
    final = evaluations.final(2, selection)
    assert state["teacher_eval"] == 0.0 and state["initial_eval"] == pytest.approx(0.1)
    snapshot = protocol.calls[0]
    assert snapshot["snapshot"] == "teacher" and snapshot["prefix"] == "eval_teacher" and snapshot["parallel"]
    assert protocol.calls[1]["tag"] == "student before training" and protocol.calls[1]["keep_mode"] is handle.actor
    assert protocol.calls[1]["step"] == 0 and protocol.calls[1]["state_error_cm"] is not None
    last = {None: 0.3, 2: 0.3, 0: 0.1, 1: 0.2, "1 not on the curve": 0.3}[kept]
    if kept == "1 not on the curve":  # evaluated afresh at the end, as eval_kept/
        assert protocol.calls[-1]["prefix"] == "eval_kept" and protocol.calls[-1]["tag"] == "the kept student (round 1)"
        last = 0.3
    assert final == pytest.approx(last) and state["final_eval"] == final
    logged = run.logger.frame()
    if kept in (0, 1):  # the curve's evaluation, logged again at the last step
        assert logged.dropna(subset=["eval_kept/normalized_performance"])["step"].tolist() == [8]
    assert evaluations.report().startswith("eval normalized performance: teacher 0.000, student before 0.100, after")


def test_student_evaluations_without_episodes_evaluate_nothing(tmp_path):
    from trakdis.student import StudentEvaluations

    run, state = distill_run(tmp_path)
    protocol = EvalProtocol(episodes=0)
    evaluations = StudentEvaluations(run, protocol, type("Handle", (), {"actor": None, "task": "ClothFold"})(), None,
                                     state)
    evaluations.teacher("teacher")
    evaluations.initial()
    evaluations.after_round(1)
    kept = type("Selection", (), {"finish": lambda self, rounds, log: 0})()
    assert evaluations.final(2, kept) is None and protocol.calls == [] and state["round_evals"] == {1: None}
    assert evaluations.report() == ("eval normalized performance: teacher not evaluated, student before not evaluated, "
                                    "after not evaluated (0 episodes)")
