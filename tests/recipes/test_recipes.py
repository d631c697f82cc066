"""Every recipe runs end to end as a subprocess with a tiny configuration and leaves its files;
killed or stopped runs resume from their checkpoint with nothing lost or duplicated."""
import json
import os
import re
import shutil

import cv2
import pandas as pd
import pytest
import torch

from trakdis.utils.checkpoint import read_checkpoint
from trakdis.modules import EncoderEnsemble, find_dt_actor
from trakdis.policies import load_encoder, load_policy
from trakdis.transforms import normalizer_parts

from .conftest import (DATA, HORIZON, RECIPES, _env, distill_args, kill_when, load_recipe, online_dt_args,
                       run_recipe, start_recipe)


def read_log(run_dir):
    frame = pd.read_csv(run_dir / "log.csv")
    steps = frame["step"].tolist()
    assert steps == sorted(set(steps)), f"log steps not unique/increasing: {steps}"
    return frame


def test_collect_is_idempotent(workdir, dataset, monkeypatch, capsys):
    # A second call finds the finished dataset and does not collect again (in-process: no subprocess needed).
    monkeypatch.chdir(workdir)
    load_recipe("collect").main(["--horizon", str(HORIZON), "--episodes", "4", "--root", "datasets", "--no-progress"])
    out = capsys.readouterr().out
    assert "collecting" not in out and "4 episodes x 6 steps" in out


def test_online_dt_files_and_scores(teacher):
    for name in ("config.json", "log.csv", "curves.png", "checkpoint.pt", "policy.pt", "policy_offline.pt"):
        assert (teacher / name).exists(), name
    cfg = json.loads((teacher / "config.json").read_text())
    assert cfg["horizon"] == HORIZON and cfg["model"]["embed_dim"] == 16
    frame = read_log(teacher)
    evals = frame["eval/normalized_performance"].dropna()
    # after offline pretraining, after each online round but the last (eval_every=1), and at the end
    assert len(evals) == 3
    assert frame["eval_expert/normalized_performance"].notna().sum() == 1
    assert frame["train/loss_nll"].notna().sum() >= 4 and frame["step"].max() == 6 + 2 * 3
    assert frame["online/normalized_performance"].notna().sum() == 2
    ck = read_checkpoint(teacher / "checkpoint.pt")
    assert ck["step"] == 12 and ck["counters"]["rounds"] == 2 and ck["buffer"]["num_online_added"] == 4
    # default (DAgger): the buffer holds the demonstrations and every rollout
    assert ck["buffer"]["config"]["capacity"] == 4 + 2 * 2 and ck["buffer"]["online"].tolist() == [False] * 4 + [True] * 4
    assert frame["online/kept"].dropna().tolist() == [2, 2]
    handle = load_policy(teacher)
    assert handle.kind == "teacher" and handle.horizon == HORIZON and handle.observation_key == "state"
    # the grasp commands are left out of the DT's action tokens (--model.hidden-action-dims, default: the task's)
    assert find_dt_actor(handle.actor).config.hidden_action_dims == (3, 7) == read_checkpoint(teacher / "policy.pt")["dt_config"]["hidden_action_dims"]
    assert cv2.imread(str(teacher / "curves.png")) is not None
    # the phase table: expert 2, offline 2, rollouts 2 x 2, after round 1 (--eval-every 1) 2, final 2 episodes
    phases = json.loads((teacher / "phases.json").read_text())
    assert phases["episodes_simulated"] == 12 and phases["parallel"] is True
    assert {k: v["episodes"] for k, v in phases["phases"].items() if v["episodes"]} == {
        "evaluation (scripted expert, background)": 2, "evaluation (offline teacher, background)": 2,
        "online rollouts": 4, "evaluation (mid-run)": 2, "evaluation (final teacher)": 2}
    assert {k for k, v in phases["phases"].items() if v["background"]} == {
        "evaluation (scripted expert, background)", "evaluation (offline teacher, background)"}
    assert all(v["wall"] >= 0 and v["cpu"] >= 0 for v in phases["phases"].values())
    # the expert's scores are cached next to the datasets
    assert len(list((teacher.parents[2] / "datasets" / "expert_scores").glob("ClothFold_eval_h6_2ep_*.json"))) == 1


def test_online_dt_serial_envs_and_cached_expert_give_the_same_run(workdir, dataset, teacher):
    """--no-parallel (SerialEnv) plays the same episodes as the teacher fixture's worker processes,
    --no-background-eval evaluates the offline teacher in this process instead of the fixture's
    background process, and the expert's scores come from the cache the fixture wrote: the same log,
    row for row; the run ends with its phases and the episodes it simulated."""
    out = run_recipe(workdir, "online_dt", *online_dt_args("serial", "--no-parallel", "--no-background-eval"))
    assert "measured once, cached in datasets/expert_scores/ClothFold_eval_h6_2ep_" in out.stdout
    assert "episodes simulated: 10 (evaluation (offline teacher) 2, online rollouts 4, evaluation (mid-run) 2, " \
           "evaluation (final teacher) 2)" in out.stdout
    table = out.stdout[out.stdout.index("phases ("):]
    for phase in ("offline training", "online updates", "online rollouts", "evaluation (final teacher)", "total"):
        assert f"\n{phase} " in table, phase
    assert "expert evaluation" not in table
    assert "online - offline" in out.stdout and "(paired: the same 2 eval episodes)" in out.stdout
    pd.testing.assert_frame_equal(read_log(teacher), read_log(workdir / "runs" / "online_dt" / "serial"),
                                  check_exact=False, atol=1e-5, check_like=True)  # columns in logging order


