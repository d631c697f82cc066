import json
import subprocess
import sys
from dataclasses import dataclass

import pandas as pd
import pytest
import torch

from trakdis.utils.run import Run, RunConfig


@dataclass
class Cfg(RunConfig):
    steps: int = 6
    """number of updates"""
    lr: float = 0.1


def train(argv):
    run = Run.start("toy", Cfg, argv, presets={"slow": {"lr": 0.01}})
    model = torch.nn.Linear(1, 1)
    opt = torch.optim.SGD(model.parameters(), lr=run.cfg.lr)
    state = run.resume_state()
    step = 0
    if state is not None:
        model.load_state_dict(state["model"]); opt.load_state_dict(state["optim"]); step = state["step"]
    while step < run.cfg.steps:
        step += 1
        run.log(step, {"train/loss": float(step)})
        if step % 2 == 0 or step == run.cfg.steps:
            run.save_checkpoint({"model": model.state_dict(), "optim": opt.state_dict()}, step=step)
        if run.should_stop(step):
            return run, step
    run.finish()
    return run, step


def test_fresh_stop_resume(tmp_path):
    root = str(tmp_path)
    run, step = train(["--root", root, "--name", "a", "--stop-after", "3", "--preset", "slow", "--no-progress"])
    assert step == 3 and run.cfg.lr == 0.01
    saved = json.loads((run.dir / "config.json").read_text())
    assert saved["lr"] == 0.01 and saved["name"] == "a" and saved["resume"] is False
    # Step 3 was logged after the step-2 checkpoint: it is logged again on resume, not duplicated.
    run2, step2 = train(["--root", root, "--resume", "--stop-after", "100", "--steps", "8"])
    assert run2.dir == run.dir and step2 == 8 and run2.cfg.lr == 0.01 and run2.cfg.steps == 8
    frame = pd.read_csv(run.dir / "log.csv")
    assert frame["step"].tolist() == list(range(1, 9))
    assert (run.dir / "curves.png").exists()
    with pytest.raises(FileExistsError):
        train(["--root", root, "--name", "a"])


@pytest.mark.skipif(sys.platform == "win32", reason="run directories are locked with fcntl (POSIX)")
def test_a_run_directory_held_by_another_process_is_refused_untouched(tmp_path):
    """A second process resuming (or starting) a run that is still going is refused, naming the holder, before
    it writes anything; once the holder ends, the same command resumes."""
    root = str(tmp_path)
    run, _ = train(["--root", root, "--name", "a", "--stop-after", "2", "--no-progress"])
    _release_all()  # as if this run had been killed: another process takes the run directory over
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(run.dir / ".lock")], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        before = _tree(tmp_path)
        with pytest.raises(RuntimeError, match=rf"run directory .*a is in use by another process \(pid {holder.pid}\)"):
            train(["--root", root, "--resume", "--name", "a", "--lr", "0.5"])
        assert _tree(tmp_path) == before
    finally:
        holder.kill(), holder.wait()
    run, step = train(["--root", root, "--resume", "--name", "a", "--no-progress"])
    assert step == 6 and json.loads((run.dir / "config.json").read_text())["lr"] == 0.1


_HOLD = """import fcntl, os, sys, time
fd = os.open(sys.argv[1], os.O_RDWR)
fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # fails at once if this test still held it
os.ftruncate(fd, 0), os.pwrite(fd, str(os.getpid()).encode(), 0)
print("held", flush=True)
time.sleep(120)
"""


def _release_all():
    from trakdis.utils import run as run_module

    for directory in list(run_module._HELD):
        run_module._release_run_dir(directory)


def _tree(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() if p.is_file() else None for p in sorted(root.rglob("*"))}


@pytest.mark.parametrize("name", ["../..", "..", ".", "", "a/b", "/abs", "ABSOLUTE"])
def test_run_name_cannot_leave_the_run_root(tmp_path, name):
    name = str(tmp_path / "elsewhere") if name == "ABSOLUTE" else name
    (tmp_path / "config.json").write_text("{}")  # what ../.. would overwrite
    (tmp_path / "summary.md").write_text("mine")
    before = _tree(tmp_path)
    for extra in ([], ["--resume"]):
        with pytest.raises(ValueError, match=r"--name .* is not a plain run name"):
            train(["--root", str(tmp_path / "runs"), "--name", name, "--no-progress", *extra])
    assert _tree(tmp_path) == before


