"""The image baselines' recipes (bc_image.py, dt_image.py) and benchmarks/table1.py at tiny sizes."""
import importlib.util
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import torch

from trakdis.utils.checkpoint import FileFormatError, read_checkpoint, save_checkpoint
from trakdis.evaluation import run_episodes
from trakdis.envs import close_env
from trakdis.policies import load_policy

from .conftest import DATA, HORIZON, load_recipe, run_recipe

TRUNK = ["--trunk.channels", 4, 4, 4, 4, "--trunk.hidden-dim", 16, "--trunk.feature-dim", 8]
TINY_DT = ["--model.embed-dim", 16, "--model.n-layer", 1, "--model.n-head", 1, "--model.context-len", 3]


def bc_args(name, *extra):
    return ["--name", name, "--horizon", HORIZON, *DATA, *TRUNK, "--hidden-dims", 16, "--epochs", 2, "--batch-size", 8,
            "--eval-episodes", 2, "--eval-every", 1, "--threads", 1, *extra]


def dt_args(name, *extra):
    return ["--name", name, "--horizon", HORIZON, *DATA, *TRUNK, *TINY_DT, "--batch-size", 4, "--updates", 4,
            "--eval-episodes", 2, "--eval-every", 2, "--log-every", 1, "--checkpoint-every", 2, "--threads", 1, *extra]


def test_bc_image_trains_saves_and_evaluates(workdir, dataset):
    run_recipe(workdir, "bc_image", *bc_args("bc"))
    run_dir = workdir / "runs" / "bc_image" / "bc"
    for name in ("config.json", "log.csv", "curves.png", "checkpoint.pt", "policy.pt"):
        assert (run_dir / name).exists(), name
    frame = pd.read_csv(run_dir / "log.csv")
    assert frame["train/loss_bc"].notna().sum() == 2 and frame["val/action_mse"].notna().sum() == 2
    assert frame["eval/normalized_performance"].notna().sum() == 2  # after epoch 1 and at the end
    handle = load_policy(run_dir)
    assert handle.kind == "bc_image" and handle.observation_key == "image_features" and handle.horizon == HORIZON
    assert handle.encoder.config["pad"] == 2 and handle.uses_pixels
    # evaluate.py, with a video: the trunk reads the agent's 32x32 view, not the large render
    run_recipe(workdir, "evaluate", "--name", "ev_bc", "--policy", "runs/bc_image/bc", "--trials", 2, "--videos", 1,
               "--video-size", 64, "--threads", 1)
    summary = pd.read_csv(workdir / "runs" / "evaluate" / "ev_bc" / "summary.csv")
    assert summary["policy"].tolist() == ["bc_image"] and summary["n"].tolist() == [2]


def test_dt_image_stop_resume_matches_uninterrupted_and_evaluates(workdir, dataset):
    run_recipe(workdir, "dt_image", *dt_args("dti"))
    run_recipe(workdir, "dt_image", *dt_args("dti2", "--stop-after", 2))
    assert not (workdir / "runs" / "dt_image" / "dti2" / "policy.pt").exists()
    out = run_recipe(workdir, "dt_image", "--resume", "--name", "dti2")
    assert "from step 2" in out.stdout
    a, b = (pd.read_csv(workdir / "runs" / "dt_image" / n / "log.csv") for n in ("dti", "dti2"))
    pd.testing.assert_frame_equal(a, b, check_exact=False, atol=1e-5)
    assert a["train/loss_nll"].notna().sum() == 4 and a["eval/normalized_performance"].notna().sum() == 2
    handle = load_policy(workdir / "runs" / "dt_image" / "dti")
    assert handle.kind == "dt_image" and handle.actor is not None and handle.target_return < 0
    # acting as evaluate.py does (in-process: the subprocess path is covered by the BC test)
    env = handle.make_env(num_envs=1, split="eval", seed=0)
    try:
        res = run_episodes(env, handle.make_policy(), 1, max_steps=HORIZON, desc=None)
    finally:
        close_env(env)
    assert res.lengths.tolist() == [HORIZON] and np.isfinite(res.final_performance).all()