def test_online_dt_dagger_learns_the_experts_action_on_its_rollouts(workdir, dataset, teacher):
    """The default --online-labels expert (DAgger): the buffer keeps every rollout beside the demonstrations, each
    step labelled with the scripted expert's action at its state and step; the demonstrations' label is their own
    action, so the offline phase is that of --online-labels executed (Online DT), update for update."""
    from trakdis.envs import expert_action

    buffer = read_checkpoint(teacher / "checkpoint.pt")["buffer"]
    assert "expert_action" in buffer["config"]["keys"]
    stored = buffer["replay_buffer"]["_storage"]["_storage"]
    state, action, label = stored["state"], stored["action"], stored["expert_action"]
    steps = torch.arange(HORIZON).expand(*state.shape[:2]).unsqueeze(-1)
    want = torch.as_tensor(expert_action("ClothFold", state.numpy(), steps.numpy()))
    torch.testing.assert_close(label[4:], want[4:])
    assert torch.equal(label[:4], action[:4]) and (label[4:] - action[4:]).abs().max() > 0.1
    run_recipe(workdir, "online_dt", *online_dt_args("executed", "--online-labels", "executed", "--eval-every", 0))
    run_dir = workdir / "runs" / "online_dt" / "executed"
    plain = read_checkpoint(run_dir / "checkpoint.pt")["buffer"]
    # Online DT: as many slots as demonstrations; a rollout enters only by beating the worst one
    assert plain["config"]["capacity"] == 4 and plain["config"]["replacement"] == "lowest_return"
    assert "expert_action" not in plain["config"]["keys"]
    kept = read_log(run_dir)["online/kept"].dropna()
    assert len(kept) == 2 and kept.between(0, 2).all() and plain["online"].sum() <= kept.sum()
    dagger, plain = read_log(teacher), read_log(run_dir)
    offline = lambda f: f.loc[f["phase"] == 0, ["step", "train/loss_nll"]].dropna().reset_index(drop=True)  # noqa: E731
    assert len(offline(plain)) >= 3
    pd.testing.assert_frame_equal(offline(plain), offline(dagger), check_exact=False, atol=1e-5)
    assert (dagger.loc[dagger["phase"] == 1, "train/loss_nll"].dropna().to_numpy()
            != plain.loc[plain["phase"] == 1, "train/loss_nll"].dropna().to_numpy()).all()


def test_online_dt_damaged_expert_cache_is_an_error_naming_it(workdir, dataset):
    import subprocess
    import sys

    from trakdis.evaluation import expert_score_key, expert_score_path
    from trakdis.utils.phases import available_workers

    key = expert_score_key(task="ClothFold", split="eval", horizon=HORIZON, episodes=2, seed=10_000,
                           num_envs=available_workers())
    path = expert_score_path(workdir / "damaged", key)
    path.parent.mkdir(parents=True)
    path.write_text('{"format": "trakdis-expert-scores", "version": 1, "key": ')  # cut short
    args = online_dt_args("damaged", "--data.path", dataset.relative_to(workdir), "--data.root", "damaged")
    cmd = [sys.executable, str(RECIPES / "online_dt.py"), *map(str, args)]
    proc = subprocess.run(cmd, cwd=workdir, env=_env(), capture_output=True, text=True, timeout=240)
    assert proc.returncode != 0
    assert f"expert score cache damaged/expert_scores/{path.name}: not valid JSON" in proc.stderr
    assert "delete the file to measure the expert again" in proc.stderr


def test_online_dt_offline_control(workdir, dataset):
    """--offline-control: the same rollouts, updates and evaluations, but no rollout enters the buffer, so the
    rollouts' labels (DAgger's, the default, or the executed ones) are never read: the same run with either. With
    --select-episodes (early stopping) the offline teacher and round 1 play the same train-split episodes and
    the kept one is the final teacher: its weights in policy.pt, its scores the final ones."""
    args = ("--offline-control", "--online-rounds", 1, "--expert-episodes", 0, "--online-lr", 1e-4, "--train-state-noise", 0.01,
            "--select-episodes", 2, "--select-every", 1)
    run_recipe(workdir, "online_dt", *online_dt_args("control", *args))
    run_recipe(workdir, "online_dt", *online_dt_args("control-executed", *args, "--online-labels", "executed"))
    pd.testing.assert_frame_equal(read_log(workdir / "runs" / "online_dt" / "control"),
                                  read_log(workdir / "runs" / "online_dt" / "control-executed"))
    run_dir = workdir / "runs" / "online_dt" / "control"
    ck = read_checkpoint(run_dir / "checkpoint.pt")
    assert ck["counters"]["rounds"] == 1 and ck["buffer"]["num_online_added"] == 0
    selection, policy = ck["counters"]["selection"], read_checkpoint(run_dir / "policy.pt")
    assert sorted(selection["scores"]) == [0, 1] and all(len(v) == 2 for v in selection["scores"].values())
    assert policy["selected_round"] == selection["best"] and set(policy["selection_scores"]) == {0, 1}
    for k, v in selection["state_dict"].items():
        assert torch.equal(policy["actor"][k], v), k
    if selection["best"] == 0:  # the offline teacher kept: its evaluation is the final one
        assert ck["counters"]["final_scores"] == ck["counters"]["offline_scores"]
    assert ck["counters"]["expert_eval"] is None  # --expert-episodes 0: the expert not evaluated
    frame = read_log(run_dir)
    assert frame["online/normalized_performance"].notna().sum() == 1
    online_lr = frame.loc[frame["step"] > 6, "train/lr"].dropna()  # after the 6 offline updates
    assert len(online_lr) and (online_lr == 1e-4).all()
    assert json.loads((run_dir / "config.json").read_text())["train_state_noise"] == 0.01