def test_resume_without_config_json_is_refused(tmp_path):
    root = str(tmp_path)
    run, _ = train(["--root", root, "--name", "a", "--stop-after", "2", "--preset", "slow", "--no-progress"])
    (run.dir / "config.json").unlink()
    before = _tree(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"--resume: .*a/config.json is missing"):
        train(["--root", root, "--resume", "--name", "a"])
    assert _tree(tmp_path) == before


@pytest.mark.parametrize("counters_key", ["counters", None])
def test_run_state_saves_and_resumes_counters_objects_and_rng(tmp_path, counters_key):
    from trakdis.utils.run import RunState

    argv = ["--root", str(tmp_path), "--name", "s", "--no-progress"]
    run = Run.start("toy", Cfg, argv)
    model = torch.nn.Linear(1, 1)
    state = RunState(run, {"step": 0, "note": None}, step_key="step", counters_key=counters_key, model=model)
    assert not state.resuming
    state.load(), state.restore_rng()  # no-ops on a fresh run
    state.on_save = lambda: state.update(note="saved")
    state["step"] = 5
    state.save()
    expected = torch.rand(3)
    saved = torch.load(run.checkpoint_path, weights_only=False)
    assert saved["step"] == 5 and ("counters" in saved) == (counters_key is not None)
    run = Run.start("toy", Cfg, [*argv, "--resume"])
    other = torch.nn.Linear(1, 1)
    state = RunState(run, {"step": 0, "note": None, "new": 1}, step_key="step", counters_key=counters_key, model=other)
    assert state.resuming and state["step"] == 5 and state["note"] == "saved" and state["new"] == 1
    state.load()
    assert torch.equal(other.weight, model.weight)
    state.restore_rng()
    assert torch.equal(torch.rand(3), expected)


def test_logger_backend_missing_is_refused_before_the_run_starts(tmp_path, monkeypatch):
    from trakdis.utils import logger as logger_module

    monkeypatch.setattr(logger_module, "_has_package", lambda name: False)
    with pytest.raises(ModuleNotFoundError, match=r"--logger tensorboard needs the 'tensorboard' package.*"
                                                  r"pip install 'trakdis\[tensorboard\]'"):
        train(["--root", str(tmp_path), "--name", "a", "--logger", "tensorboard", "--no-progress"])
    assert not (tmp_path / "toy").exists()


def test_logger_backend_gets_every_row_and_resumes_from_the_checkpoint(tmp_path, monkeypatch):
    """With --logger tensorboard|wandb, run.log writes log.csv and TorchRL's logger (here a stand-in:
    another WideCSVLogger, itself a TorchRL Logger); the logger's state travels in the checkpoint."""
    from trakdis.utils import logger as logger_module
    from trakdis.utils import run as run_module

    opened, hparams = [], []

    def fake_backend(kind, directory, name, *, state_dict=None):
        opened.append((kind, name, state_dict))
        backend = logger_module.WideCSVLogger(directory / f"backend{len(opened)}.csv")
        backend.log_hparams = hparams.append
        return backend

    monkeypatch.setattr(logger_module, "_has_package", lambda name: True)
    monkeypatch.setattr(run_module, "make_torchrl_logger", fake_backend)
    root = str(tmp_path)
    run, _ = train(["--root", root, "--name", "a", "--logger", "tensorboard", "--stop-after", "3", "--no-progress"])
    assert run.cfg.logger == "tensorboard" and opened[0] == ("tensorboard", "toy/a", None)
    assert hparams[0]["logger"] == "tensorboard" and hparams[0]["lr"] == 0.1
    assert pd.read_csv(run.dir / "backend1.csv")["train/loss"].tolist() == [1.0, 2.0, 3.0]
    saved = torch.load(run.checkpoint_path, weights_only=True)
    assert saved["logger"]["kind"] == "tensorboard" and saved["logger"]["state"]["exp_name"] == "a"
    run2, _ = train(["--root", root, "--resume", "--name", "a", "--no-progress"])
    assert run2.dir == run.dir and opened[1][2]["exp_name"] == "a"  # reopened with the checkpoint's logger state
    assert pd.read_csv(run.dir / "backend2.csv")["step"].tolist() == [3, 4, 5, 6]
    assert pd.read_csv(run.dir / "log.csv")["step"].tolist() == [1, 2, 3, 4, 5, 6]


def test_tensorboard_logger_writes_event_files(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run, _ = train(["--root", str(tmp_path), "--name", "tb", "--logger", "tensorboard", "--no-progress"])
    events = EventAccumulator(str(run.dir / "tensorboard"))
    events.Reload()
    assert [e.value for e in events.Scalars("train/loss")] == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    assert pd.read_csv(run.dir / "log.csv")["train/loss"].tolist() == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]