def test_image_policy_file_errors(workdir, tmp_path):
    path = workdir / "runs" / "bc_image" / "bc" / "policy.pt"
    if not path.exists():
        pytest.skip("needs test_bc_image_trains_saves_and_evaluates")
    data = read_checkpoint(path)
    bad = {k: v for k, v in data.items() if k != "trunk"}
    save_checkpoint(tmp_path / "no_trunk.pt", bad)
    with pytest.raises(FileFormatError, match=r"lacks \['trunk'\]"):
        load_policy(tmp_path / "no_trunk.pt")
    wrong = dict(data, trunk_config={**data["trunk_config"], "feature_dim": 9})
    save_checkpoint(tmp_path / "wrong.pt", wrong)
    with pytest.raises(FileFormatError, match="trunk does not match"):
        load_policy(tmp_path / "wrong.pt")
    with pytest.raises(ValueError, match="ClothFold policy, but task"):
        load_policy(path, task="ClothFoldDiagonalPinned")
    assert data["render_version"] == 2  # its CNN learnt ClothFold's images; another rendering is refused
    save_checkpoint(tmp_path / "older.pt", dict(data, render_version=1))
    with pytest.raises(FileFormatError, match="rendering version 1; this trakdis renders ClothFold at version 2"):
        load_policy(tmp_path / "older.pt")