def test_online_dt_sigkill_then_resume_matches_uninterrupted(workdir, dataset, teacher):
    """SIGKILL the run as soon as its first checkpoint exists, resume it: the log (losses, online
    rollouts, evaluations) equals the uninterrupted run's, row for row."""
    run_dir = workdir / "runs" / "online_dt" / "killed"
    proc = start_recipe(workdir, "online_dt", *online_dt_args("killed"))
    kill_when(proc, lambda: (run_dir / "checkpoint.pt").exists())
    assert not (run_dir / "policy.pt").exists()
    step = read_checkpoint(run_dir / "checkpoint.pt")["step"]
    out = run_recipe(workdir, "online_dt", "--resume", "--name", "killed")
    assert f"from step {step}" in out.stdout
    assert (run_dir / "policy.pt").exists()
    pd.testing.assert_frame_equal(read_log(teacher), read_log(run_dir), check_exact=False, atol=1e-5,
                                  check_like=True)  # columns in logging order


def test_train_encoder_stop_resume(workdir, dataset, encoder):
    assert (encoder / "encoder.pt").exists() and (encoder / "curves.png").exists()
    frame = read_log(encoder)
    assert frame["step"].tolist() == [1, 2] and frame["val/mae"].notna().all()
    run_recipe(workdir, "train_encoder", "--name", "enc2", "--horizon", HORIZON, *DATA, "--epochs", 2,
               "--batch-size", 8, "--channels", 4, 4, 4, 4, "--hidden-dim", 16, "--no-aug", "--stop-after", 1)
    run_dir = workdir / "runs" / "train_encoder" / "enc2"
    assert not (run_dir / "encoder.pt").exists()
    out = run_recipe(workdir, "train_encoder", "--resume", "--name", "enc2")
    assert "from step 1" in out.stdout and "epoch 2/2" in out.stdout and "epoch 1/2" not in out.stdout
    assert read_log(run_dir)["step"].tolist() == [1, 2]
    assert json.loads((run_dir / "config.json").read_text())["aug"] is False


def test_train_encoder_with_teacher_resumes_exactly(workdir, dataset, teacher):
    """With --teacher (student rounds), a run stopped after its first epoch and resumed saves the uninterrupted run's
    encoder bit for bit: building the teacher's modules draws from the RNG, so the checkpoint's streams are restored
    after it (restored before it, the resumed encoder differed from its second epoch on)."""
    args = ["--horizon", HORIZON, *DATA, "--epochs", 2, "--batch-size", 8, "--channels", 4, 4, 4, 4, "--hidden-dim", 16,
            "--threads", 1, "--teacher", "runs/online_dt/teacher", "--student-rounds", 1, "--student-episodes", 1,
            "--student-epochs", 1]
    run_recipe(workdir, "train_encoder", "--name", "enc_t_full", *args)
    run_recipe(workdir, "train_encoder", "--name", "enc_t_cut", *args, "--stop-after", 1)
    out = run_recipe(workdir, "train_encoder", "--resume", "--name", "enc_t_cut")
    assert "from step 1" in out.stdout and "student round 1/1" in out.stdout
    runs = workdir / "runs" / "train_encoder"
    full, cut = (read_checkpoint(runs / name / "encoder.pt")["state_dict"] for name in ("enc_t_full", "enc_t_cut"))
    assert full.keys() == cut.keys() and all(torch.equal(full[k], cut[k]) for k in full)
    pd.testing.assert_frame_equal(read_log(runs / "enc_t_full"), read_log(runs / "enc_t_cut"), check_like=True)


def test_train_encoder_cosine_schedule_resumes(workdir, dataset):
    """--lr-schedule cosine: the learning rate falls to 0 at the last epoch, also across a --stop-after /
    --resume (the schedule's state is in the checkpoint; a fresh one would end at a quarter of --lr)."""
    args = ["--name", "enc_cos", "--horizon", HORIZON, *DATA, "--epochs", 3, "--batch-size", 8, "--channels", 4, 4, 4, 4,
            "--hidden-dim", 16, "--lr", 1e-3, "--lr-schedule", "cosine"]
    run_recipe(workdir, "train_encoder", *args, "--stop-after", 1)
    run_dir = workdir / "runs" / "train_encoder" / "enc_cos"
    after_one = read_checkpoint(run_dir / "checkpoint.pt")
    assert after_one["optim"]["param_groups"][0]["lr"] == pytest.approx(1e-3 * 0.75)  # (1 + cos(pi / 3)) / 2
    run_recipe(workdir, "train_encoder", "--resume", "--name", "enc_cos")
    final = read_checkpoint(run_dir / "checkpoint.pt")
    assert final["schedule"]["last_epoch"] == 3
    assert final["optim"]["param_groups"][0]["lr"] == pytest.approx(0.0, abs=1e-12)
    assert (run_dir / "encoder.pt").exists()


def test_train_encoder_extra_noisy_data_and_keypoint_layout(workdir, dataset):
    """--extra-noise and --extra-aim-error collect (once) and add a noisier and a misled expert's dataset to the
    training images only; the keypoint layout trains, saves its options and reports the error per state group in cm."""
    out = run_recipe(workdir, "train_encoder", "--name", "enc_extra", "--horizon", HORIZON, *DATA, "--epochs", 1,
                     "--batch-size", 8, "--channels", 4, 4, 4, 4, "--hidden-dim", 16, "--extra-noise", 0.4,
                     "--extra-aim-error", 0.03, "--head", "keypoints", "--stem-stride", 1, "--coord-channels")
    assert (workdir / "datasets" / f"ClothFold_4ep_h{HORIZON}_noise0.4_px32" / "meta.json").exists()
    aimed = workdir / "datasets" / f"ClothFold_4ep_h{HORIZON}_noise0.15_aim0.03_px32"
    assert json.loads((aimed / "meta.json").read_text())["config"]["aim_error"] == 0.03
    # 4 episodes of 6 steps: 3 train + 1 validation from the main dataset, + 4 noisy and 4 misled ones for training
    assert f"{11 * HORIZON} training / {HORIZON} validation images" in out.stdout
    assert out.stdout.count(f"training images +{4 * HORIZON} from") == 2
    assert "corners" in out.stdout and "pickers" in out.stdout
    saved = read_checkpoint(workdir / "runs" / "train_encoder" / "enc_extra" / "encoder.pt")
    assert saved["encoder_kwargs"]["head"] == "keypoints" and set(saved["val_error_cm"]) == {"corners_cm", "pickers_cm"}


