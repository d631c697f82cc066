"""Shared fixtures of the recipe tests: every recipe runs as a subprocess with a tiny configuration
(horizon 6, 4 expert episodes, a 1-layer DT) in a temporary working directory."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from trakdis.data import DataConfig

RECIPES = Path(__file__).resolve().parents[2] / "recipes"
HORIZON = 6
DATA = ["--data.root", "datasets", "--data.episodes", "4", "--data.num-envs", "1"]
TINY_DT = ["--model.embed-dim", "16", "--model.n-layer", "1", "--model.n-head", "1", "--model.context-len", "4",
           "--batch-size", "8", "--threads", "1"]


def _env():
    env = dict(os.environ, TRAKDIS_NO_PROGRESS="1", PYTHONUNBUFFERED="1")
    env.setdefault("MUJOCO_GL", "egl")
    return env


def run_recipe(cwd: Path, recipe: str, *args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    """Run recipes/<recipe>.py in ``cwd``; fail with its output if it exits non-zero."""
    cmd = [sys.executable, str(RECIPES / f"{recipe}.py"), *map(str, args)]
    proc = subprocess.run(cmd, cwd=cwd, env=_env(), capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        pytest.fail(f"{' '.join(cmd)} exited with {proc.returncode}\n--- stdout\n{proc.stdout}\n--- stderr\n{proc.stderr[-4000:]}")
    return proc


def load_recipe(recipe: str):
    """Import recipes/<recipe>.py as a module (for in-process checks that need no subprocess)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"_recipe_{recipe}", RECIPES / f"{recipe}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def start_recipe(cwd: Path, recipe: str, *args: str) -> subprocess.Popen:
    cmd = [sys.executable, str(RECIPES / f"{recipe}.py"), *map(str, args)]
    return subprocess.Popen(cmd, cwd=cwd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)


def kill_when(proc: subprocess.Popen, condition, timeout: float = 120) -> None:
    """SIGKILL ``proc`` as soon as ``condition()`` holds (fails if it exits or times out first)."""
    t0 = time.time()
    while not condition():
        if proc.poll() is not None:
            pytest.fail(f"the recipe exited ({proc.returncode}) before it could be killed:\n{proc.stdout.read()}")
        if time.time() - t0 > timeout:
            proc.kill()
            pytest.fail("timed out waiting for the kill condition")
        time.sleep(0.1)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


@pytest.fixture(scope="session")
def workdir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("recipes")


@pytest.fixture(scope="session")
def dataset(workdir) -> Path:
    run_recipe(workdir, "collect", "--horizon", HORIZON, "--episodes", 4, "--root", "datasets", "--num-envs", 1)
    path = workdir / "datasets" / f"ClothFold_4ep_h{HORIZON}_noise{DataConfig.expert_noise:g}_px32"
    assert json.loads((path / "meta.json").read_text())["format"] == "trakdis-dataset"
    return path


def online_dt_args(name: str, *extra: str) -> list:
    """The tiny online_dt configuration; evaluations in this process unless ``--background-eval`` is
    in ``extra`` (a background process costs seconds to start: the teacher fixture covers it), and
    envs stepped in turn unless ``--parallel`` is (worker processes cost seconds to start; the teacher
    fixture uses them, and --no-parallel plays the same episodes: test_online_dt_serial_envs...)."""
    background = [] if "--background-eval" in extra else ["--no-background-eval"]
    parallel = [] if {"--parallel", "--no-parallel"} & set(map(str, extra)) else ["--no-parallel"]
    return ["--name", name, "--horizon", HORIZON, *DATA, *TINY_DT, "--offline-updates", 6, "--online-rounds", 2,
            "--episodes-per-round", 2, "--updates-per-round", 3, "--eval-episodes", 2, "--eval-every", 1,
            "--log-every", 2, "--checkpoint-every", 2, *background, *parallel, *extra]


@pytest.fixture(scope="session")
def teacher(workdir, dataset) -> Path:
    run_recipe(workdir, "online_dt", *online_dt_args("teacher", "--background-eval", "--parallel"))
    return workdir / "runs" / "online_dt" / "teacher"


@pytest.fixture(scope="session")
def encoder(workdir, dataset) -> Path:
    run_recipe(workdir, "train_encoder", "--name", "enc", "--horizon", HORIZON, *DATA, "--epochs", 2,
               "--batch-size", 8, "--channels", 4, 4, 4, 4, "--hidden-dim", 16, "--threads", 1)
    return workdir / "runs" / "train_encoder" / "enc"


@pytest.fixture(scope="session")
def student(workdir, teacher, encoder) -> Path:
    run_recipe(workdir, "distill", *distill_args("student"))
    return workdir / "runs" / "distill" / "student"


def distill_args(name: str, *extra: str) -> list:
    return ["--name", name, "--teacher", "runs/online_dt/teacher", "--encoder", "runs/train_encoder/enc",
            "--rounds", 2, "--updates-per-round", 2, "--episodes-per-round", 2, "--eval-episodes", 2,
            "--eval-every", 1, "--select-episodes", 2, "--select-every", 1, "--batch-size", 8, "--threads", 1, *DATA,
            *extra]