def load_benchmark():
    path = Path(__file__).resolve().parents[2] / "benchmarks" / "table1.py"
    spec = importlib.util.spec_from_file_location("_benchmark_table1", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def tiny_table1_args() -> list[str]:
    """The tiny Table I: one task, one seed, every method, 2 trials, the noise levels 0 and 1e-3."""
    h, data = ["--horizon", str(HORIZON)], list(map(str, DATA))
    dt = list(map(str, TINY_DT)) + ["--batch-size", "4"]
    trunk = list(map(str, TRUNK))
    return ["--tasks", "ClothFold", "--seeds", "1", "--trials", "2", "--no-progress",
            "--teacher-args=" + " ".join([*h, *data, *dt, "--offline-updates", "2", "--online-rounds", "0",
                                          "--eval-episodes", "1", "--expert-episodes", "0", "--log-every", "1"]),
            "--encoder-args=" + " ".join([*h, *data, "--epochs", "1", "--batch-size", "8", "--channels", "4", "4", "4", "4",
                                          "--hidden-dim", "8", "--student-rounds", "1", "--student-episodes", "1",
                                          "--student-epochs", "1"]),
            "--student-args=" + " ".join([*data, "--rounds", "1", "--updates-per-round", "1", "--eval-episodes", "1",
                                          "--eval-every", "1", "--select-episodes", "0", "--batch-size", "4",
                                          "--no-eval-teacher"]),
            "--bc-args=" + " ".join([*h, *data, *trunk, "--epochs", "1", "--batch-size", "8", "--hidden-dims", "8"]),
            "--dt-image-args=" + " ".join([*h, *data, *trunk, *dt, "--updates", "1", "--log-every", "1"]),
            "--noise-levels", "0", "0.001", "--noise-trials", "2", "--no-parallel",  # workers: see the test below
            "--no-overlap"]  # evaluations in this process: ten background ones cost ~70 s of imports (tests/utils/test_stages.py)


def test_table1_tiny_leaves_table_and_curves_and_skips_finished_stages(workdir, dataset, monkeypatch, capsys):
    """One task, one seed, every method at tiny sizes (in-process, as the benchmark runs its stages):
    the table in the paper's layout with the paper's numbers beside ours, the curves PNG, and a
    second call that finds every stage finished."""
    monkeypatch.chdir(workdir)
    torch_threads = torch.get_num_threads()
    args = ["--name", "t1", *tiny_table1_args()]
    try:
        bench = load_benchmark()
        frame = bench.main(args)
        out = workdir / "runs" / "table1" / "t1"
        assert set(frame["method"]) == set(bench.METHODS) and (frame["n"] == 2).all() and (frame["seeds"] == 1).all()
        md = (out / "table1.md").read_text()
        assert "| ClothFold (ours) |" in md and "| ClothFold (paper) | 0.706 +- 0.159 | 0.740 +- 0.111 | 0.583 +- 0.190 |" in md
        for label in ("BC-image", "DT-image", "No-Aug", "No-Pretrain", "| No-Distill |", "No-Distill (weight copy)",
                      "p25", "seed_mean_std", "TraKDis - this"):
            assert label in md, label
        # TraKDis minus each method, paired per episode (one seed: the standard error over its episodes)
        evaluations = workdir / "runs" / "evaluate"
        ours = pd.read_csv(evaluations / "t1-ClothFold-s0-eval-trakdis" / "episodes.csv")["final_normalized_performance"]
        theirs = pd.read_csv(evaluations / "t1-ClothFold-s0-eval-no_pretrain" / "episodes.csv")["final_normalized_performance"]
        row = frame.set_index("method").loc["no_pretrain"]
        assert np.isclose(row["trakdis_minus"], (ours - theirs).mean()) and row["trakdis_paired_seeds"] == 1
        assert np.isclose(row["trakdis_minus_se"], (ours - theirs).std(ddof=1) / np.sqrt(2))
        assert np.isnan(frame.set_index("method").loc["trakdis", "trakdis_minus"])
        for png in ("curves_ClothFold.png", "robustness_ClothFold.png"):
            assert cv2.imread(str(out / png)) is not None, png
        # the robustness study: both students at both noise levels, two episodes each
        robust = pd.read_csv(out / "robustness.csv")
        assert sorted(zip(robust["method"], robust["state_noise"])) == [
            ("trakdis", 0.0), ("trakdis", 0.001), ("trakdis_noise", 0.0), ("trakdis_noise", 0.001)]
        assert (robust["n"] == 2).all() and np.allclose(robust.loc[robust["state_noise"] == 0, "kept"].fillna(1), 1)
        clean = robust[robust["state_noise"] == 0].set_index("method")["mean"]
        # paired on the same episodes: the change is the difference of the means
        assert np.allclose(robust["change"], robust["mean"] - robust["method"].map(clean))
        # TraKDis's noise-free level is its own evaluation (as many trials), not played again by its ladder
        ladder = pd.read_csv(workdir / "runs" / "evaluate" / "t1-ClothFold-s0-noise-trakdis" / "episodes.csv")
        assert sorted(ladder["state_noise"].unique()) == [0.001] and len(ladder) == 2
        assert np.isclose(clean["trakdis"], frame.set_index("method").loc["trakdis", "mean"])
        assert "change at 0.001 (paired)" in md
        assert "## Robustness" in md and "| ClothFold | TraKDis+noise |" in md
        noisy = json.loads((workdir / "runs" / "distill" / "t1-ClothFold-s0-trakdis_noise" / "config.json").read_text())
        assert noisy["estimate_noise"] == 0.001
        timings = pd.read_csv(out / "timings.csv")
        # teacher, 2 encoders, 5 distills (+1 with noise), 2 baselines, 9 evaluations (+2 over the noise levels)
        assert len(timings) == 22
        distills = workdir / "runs" / "distill"
        assert json.loads((distills / "t1-ClothFold-s0-no_pretrain" / "config.json").read_text())["weight_copy"] is False
        # the paper's No-Distill: fresh weights, the expert's actions, the teacher's 2 offline updates in the 1 round;
        # the weight copy's arm under the stage name the key no_distill had before
        paper = json.loads((distills / "t1-ClothFold-s0-no_distill_paper" / "config.json").read_text())
        assert (paper["weight_copy"], paper["distill"], paper["updates_per_round"], paper["select_episodes"]) == (
            False, False, 2, 0)
        copy = json.loads((distills / "t1-ClothFold-s0-no_distill" / "config.json").read_text())
        assert (copy["weight_copy"], copy["distill"], copy["updates_per_round"]) == (True, False, 1)
        assert (evaluations / "t1-ClothFold-s0-eval-no_distill_paper" / "summary.csv").exists()
        for baseline in ("bc_image", "dt_image"):  # evaluated by evaluate.py only, on 2 workers like the others
            log = pd.read_csv(workdir / "runs" / baseline / f"t1-ClothFold-s0-{baseline}" / "log.csv")
            assert "eval/normalized_performance" not in log.columns, baseline
            ev = json.loads((workdir / "runs" / "evaluate" / f"t1-ClothFold-s0-eval-{baseline}" / "config.json").read_text())
            assert ev["parallel"] is False, baseline
        assert json.loads((workdir / "runs" / "train_encoder" / "t1-ClothFold-s0-encoder-noaug" / "config.json").read_text())["aug"] is False
        # the test-time flip is an augmentation too: the No-Aug encoder reads the image once, the full method's twice
        encoders = workdir / "runs" / "train_encoder"
        assert read_checkpoint(encoders / "t1-ClothFold-s0-encoder-noaug" / "encoder.pt")["ensemble"] is None
        assert read_checkpoint(encoders / "t1-ClothFold-s0-encoder" / "encoder.pt")["ensemble"]["state_mirror"] is not None
        capsys.readouterr()
        again = bench.main(["--name", "t1", "--resume"])
        assert "run directory:" not in capsys.readouterr().out  # no stage ran again
        pd.testing.assert_frame_equal(frame, again)
        assert len(pd.read_csv(out / "timings.csv")) == 22
        # --report: the finished evaluations tabulated into report/, nothing run, nothing of the run written; an
        # evaluation without its summary (still running) is left out and counted as to come
        saved = {f: (out / f).read_bytes() for f in ("config.json", "timings.csv", "table1.md", "table1.csv")}
        pd.testing.assert_frame_equal(frame, bench.main(["--name", "t1", "--report"]))
        (workdir / "runs" / "evaluate" / "t1-ClothFold-s0-eval-dt_image" / "summary.csv").unlink()
        partial = bench.main(["--name", "t1", "--report", "--tasks", "ClothFold"])
        assert set(partial["method"]) == set(bench.METHODS) - {"dt_image"}
        out_text = capsys.readouterr().out
        assert "run directory:" not in out_text and "started" not in out_text and "done in" not in out_text
        assert "So far: the 10 of 11 evaluations that have finished" in (out / "report" / "table1.md").read_text()
        assert (out / "report" / "curves_ClothFold.png").exists()
        assert saved == {f: (out / f).read_bytes() for f in saved}
        with pytest.raises(ValueError, match="only --tasks and --methods may narrow it, not --trials"):
            bench.main(["--name", "t1", "--report", "--trials", "5"])  # would label 2-trial evaluations as 5
        with pytest.raises(FileNotFoundError, match="table1/nope/config.json does not exist"):
            bench.main(["--name", "nope", "--report"])
    finally:
        torch.set_num_threads(torch_threads)


def test_table1_tiny_on_a_local_2_cpu_ray_equals_the_serial_run(workdir, dataset, monkeypatch):
    """The same tiny Table I with --ray (a local Ray of 2 CPUs; its own stages, under another name): the same
    table1.csv, value for value; the noise ladder's two levels ran as two parts, merged."""
    ray = pytest.importorskip("ray")
    serial = workdir / "runs" / "table1" / "t1" / "table1.csv"
    if not serial.exists():
        pytest.skip("needs test_table1_tiny_leaves_table_and_curves_and_skips_finished_stages")
    monkeypatch.chdir(workdir)
    torch_threads = torch.get_num_threads()
    try:
        frame = load_benchmark().main(["--name", "t1ray", *tiny_table1_args(), "--ray", "--ray-cpus", "2"])
    finally:
        ray.shutdown()
        torch.set_num_threads(torch_threads)
    pd.testing.assert_frame_equal(frame, pd.read_csv(serial), check_exact=True)
    ladder = workdir / "runs" / "evaluate" / "t1ray-ClothFold-s0-noise-trakdis_noise"
    assert len(json.loads((ladder / "parts.json").read_text())) == 2
    pd.testing.assert_frame_equal(pd.read_csv(ladder / "episodes.csv"), pd.read_csv(
        workdir / "runs" / "evaluate" / "t1-ClothFold-s0-noise-trakdis_noise" / "episodes.csv"), check_exact=True)
    assert len(pd.read_csv(workdir / "runs" / "table1" / "t1ray" / "timings.csv")) == 22 + 2  # + the ladder's parts


@pytest.mark.parametrize("recipe,flags", [
    ("bc_image", ["--trunk.pad", "--trunk.feature-dim", "--loss-function", "--epochs", "--resume"]),
    ("dt_image", ["--trunk.pad", "--model.context-len", "--updates", "--eval-rtg", "--lambda-entropy"]),
])
def test_help(recipe, flags, capsys):
    from .conftest import load_recipe

    with pytest.raises(SystemExit) as exc:
        load_recipe(recipe).main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for flag in flags:
        assert flag in out, flag


def test_table1_stages_and_their_options():
    """Which stages one task and seed runs, with which options (recorded, nothing run): every evaluation
    and every student's curve on 2 workers by default, the baselines evaluated by evaluate.py only,
    the robust student distilled with --estimate-noise and both students evaluated at every noise level (TraKDis's
    noise-free level by its own evaluation when the trial counts agree)."""
    bench = load_benchmark()
    from trakdis.utils.config import parse_config

    class Recorder:
        def __init__(self):
            self.calls, self.submitted = {}, []

        def run(self, recipe, run_name, output, args, *, seed=None, **scheduling):
            self.calls[run_name] = (recipe, list(args), seed)
            return Path("runs") / recipe / run_name

        def submit(self, recipe, run_name, output, args, *, seed=None, **scheduling):
            self.submitted.append(run_name)
            return self.run(recipe, run_name, output, args, seed=seed)

        def first_of(self, group, *args, **kwargs):
            return self.run(*args, **kwargs)

        def wait(self, directory):
            return directory

    methods = [m for m in bench.METHODS if m != "expert"]  # the expert's stage reads the teacher's file
    cfg = parse_config(bench.Table1Config, ["--noise-levels", "0", "1e-3", "--noise-trials", "7", "--methods", *methods])
    stages = Recorder()
    evals, robust, students = bench.run_task_seed(stages, cfg, "t", "ClothFold", 3)
    assert set(students) == {"trakdis", "no_aug", "no_pretrain", "no_distill", "no_distill_copy"}
    assert set(evals) == set(methods) and set(robust) == {"trakdis", "trakdis_noise"}
    calls = stages.calls
    assert {seed for _, _, seed in calls.values()} == {3}
    evaluations = [args for recipe, args, _ in calls.values() if recipe == "evaluate"]
    assert len(evaluations) == 10 and all("--parallel" in a for a in evaluations)
    # --overlap (default): every evaluation queued as soon as its policy exists (the teacher's and the expert's first)
    order = list(calls)
    assert sorted(stages.submitted) == sorted(n for n, (recipe, _, _) in calls.items() if recipe == "evaluate")
    assert order.index("t-ClothFold-s3-eval-teacher") < order.index("t-ClothFold-s3-encoder")
    assert order.index("t-ClothFold-s3-eval-trakdis") < order.index("t-ClothFold-s3-no_pretrain")
    students = {name: args for name, (recipe, args, _) in calls.items() if recipe == "distill"}
    assert len(students) == 6 and all("--parallel" in a for a in students.values())
    # the paper's No-Distill: fresh weights, the expert's actions, the teacher's offline recipe (1500 updates of 64
    # windows, lr 1e-3 decayed to a tenth) over the student's 10 rounds, the last round kept; the weight copy's arm:
    # --no-distill alone, under the stage names the key no_distill had before
    paper = parse_config(load_recipe("distill").DistillConfig, students["t-ClothFold-s3-no_distill_paper"])
    assert (paper.weight_copy, paper.distill, paper.rounds, paper.updates_per_round, paper.batch_size) == (
        False, False, 10, 150, 64)
    assert (paper.lr, paper.warmup_steps, paper.min_lr_fraction, paper.select_episodes) == (1e-3, 100, 0.1, 0)
    copy = parse_config(load_recipe("distill").DistillConfig, students["t-ClothFold-s3-no_distill"])
    assert (copy.weight_copy, copy.distill, copy.updates_per_round, copy.lr, copy.select_episodes) == (
        True, False, 50, 1e-4, None)
    assert evals["no_distill"] == Path("runs") / "evaluate" / "t-ClothFold-s3-eval-no_distill_paper"
    assert evals["no_distill_copy"] == Path("runs") / "evaluate" / "t-ClothFold-s3-eval-no_distill"
    # the method's encoder (trakdis.method, as recipes/pipeline.py runs it): on the teacher's weight-copied student,
    # three members, the copy's selection; No-Aug the same encoder without augmentation
    teacher = str(Path("runs") / "online_dt" / "t-ClothFold-s3-teacher")
    for name in ("t-ClothFold-s3-encoder", "t-ClothFold-s3-encoder-noaug"):
        args = calls[name][1]
        assert args[args.index("--teacher") + 1] == teacher and "--parallel" in args, name
        assert " ".join(args).count("--extra-noise 0.5 --members 3 --select-episodes 30") == 1, name
    assert calls["t-ClothFold-s3-encoder-noaug"][1][-1] == "--no-aug" and "--no-aug" not in calls["t-ClothFold-s3-encoder"][1]
    assert all(args[args.index("--teacher") + 1] == teacher for args in students.values())
    noisy = students["t-ClothFold-s3-trakdis_noise"]
    assert noisy[noisy.index("--estimate-noise") + 1] == "0.001" and "--estimate-noise" not in students["t-ClothFold-s3-trakdis"]
    for name in ("t-ClothFold-s3-bc_image", "t-ClothFold-s3-dt_image"):
        args = calls[name][1]
        assert args[args.index("--eval-episodes") + 1] == "0", name
    for student in ("trakdis", "trakdis_noise"):  # 7 trials, not the method's 100: both play every level
        robust_eval = calls[f"t-ClothFold-s3-noise-{student}"][1]
        assert robust_eval[robust_eval.index("--noise-levels") + 1:] == ["0.0", "0.001"]
        assert robust_eval[robust_eval.index("--trials") + 1] == "7"
        assert robust[student] == (Path("runs") / "evaluate" / f"t-ClothFold-s3-noise-{student}",)
    # as many trials as the method's evaluation: TraKDis's noise-free level is that evaluation
    for levels, ladder in ((["0", "1e-3"], ["0.001"]), (["0"], None)):
        stages = Recorder()
        cfg = parse_config(bench.Table1Config,
                           ["--noise-levels", *levels, "--noise-trials", "100", "--methods", *methods])
        _, robust, _ = bench.run_task_seed(stages, cfg, "t", "ClothFold", 3)
        own = Path("runs") / "evaluate" / "t-ClothFold-s3-eval-trakdis"
        noise_eval = Path("runs") / "evaluate" / "t-ClothFold-s3-noise-trakdis"
        assert robust["trakdis"] == ((own, noise_eval) if ladder else (own,))
        assert ("t-ClothFold-s3-noise-trakdis" in stages.calls) == bool(ladder)
        if ladder:
            args = stages.calls["t-ClothFold-s3-noise-trakdis"][1]
            assert args[args.index("--noise-levels") + 1:] == ladder
        args = stages.calls["t-ClothFold-s3-noise-trakdis_noise"][1]
        assert args[args.index("--noise-levels") + 1:] == [str(float(x)) for x in levels]
    stages = Recorder()
    bench.run_task_seed(stages, parse_config(bench.Table1Config, ["--no-parallel", "--no-overlap", "--noise-levels",
                                                                  "--methods", *methods]), "t", "ClothFold", 0)
    assert not any("--parallel" in args for _, args, _ in stages.calls.values()) and not stages.submitted
    assert not any("noise" in name for name in stages.calls)  # no robustness study


def test_table1_no_distill_rows_the_papers_and_the_weight_copys():
    """Method no_distill is the paper's No-Distill (its label); the weight copy fine-tuned on the expert's actions is the
    extra row no_distill_copy, both selectable and both on the curves; their stages are named apart, the weight
    copy's as the key no_distill named them before, so that a run saved then never reads them as the paper's arm."""
    bench = load_benchmark()
    from trakdis.utils.config import parse_config

    assert bench.METHODS[-2:] == ("no_distill", "no_distill_copy")
    assert (bench.LABELS["no_distill"], bench.LABELS["no_distill_copy"]) == ("No-Distill", "No-Distill (weight copy)")
    assert {"no_distill", "no_distill_copy"} <= set(bench.CURVE_METHODS) == set(bench.STUDENT_OF_TEACHER)
    assert bench.STAGE_NAMES == {"no_distill": "no_distill_paper", "no_distill_copy": "no_distill"}
    assert len(set(bench.LABELS.values())) == len(bench.LABELS)
    cfg = parse_config(bench.Table1Config, ["--methods", "no_distill_copy", "no_distill"])
    assert cfg.methods == ("no_distill_copy", "no_distill")
    with pytest.raises(SystemExit):
        parse_config(bench.Table1Config, ["--methods", "no_distill_weight_copy"])


def test_table1_versus_trakdis_pairs_within_seeds():
    """TraKDis minus a method: per seed over the same configurations, then over seeds (a seed that one of them has
    not finished yet is left out of the pairs, not shifted onto another)."""
    bench = load_benchmark()
    ours = [np.array([0.8, 0.6]), np.array([0.7, 0.7]), np.array([0.9, 0.5])]
    theirs = [np.array([0.5, 0.5]), None, np.array([0.8, 0.6])]
    out = bench.versus_trakdis(ours, theirs)
    per_seed = np.array([0.2, 0.0])  # seed 0: (0.3 + 0.1) / 2; seed 2: (0.1 - 0.1) / 2
    assert np.isclose(out["minus"], per_seed.mean()) and out["paired_seeds"] == 2 and out["seeds_above"] == 1
    assert np.isclose(out["minus_se"], per_seed.std(ddof=1) / np.sqrt(2))
    assert bench.versus_trakdis(ours, [None, None, None])["paired_seeds"] == 0


def test_table1_help_and_quick_preset(capsys):
    bench = load_benchmark()
    from trakdis.utils.config import parse_config

    cfg = parse_config(bench.Table1Config, ["--preset", "quick", "--seeds", "2"], presets=bench.PRESETS)
    assert cfg.trials == 20 and cfg.seeds == 2 and "--offline-updates" not in cfg.teacher_args  # the teacher as usual
    assert cfg.noise_levels == ()  # no robustness study unless asked for
    assert "--select-episodes 0" in cfg.student_args  # every arm keeps its last round: no 10-episode selection
    cfg = parse_config(bench.Table1Config, ["--preset", "quick", "--noise-levels", "0", "1e-3"], presets=bench.PRESETS)
    assert cfg.noise_levels == (0.0, 1e-3)
    for bad in (["--noise-levels", "1e-3", "1e-2"], ["--noise-levels", "0", "-1"], ["--estimate-noise", "nan"]):
        with pytest.raises((ValueError, SystemExit), match="noise|"):
            parse_config(bench.Table1Config, bad, presets=bench.PRESETS)
    with pytest.raises(SystemExit) as exc:
        bench.main(["--help"])
    assert exc.value.code == 0 and "--seeds" in capsys.readouterr().out


def test_mirror_symmetry_tells_a_symmetric_task_from_one_that_folds_one_corner():
    """benchmarks/mirror_symmetry.py: states together with their mirror images are symmetric (the mean state is its
    own mirror, the travels swap); a fold that moves c00 alone is not (its mean and mirrored mean part at c00, cN0)."""
    path = Path(__file__).resolve().parents[2] / "benchmarks" / "mirror_symmetry.py"
    spec = importlib.util.spec_from_file_location("_benchmark_mirror_symmetry", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    from trakdis.envs import task_spec
    from trakdis.transforms import mirror_state

    mirror = task_spec("ClothFoldDiagonalPinned").state_mirror
    g = torch.Generator().manual_seed(0)
    states = torch.randn(6, 20, 15, generator=g, dtype=torch.float64) * 0.01
    states[:, :, 0] += torch.linspace(0, 0.3, 20, dtype=torch.float64)  # c00 carried 30 cm along x
    one_sided = module.mirror_gap(states, mirror)
    assert one_sided["travel"][0] > 25 and one_sided["travel_mirrored"][2] == pytest.approx(one_sided["travel"][0])
    assert min(one_sided["mean_gap"][0], one_sided["mean_gap"][2]) > 10 and one_sided["mean_gap"][1] < 3
    both = module.mirror_gap(torch.cat([states, mirror_state(states, *mirror)]), mirror)
    assert max(both["mean_gap"]) < 1e-9
    assert both["travel"] == pytest.approx([both["travel_mirrored"][i] for i in (2, 3, 0, 1)])