def test_distill_files_and_resume(workdir, student):
    for name in ("config.json", "log.csv", "curves.png", "checkpoint.pt", "policy.pt"):
        assert (student / name).exists(), name
    frame = read_log(student)
    assert frame["train/loss_distill"].notna().sum() == 2
    assert frame["eval_teacher/normalized_performance"].notna().sum() == 1
    assert frame["eval/normalized_performance"].notna().sum() == 3  # before, after rounds 1 and 2 (the curve)
    # early stopping: the copy and the students after rounds 1 and 2 played 2 train-split episodes each
    assert frame.dropna(subset=["selection/normalized_performance"])["step"].tolist() == [0, 2, 4]  # 2 updates a round
    saved = read_checkpoint(student / "policy.pt")
    assert list(saved["selection_scores"]) == [0, 1, 2] and saved["selected_round"] in (0, 1, 2)
    assert saved["select_episodes"] == 2  # given: the task's default (TaskDefaults.select_episodes) does not apply
    assert saved["expert_coef"] == 0.0  # rollouts in the data: the task's default (TaskDefaults.expert_coef) does not apply
    assert saved["picker_odometry"] is True  # the default (--picker-odometry auto, executed actions)
    handle = load_policy(student)
    assert handle.picker_odometry and any(type(t).__name__ == "PickerOdometry" for t in handle.make_env().transform)
    assert handle.kind == "student" and handle.observation_key == "state_estimate" and handle.encoder is not None
    assert find_dt_actor(handle.actor).config.hidden_action_dims == (3, 7)  # the teacher's architecture
    run_recipe(workdir, "distill", *distill_args("student2", "--stop-after", 1))
    out = run_recipe(workdir, "distill", "--resume", "--name", "student2")
    assert "from step 2" in out.stdout
    a, b = read_log(student), read_log(workdir / "runs" / "distill" / "student2")
    assert a["step"].tolist() == b["step"].tolist()
    resumed = read_checkpoint(workdir / "runs" / "distill" / "student2" / "policy.pt")
    assert list(resumed["selection_scores"]) == [0, 1, 2]  # round 1's score came back from the checkpoint


def test_distill_curve_ends_with_the_last_round(workdir, teacher, encoder):
    """The curve (eval/) ends with the last round's weights; the kept snapshot's score (here the copy's:
    no later snapshot can beat it by 1e9 standard errors) is logged as eval_kept/ at the same step, reused
    from the curve's first point, and the saved policy is the copy."""
    out = run_recipe(workdir, "distill", *distill_args("kept", "--select-margin", "1e9", "--no-eval-teacher",
                                                        "--eval-every", 0))
    frame = read_log(workdir / "runs" / "distill" / "kept")
    curve = frame.dropna(subset=["eval/normalized_performance"])
    assert curve["step"].tolist() == [0, 4]  # the copy, then the last round (2 rounds x 2 updates)
    kept = frame.dropna(subset=["eval_kept/normalized_performance"])
    assert kept["step"].tolist() == [4]
    assert kept["eval_kept/normalized_performance"].item() == curve["eval/normalized_performance"].iloc[0]
    assert "the kept student (round 0)" in out.stdout
    saved = read_checkpoint(workdir / "runs" / "distill" / "kept" / "policy.pt")
    copy = read_checkpoint(workdir / "runs" / "online_dt" / "teacher" / "policy.pt")
    assert saved["selected_round"] == 0
    assert all(torch.equal(saved["actor"][k], v) for k, v in copy["actor"].items())  # the weight copy, unchanged


def test_distill_kept_middle_round_is_evaluated(workdir, teacher, encoder, monkeypatch):
    """A kept snapshot that is neither the copy nor on the curve (round 1 of 2, no evaluation between rounds) is
    evaluated afresh as eval_kept/ at the last step, after the curve's last point (round 2's weights); its score is the
    run's final one. In process, the selection's scores forced: round 1 beats the copy, round 2 does not beat round 1."""
    distill = load_recipe("distill")

    class ForcedSelection(distill.SnapshotSelection):
        def __init__(self, module, score, state, **kwargs):
            super().__init__(module, lambda step: [1.0, 1.0] if step == 1 else [0.0, 0.0], state, **kwargs)

    monkeypatch.setattr(distill, "SnapshotSelection", ForcedSelection)
    monkeypatch.chdir(workdir)
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))
    state = distill.main([str(a) for a in distill_args("middle", "--no-eval-teacher", "--eval-every", 0,
                                                         "--episodes-per-round", 0, "--no-progress",
                                                         "--picker-odometry", "off")])
    frame = read_log(workdir / "runs" / "distill" / "middle")
    assert frame.dropna(subset=["eval/normalized_performance"])["step"].tolist() == [0, 4]
    kept = frame.dropna(subset=["eval_kept/normalized_performance"])
    assert kept["step"].tolist() == [4] and kept["eval_kept/normalized_performance"].item() == state["final_eval"]
    saved = read_checkpoint(workdir / "runs" / "distill" / "middle" / "policy.pt")
    assert saved["selected_round"] == 1
    assert saved["expert_coef"] == 1.0  # the expert data alone: ClothFold's default (TaskDefaults.expert_coef)
    assert frame["train/loss_expert"].notna().sum() == 2
    assert saved["picker_odometry"] is False  # --picker-odometry off: the default (on) does not apply