def test_run_state_save_and_should_stop(tmp_path, capsys):
    from trakdis.utils.run import RunState

    run = Run.start("toy", Cfg, ["--root", str(tmp_path), "--name", "s", "--no-progress", "--stop-after", "2"])
    state = RunState(run, {"updates": 0, "rounds": 1}, step_key="updates")
    assert not state.save_and_should_stop(3, key="rounds", unit="round")  # 1 < --stop-after
    assert torch.load(run.checkpoint_path, weights_only=False)["counters"]["rounds"] == 1
    state.update(rounds=2, updates=7)
    assert state.save_and_should_stop(3, key="rounds", unit="round")
    assert torch.load(run.checkpoint_path, weights_only=False)["step"] == 7
    assert "stopping after round 2 (--stop-after); continue with --resume" in capsys.readouterr().out
    assert not state.save_and_should_stop(2, key="rounds")  # the last round: the run finishes instead
    assert state.save_and_should_stop(8)  # the step key
    assert "stopping after updates 7" in capsys.readouterr().out


def test_run_state_phases_and_once_continue_across_a_resume(tmp_path):
    from trakdis.utils.run import RunState

    args = ["--root", str(tmp_path), "--name", "p", "--no-progress"]
    run = Run.start("toy", Cfg, args)
    state = RunState(run, {"updates": 0}, step_key="updates", phases_key="phases")
    state.phases.add("training", episodes=2, wall=1.0, cpu=0.5)
    calls = []
    state.once("written", lambda: calls.append(1))
    state.once("written", lambda: calls.append(2))
    assert calls == [1] and state["written"] is True
    assert torch.load(run.checkpoint_path, weights_only=False)["counters"]["phases"]["training"]["episodes"] == 2
    resumed = RunState(Run.start("toy", Cfg, [*args, "--resume"]), {"updates": 0}, step_key="updates", phases_key="phases")
    resumed.once("written", lambda: calls.append(3))  # ran before the resume
    assert calls == [1] and resumed.phases.episodes == 2


def test_finish_draws_only_the_columns_the_log_has(tmp_path):
    run = Run.start("toy", Cfg, ["--root", str(tmp_path), "--name", "f", "--no-progress"])
    run.log(1, {"train/loss": 1.0})
    run.log(2, {"train/loss": 0.5})
    assert run.finish(columns=("train/loss", "eval/missing")) == run.dir / "curves.png"
    assert (run.dir / "curves.png").exists()


def test_run_state_finish_saves_draws_and_reports_the_phases(tmp_path, capsys):
    from trakdis.utils.run import RunState

    run = Run.start("toy", Cfg, ["--root", str(tmp_path), "--name", "e", "--no-progress"])
    state = RunState(run, {"updates": 3}, step_key="updates", phases_key="phases")
    run.log(3, {"train/loss": 1.0})
    state.finish(columns=("train/loss",), extra={"num_envs": 2})
    assert (run.dir / "curves.png").exists() and "files and curves" in state.phases.records
    report = json.loads((run.dir / "phases.json").read_text())
    assert report["num_envs"] == 2 and "files and curves" in report["phases"]
    assert torch.load(run.checkpoint_path, weights_only=False)["counters"]["updates"] == 3
    assert "episodes simulated: 0" in capsys.readouterr().out


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_a_gpu_run_resumes_on_a_cpu_only_machine_and_a_new_one_is_refused_before_its_directory(tmp_path):
    root = str(tmp_path)
    run, _ = train(["--root", root, "--name", "g", "--stop-after", "2", "--no-progress"])
    saved = json.loads((run.dir / "config.json").read_text())
    (run.dir / "config.json").write_text(json.dumps({**saved, "device": "cuda"}))  # as a GPU machine saved it
    with pytest.raises(ValueError, match="--device cuda: this machine has no CUDA device"):
        train(["--root", root, "--resume", "--name", "g"])  # resuming on its saved device
    resumed, step = train(["--root", root, "--resume", "--name", "g", "--device", "cpu"])
    assert step == 6 and resumed.cfg.device == "cpu"
    with pytest.raises(ValueError, match="--device cuda: this machine has no CUDA device"):
        train(["--root", root, "--name", "new", "--device", "cuda"])
    assert not (run.dir.parent / "new").exists() and run.dir.exists()