def test_distill_ablations(workdir, teacher, encoder):
    out = run_recipe(workdir, "distill", *distill_args("ablation", "--no-weight-copy", "--no-distill",
                                                        "--estimate-noise", "1e-3", "--no-eval-teacher",
                                                        "--proprio-pickers"))
    assert "expert imitation" in out.stdout and "weight copy False" in out.stdout
    frame = read_log(workdir / "runs" / "distill" / "ablation")
    assert frame["train/loss_nll"].notna().sum() == 2 and "train/loss_distill" not in frame.columns
    ck = read_checkpoint(workdir / "runs" / "distill" / "ablation" / "policy.pt")
    assert ck["distill"] is False and ck["weight_copy"] is False and ck["estimate_noise"] == 1e-3
    assert ck["proprio_dims"] == list(range(12, 18))  # ClothFold: two pickers after the 4 corners
    assert load_policy(workdir / "runs" / "distill" / "ablation").proprio_dims == tuple(range(12, 18))
    assert ck["picker_odometry"] is False  # off with --proprio-pickers: proprioception gives the pickers
    # fresh weights are no candidate of the selection: the rounds' snapshots alone are scored
    assert list(ck["selection_scores"]) == [1, 2] and ck["selected_round"] in (1, 2)


def test_distill_the_papers_no_distill_starts_from_fresh_weights(workdir, teacher, encoder):
    """The paper's No-Distill (trakdis.method.no_distill_stage_args on the tiny teacher's and student's
    configurations): the expert's actions (the DT's NLL, no teacher label) over the teacher's offline updates, the
    last round kept; its student starts from weights other than the teacher's (a run of no rounds saves them)."""
    from trakdis.method import no_distill_stage_args
    from trakdis.utils.config import load_config, parse_config

    teacher_cfg = load_config(load_recipe("online_dt").OnlineDTConfig, teacher / "config.json")
    args = [str(a) for a in distill_args("paper_nd", "--no-eval-teacher", "--eval-every", 0, "--episodes-per-round", 0)]
    flags = no_distill_stage_args(teacher_cfg, parse_config(load_recipe("distill").DistillConfig, args))
    assert flags[:4] == ["--no-weight-copy", "--no-distill", "--updates-per-round", "3"]  # 6 offline updates, 2 rounds
    out = run_recipe(workdir, "distill", *args, *flags)
    assert "expert imitation" in out.stdout and "weight copy False" in out.stdout
    frame = read_log(workdir / "runs" / "distill" / "paper_nd")
    assert frame["train/loss_nll"].notna().sum() == 2 and "train/loss_distill" not in frame.columns
    assert "selection/normalized_performance" not in frame.columns  # --select-episodes 0: the last round
    assert frame["step"].max() == teacher_cfg.offline_updates
    ck = read_checkpoint(workdir / "runs" / "distill" / "paper_nd" / "policy.pt")
    assert (ck["weight_copy"], ck["distill"], ck["expert_coef"], ck["selected_round"]) == (False, False, 0.0, None)
    fresh_args = distill_args("paper_nd0", "--no-eval-teacher", "--eval-episodes", 0, "--episodes-per-round", 0)
    run_recipe(workdir, "distill", *fresh_args, *flags, "--rounds", 0)
    fresh = read_checkpoint(workdir / "runs" / "distill" / "paper_nd0" / "policy.pt")["actor"]
    copy = read_checkpoint(teacher / "policy.pt")["actor"]
    weights = [k for k, v in copy.items() if v.is_floating_point() and v.dim() == 2]
    assert fresh.keys() == copy.keys() and weights
    assert not any(torch.equal(fresh[k], copy[k]) for k in weights)  # not one weight matrix is the teacher's


def test_distill_dagger_mixture_and_expert_data(workdir, teacher, encoder):
    # DAgger's mixture: the teacher drives the first round, the student the last
    run_recipe(workdir, "distill", *distill_args("mixed", "--act", "mixed", "--teacher-context", "step",
                                                  "--no-eval-teacher", "--eval-every", 0))
    frame = read_log(workdir / "runs" / "distill" / "mixed")
    rounds = frame[frame["round"].notna()]
    assert rounds["rollout/teacher_normalized_performance"].notna().tolist() == [True, False]
    assert rounds["rollout/student_normalized_performance"].notna().tolist() == [False, True]
    # the expert dataset alone, with the teacher's labels; the pickers fused with the commands
    out = run_recipe(workdir, "distill", *distill_args("offline", "--expert-data", "--episodes-per-round", 0,
                                                        "--no-eval-teacher", "--eval-every", 0, *DATA,
                                                        "--picker-odometry", "on",
                                                        "--select-episodes", "None",  # the task's default
                                                        "--expert-coef", 0.5))  # the expert's actions as well
    assert "--expert-data" in out.stdout
    frame = read_log(workdir / "runs" / "distill" / "offline")
    assert frame["train/loss_distill"].notna().sum() == 2 and not any(c.startswith("rollout/") for c in frame.columns)
    assert frame["train/loss_expert"].notna().sum() == 2
    assert frame["eval/normalized_performance"].notna().sum() == 2  # acted with PickerOdometry in its env
    handle = load_policy(workdir / "runs" / "distill" / "offline")
    saved = read_checkpoint(workdir / "runs" / "distill" / "offline" / "policy.pt")
    assert handle.picker_odometry and saved["picker_odometry"]
    # ClothFold's default: no selection episodes, the last round's student kept
    assert saved["select_episodes"] == 0 and saved["selected_round"] is None and "selection/" not in " ".join(frame.columns)
    env = handle.make_env()  # not started: nothing to close
    assert any(type(t).__name__ == "PickerOdometry" for t in env.transform)
    # --episodes-per-round 0 --no-expert-data: refused while parsing (test_bad_options_are_refused_...)


def test_evaluate_student_and_expert(workdir, student):
    run_recipe(workdir, "evaluate", "--name", "ev", "--policy", "runs/distill/student", "--trials", 3,
               "--noise-levels", 0, 1e-3, "--videos", 1, "--video-size", 64, "--threads", 1)
    run_dir = workdir / "runs" / "evaluate" / "ev"
    summary = pd.read_csv(run_dir / "summary.csv")
    assert summary["state_noise"].tolist() == [0.0, 1e-3] and (summary["n"] == 3).all()
    assert {"mean", "std", "p25", "p50", "p75"} <= set(summary.columns)
    episodes = pd.read_csv(run_dir / "episodes.csv")
    assert len(episodes) == 6 and (episodes["length"] == HORIZON).all()
    # where each picker first closed, and whether its corner was lifted (trakdis.evaluation.grasp_report)
    assert {"picker0_first_close_cm", "picker0_corner_lifted", "picker1_first_close_cm"} <= set(episodes.columns)
    # for a policy reading an estimate, what it believed at that first close (the decision the encoder serves)
    assert {"picker0_close_estimate_cm", "picker1_close_offset_error_cm"} <= set(episodes.columns)
    # the encoder's error on the states each episode visited, per state group
    assert (episodes["encoder_corners_cm"] > 0).all() and (episodes["encoder_pickers_cm"] > 0).all()
    assert summary["mean"].iloc[0] == pytest.approx(episodes[episodes.state_noise == 0]["final_normalized_performance"].mean())
    md = (run_dir / "summary.md").read_text()
    assert md.startswith("| task | policy | state_noise | n | mean") and "| ClothFold | student |" in md
    videos = list((run_dir / "videos").iterdir())
    assert len(videos) == 1 and videos[0].stat().st_size > 0
    cap = cv2.VideoCapture(str(videos[0]))
    ok, frame = cap.read()
    assert ok and frame.shape[0] == 64 and frame.shape[1] == 64 + 4 + 64  # render | 32x32 view upscaled

    run_recipe(workdir, "evaluate", "--name", "ev_expert", "--policy", "expert", "--task", "ClothFold",
               "--horizon", HORIZON, "--trials", 2, "--videos", 0)
    summary = pd.read_csv(workdir / "runs" / "evaluate" / "ev_expert" / "summary.csv")
    assert summary["policy"].tolist() == ["expert"] and summary["n"].tolist() == [2]


@pytest.mark.parametrize("recipe,flags", [
    ("collect", ["--episodes", "--no-pixels"]),
    ("online_dt", ["--preset", "--model.embed-dim", "--offline-updates", "--exploration-rtg", "--resume",
                   "--mask-unseen-pickers"]),
    ("train_encoder", ["--no-aug", "--val-fraction", "--mask-unseen-pickers"]),
    ("distill", ["--no-weight-copy", "--no-distill", "--estimate-noise"]),
    ("evaluate", ["--trials", "--noise-levels", "--videos"]),
])
def test_help(recipe, flags, capsys):
    with pytest.raises(SystemExit) as exc:
        load_recipe(recipe).main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for flag in flags:
        assert flag in out, flag


def test_paper_preset_config():
    from trakdis.modules import DTModelConfig
    from trakdis.utils.config import parse_config

    module = load_recipe("online_dt")
    cfg = parse_config(module.OnlineDTConfig, ["--preset", "paper", "--model.n-layer", "1", "--data.episodes", "4"],
                      presets=module.PRESETS)
    assert (cfg.model.embed_dim, cfg.model.n_layer, cfg.model.n_head, cfg.model.context_len) == (256, 1, 16, 30)
    assert cfg.optimizer == "lamb" and cfg.lr == 1e-4 and cfg.weight_decay == 1e-4 and cfg.eval_rtg == -1.0
    assert cfg.data.episodes == 4  # explicit flags win over the preset
    dt = cfg.model.for_task(18, 8, horizon=100)
    assert (dt.embed_dim, dt.n_head, dt.context_len, dt.dropout, dt.attn_dropout) == (256, 16, 30, 0.1, 0.1)
    assert cfg.online_labels == "executed" and cfg.model.log_std_min == -2.5  # Online DT; DTModelConfig's floor
    cfg = parse_config(module.OnlineDTConfig, ["--preset", "cpu"], presets=module.PRESETS)
    assert (cfg.data.episodes, cfg.offline_updates, cfg.online_labels, cfg.eval_episodes) == (200, 6000, "expert", 100)
    assert (cfg.select_episodes, cfg.select_every) == (30, 8)
    assert cfg.model == DTModelConfig()  # the library's default model, not the main job's log-std floor
    main_job = module.OnlineDTConfig()
    assert (main_job.data.episodes, main_job.model.log_std_min, main_job.online_labels) == (20, -1.5, "expert")
    module = load_recipe("distill")
    cfg = parse_config(module.DistillConfig, ["--preset", "paper"], presets=module.PRESETS)
    assert cfg.rounds == 60 and cfg.optimizer == "lamb"


def test_distill_picker_odometry_auto_on_with_executed_actions():
    """--picker-odometry auto: on where the data's actions are the executed ones (every task); on / off win; never
    with --proprio-pickers."""
    from trakdis.utils.config import parse_config

    module = load_recipe("distill")

    def odometry(*argv: str) -> bool:
        return parse_config(module.DistillConfig, list(argv)).odometry

    assert odometry() is True and odometry("--picker-odometry", "on") is True
    assert odometry("--data.action-labels", "expert") is False  # auto: no executed actions to integrate
    assert odometry("--picker-odometry", "off") is False
    assert odometry("--picker-odometry", "on", "--proprio-pickers") is False
    assert odometry("--proprio-pickers") is False


def test_model_section_is_the_dt_config_and_old_run_configs_load():
    """``--model.*`` is DTModelConfig itself: the recipes' defaults, and the ``model`` section of a
    config.json written when it was a separate ModelConfig (7 keys) loads into the same model."""
    from trakdis.modules import DTModelConfig
    from trakdis.utils.config import config_from_dict, config_to_dict

    module = load_recipe("online_dt")
    d = module.OnlineDTConfig().model.for_task(18, 8, horizon=100)
    assert (d.embed_dim, d.n_layer, d.n_head, d.context_len, d.dropout, d.attn_dropout, d.loc_bound, d.log_std_min,
            d.max_timestep) == (64, 2, 2, 20, 0.0, 0.0, 5.0, -1.5, 1024)  # the main job's floor (DTModelConfig's: -2.5)
    assert module.OnlineDTConfig().model.for_task(18, 8, horizon=2000).max_timestep == 2001
    old = config_to_dict(module.OnlineDTConfig())
    old["model"] = {"embed_dim": 16, "n_layer": 1, "n_head": 1, "context_len": 4, "dropout": 0.1, "loc_bound": 5.0,
                    "log_std_min": -2.5}
    dt = config_from_dict(module.OnlineDTConfig, old).model.for_task(18, 8, horizon=6)
    assert dt == DTModelConfig(state_dim=18, action_dim=8, embed_dim=16, n_layer=1, n_head=1, context_len=4,
                               dropout=0.1, attn_dropout=0.1, loc_bound=5.0, log_std_min=-2.5, max_timestep=1024,
                               hidden_action_dims=())
    assert DTModelConfig(**dt.to_dict()) == dt  # a policy file's dt_config
    # an old section has no hidden_action_dims: the recipe's default for the task applies (docs/design.md)
    old_model = config_from_dict(module.OnlineDTConfig, old).model
    assert old_model.hidden_action_dims is None
    # a run saved before --online-labels existed resumes with the labels it ran with, not today's default (DAgger)
    assert config_from_dict(module.OnlineDTConfig, old).online_labels == "expert"
    assert config_from_dict(module.OnlineDTConfig, {k: v for k, v in old.items() if k != "online_labels"}
                            ).online_labels == "executed"
    assert old_model.for_task(18, 8, horizon=6, hidden_action_dims=(3, 7)).hidden_action_dims == (3, 7)


@pytest.mark.parametrize("recipe,args,message", [
    ("evaluate", ["--task", "ClothFold", "--noise-levels", "-1"], r"--noise-levels -1\.0: every noise level must be a finite std >= 0"),
    ("evaluate", ["--task", "ClothFold", "--noise-levels", "0", "nan"], r"--noise-levels nan"),
    ("evaluate", ["--task", "ClothFold", "--horizon", "0"], r"--horizon 0"),
    ("evaluate", ["--task", "ClothFold", "--hold-radius", "-0.1"], r"--hold-radius must be a finite number >= 0 and < 1, got -0\.1"),
    ("distill", ["--hold-radius", "0.02", "--picker-odometry", "off"], r"held corner is part of the picker odometry"),
    ("online_dt", ["--horizon", "0"], r"--horizon 0"),
    ("online_dt", ["--expert-episodes", "-1"], r"--expert-episodes -1: must be >= 0"),
    ("distill", ["--episodes-per-round", "0", "--no-expert-data"], r"--episodes-per-round 0: distillation needs"),
    ("distill", ["--picker-odometry", "on", "--data.action-labels", "expert"], r"integrates the executed actions"),
    ("distill", ["--expert-coef", "1", "--no-distill"], r"--expert-coef 1\.0: the expert's actions exist on the expert"),
    ("distill", ["--expert-coef", "1", "--episodes-per-round", "2"], r"--expert-coef 1\.0"),
    ("distill", ["--expert-coef", "-1"], r"--expert-coef -1\.0: must be >= 0"),
    ("train_encoder", ["--members", "0"], r"--members 0: need at least 1 encoder"),
    ("train_encoder", ["--select-episodes", "3", "--teacher", "t.pt"], r"--select-episodes 3: needs --members >= 2"),
    ("train_encoder", ["--select-episodes", "3", "--members", "2"], r"and --teacher"),
])
def test_bad_options_are_refused_before_anything_is_written(tmp_path, monkeypatch, capsys, recipe, args, message):
    # --noise-levels -1 / nan were skipped yet reported in the table; evaluate's --horizon 0 was ignored
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        load_recipe(recipe).main(["--name", "bad", *args])
    assert exc.value.code == 2
    assert re.search(message, " ".join(re.sub(r"[│╭╮╰╯─]", " ", capsys.readouterr().err).split()))
    assert list(tmp_path.iterdir()) == []


def test_pipeline_runs_every_stage_and_writes_one_table(workdir, dataset):
    """recipes/pipeline.py: teacher, encoder, student and the three evaluations, then one table;
    a second call finds every stage's output and only rebuilds the table. With --mask-unseen-pickers
    (the default-off runs are the fixtures'): the teacher's policy file carries the fill, the encoder
    learns masked labels, the student rounds and the student act with it. The expert's evaluation, then
    the teacher's, run in the background meanwhile."""
    # --no-parallel: the same numbers (test_online_dt_serial_envs...), without starting worker processes
    def without_eval(args):  # the pipeline's own --eval-episodes 0 stays in force
        i = args.index("--eval-episodes")
        return args[:i] + args[i + 2:]

    teacher = " ".join(map(str, without_eval(online_dt_args("unused")[2:])))
    encoder = " ".join(map(str, ["--horizon", HORIZON, *DATA, "--epochs", 1, "--batch-size", 8,
                                 "--channels", 4, 4, 4, 4, "--hidden-dim", 16, "--student-rounds", 1,
                                 "--student-episodes", 2, "--student-epochs", 1]))
    student = " ".join(map(str, ["--rounds", 1, "--updates-per-round", 2, "--batch-size", 8, "--select-episodes", 2,
                                 *DATA]))
    args = ["--name", "pipe", "--trials", 2, f"--teacher-args={teacher}", f"--encoder-args={encoder}",
            f"--student-args={student}", "--threads", 1, "--mask-unseen-pickers", "--no-parallel"]
    out = run_recipe(workdir, "pipeline", *args, timeout=400)
    assert "pipe-eval-expert started in the background" in out.stdout
    assert "evaluate/pipe-eval-teacher" in out.stdout  # in the background, or here once withdrawn from its queue
    assert "of the training images' picker positions are out of view" in out.stdout
    for run_dir in ("online_dt/pipe-teacher", "distill/pipe-student"):
        assert normalizer_parts(load_policy(workdir / "runs" / run_dir).normalizer)[1] is not None, run_dir
    ck = read_checkpoint(workdir / "runs" / "train_encoder" / "pipe-encoder" / "encoder.pt")
    assert ck["mask_unseen_pickers"] is True and ck["out_of_view_fill"]["starts"] == [12, 15]
    table = pd.read_csv(workdir / "runs" / "pipeline" / "pipe" / "summary.csv")
    assert table["policy"].tolist() == ["expert", "teacher", "student"]
    assert (table["n"] == 2).all() and table.loc[1, "x_teacher"] == pytest.approx(1.0)
    assert "| student |" in (workdir / "runs" / "pipeline" / "pipe" / "summary.md").read_text()
    assert (workdir / "runs" / "distill" / "pipe-student" / "policy.pt").exists()
    # the stages evaluate nothing themselves (--eval-episodes 0): the table has the evaluations
    for run_dir in ("distill/pipe-student", "online_dt/pipe-teacher"):
        log = read_log(workdir / "runs" / run_dir)
        assert not [c for c in log.columns if c.startswith("eval")], (run_dir, list(log.columns))
    assert "student before not evaluated, after not evaluated" in out.stdout
    again = run_recipe(workdir, "pipeline", "--resume", "--name", "pipe")
    assert again.stdout.count("skipped") == 6
    # the evaluations again, in this process after the stages: the background's numbers
    for label in ("expert", "teacher"):
        shutil.rmtree(workdir / "runs" / "evaluate" / f"pipe-eval-{label}")
    foreground = run_recipe(workdir, "pipeline", "--resume", "--name", "pipe", "--no-background-evaluations",
                            "--no-parallel")
    assert "in the background" not in foreground.stdout and foreground.stdout.count("skipped") == 4
    pd.testing.assert_frame_equal(pd.read_csv(workdir / "runs" / "pipeline" / "pipe" / "summary.csv"), table)


def test_train_encoder_keeps_the_member_whose_weight_copy_folds_best(workdir, teacher):
    """--members 2 --select-episodes N: each member's weight copy plays the same N train-split episodes (raced in
    chunks) and the file holds the best one alone (with the flip), its scores recorded."""
    out = run_recipe(workdir, "train_encoder", "--name", "enc-select", "--horizon", HORIZON, *DATA, "--epochs", 1,
                     "--batch-size", 8, "--channels", 4, 4, 4, 4, "--hidden-dim", 16, "--threads", 1,
                     "--teacher", "runs/online_dt/teacher", "--student-rounds", 0, "--members", 2,
                     "--select-episodes", 2, "--select-chunk", 1, "--test-time-flip", "on")
    assert "member 0: weight copy" in out.stdout and "member 1: weight copy" in out.stdout
    assert "weight copies after 1 episodes: member 0" in out.stdout  # raced: one episode gives no error, both play on
    run_dir = workdir / "runs" / "train_encoder" / "enc-select"
    saved = read_checkpoint(run_dir / "encoder.pt")
    means = {k: sum(v) / len(v) for k, v in saved["member_scores"].items()}
    assert set(means) == {0, 1} and all(len(v) == 2 for v in saved["member_scores"].values())
    kept = saved["selected_member"]
    assert means[kept] == max(means.values()) and f"member {kept} kept" in out.stdout
    encoder, _ = load_encoder(run_dir)
    assert isinstance(encoder, EncoderEnsemble) and len(encoder.members) == 1 and encoder.state_mirror is not None
    trained = read_checkpoint(run_dir / "checkpoint.pt")["encoder"]  # both members, as trained
    for name, value in encoder.members[0].state_dict().items():
        assert torch.equal(value, trained[f"members.{kept}.{name}"]), name
    assert read_log(run_dir)[f"select/member{kept}_normalized_performance"].notna().sum() == 1


def test_train_encoder_on_the_weight_copied_students_states(workdir, teacher):
    out = run_recipe(workdir, "train_encoder", "--name", "enc-student", "--horizon", HORIZON, *DATA, "--epochs", 1,
                     "--batch-size", 8, "--channels", 4, 4, 4, 4, "--hidden-dim", 16, "--threads", 1,
                     "--teacher", "runs/online_dt/teacher", "--student-rounds", 1, "--student-episodes", 2,
                     "--student-epochs", 1, "--members", 2, "--test-time-flip", "on")
    assert "student round 1/1" in out.stdout
    frame = read_log(workdir / "runs" / "train_encoder" / "enc-student")
    assert frame["student/normalized_performance"].notna().sum() == 1
    assert frame["student/pickers_cm"].notna().sum() == 1
    ck = read_checkpoint(workdir / "runs" / "train_encoder" / "enc-student" / "encoder.pt")
    assert ck["student_rounds"] == 1 and ck["epoch"] == 2
    # --members 2 --test-time-flip on: an ensemble of two encoders, each also reading the mirrored image
    encoder, _ = load_encoder(workdir / "runs" / "train_encoder" / "enc-student")
    assert isinstance(encoder, EncoderEnsemble) and len(encoder.members) == 2 and encoder.state_mirror is not None
    assert ck["ensemble"]["members"] == 2
    # the run's checkpoint (with the student's images) loads with the safe loader, so --resume works
    ck = read_checkpoint(workdir / "runs" / "train_encoder" / "enc-student" / "checkpoint.pt")
    assert ck["student_steps"]["pixels"].shape[0] == 2 * HORIZON
    run_recipe(workdir, "train_encoder", "--resume", "--name", "enc-student")
