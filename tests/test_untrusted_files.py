"""Files from others and numbers from the command line: each bad one ends quickly with an error naming it.

Every test here loads or parses something crafted to exhaust memory, hang, or train silently on a bad
number, and asserts the clear error, within a bounded time (an alarm) and memory (the peak resident
set), with nothing changed on disk.
"""
import io
import json
import os
import resource
import signal
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from trakdis.data import DatasetError, load_expert_dataset
from trakdis.modules import DTModelConfig, NormalizedEncoder, StateEncoder, make_dt_actor
from trakdis.policies import load_encoder, load_policy, save_encoder, save_policy
from trakdis.utils import limits
from trakdis.utils.checkpoint import FileFormatError, read_checkpoint, save_checkpoint

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
GROWTH_LIMIT_MB = 300  # peak resident memory a refused file may add


@pytest.fixture(autouse=True)
def bounded():
    """Each test ends within 20 s (a hang fails it) and adds at most GROWTH_LIMIT_MB to the peak memory."""
    def hang(signum, frame):
        raise TimeoutError("the load did not end within 20 s")

    old = signal.signal(signal.SIGALRM, hang)
    signal.alarm(20)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - before
    assert grown < GROWTH_LIMIT_MB, f"peak memory grew by {grown:.0f} MB"


def plain(text):
    """tyro's boxed error message as one line."""
    return " ".join(text.replace("│", " ").replace("|", " ").split())


def snapshot(directory):
    """Every path under ``directory`` with its size and modification time (symlinks not followed)."""
    out = {}
    for root, dirs, files in os.walk(directory):
        for name in dirs + files:
            st = os.lstat(os.path.join(root, name))
            out[os.path.join(root, name)] = (st.st_size, st.st_mtime_ns, st.st_mode)
    return out


# --------------------------------------------------------------------------- datasets
H, N = 3, 2
KEYS = {"state": ([2], "float32"), "action": ([2], "float32"), "reward": ([1], "float32"), "done": ([1], "bool"),
        "terminated": ([1], "bool"), "truncated": ([1], "bool"), "step_count": ([1], "int64")}


def fake_dataset(path, task="Toy", keys=KEYS, lengths=(3, 2)):
    """A dataset directory of the on-disk format, written directly (no collection)."""
    (path / "data" / "steps").mkdir(parents=True)
    for key, (shape, dtype) in keys.items():
        np.zeros((N, H, *shape), dtype=dtype).tofile(path / "data" / "steps" / f"{key}.memmap")
    np.asarray(lengths, dtype=np.int64).tofile(path / "data" / "length.memmap")
    meta = {"format": "trakdis-dataset", "version": 1, "task": task, "num_episodes": N, "horizon": H,
            "keys": {k: {"shape": s, "dtype": d} for k, (s, d) in keys.items()}, "config": {}}
    (path / "meta.json").write_text(json.dumps(meta))
    return path


def test_fake_dataset_loads(tmp_path):
    steps, meta = load_expert_dataset(fake_dataset(tmp_path / "ds"))
    assert steps.batch_size == (N, H) and meta["lengths"].tolist() == [3, 2]


@pytest.mark.parametrize("special", ["dev_zero", "fifo"])
def test_special_file_as_meta_json_is_refused(tmp_path, special):
    """Failure 1: meta.json a symlink to /dev/zero (read until memory ran out) or a FIFO (hung forever)."""
    from trakdis.data.loading import DataConfig, ensure_dataset

    ds = fake_dataset(tmp_path / "ds")
    (ds / "meta.json").unlink()
    if special == "dev_zero":
        os.symlink("/dev/zero", ds / "meta.json")
    else:
        os.mkfifo(ds / "meta.json")
    before = snapshot(tmp_path)
    with pytest.raises(DatasetError, match=r"meta.json is not a regular file \(a (device|FIFO)\)"):
        load_expert_dataset(ds)
    with pytest.raises(DatasetError, match="meta.json is not a regular file"):  # what a recipe runs on --data.path
        ensure_dataset(DataConfig(path=str(ds)), task="Toy", horizon=H, seed=0, pixels=False)
    assert snapshot(tmp_path) == before


def test_oversized_meta_json_is_refused(tmp_path, monkeypatch):
    ds = fake_dataset(tmp_path / "ds")
    monkeypatch.setattr(limits, "MAX_JSON_BYTES", 64)
    with pytest.raises(DatasetError, match="larger than 64 bytes"):
        load_expert_dataset(ds)


@pytest.mark.parametrize("length", [0, -3, 10**6])
def test_episode_lengths_out_of_range_are_refused(tmp_path, length):
    ds = fake_dataset(tmp_path / "ds", lengths=(3, length))
    with pytest.raises(DatasetError, match=rf"length.memmap: episode 1 has length {length}; .* \[1, {H}\]"):
        load_expert_dataset(ds)


def test_meta_json_that_lies_consistently_is_refused(tmp_path):
    """Shapes, dtypes or task that agree with the files' sizes but not with what a collection writes."""
    for i, (task, key, spec, match) in enumerate([
            ("ClothFold", "state", ([2], "float32"), r"keys.state.shape' must be \[\d+\] for task ClothFold"),
            ("Toy", "done", ([1], "float32"), r"keys.done.dtype' must be bool"),
            ("Toy", "reward", ([2], "float32"), r"keys.reward.shape' must be \[1\]")]):
        keys = {**KEYS, key: spec}
        ds = fake_dataset(tmp_path / f"ds{i}", task=task, keys=keys)
        with pytest.raises(DatasetError, match=match):
            load_expert_dataset(ds)


def test_symlink_out_of_the_dataset_is_refused(tmp_path):
    ds = fake_dataset(tmp_path / "ds")
    outside = tmp_path / "secret.bin"
    (ds / "data" / "steps" / "state.memmap").rename(outside)
    os.symlink(outside, ds / "data" / "steps" / "state.memmap")
    with pytest.raises(DatasetError, match="leads outside"):
        load_expert_dataset(ds)
    os.symlink(outside, ds / "inside.bin")  # a symlink inside the directory to a file inside it is fine
    (ds / "data" / "steps" / "state.memmap").unlink()
    os.symlink(ds / "inside.bin", ds / "data" / "steps" / "state.memmap")
    with pytest.raises(DatasetError, match="leads outside"):  # ... unless it ends outside
        load_expert_dataset(ds)


# --------------------------------------------------------------------------- policy and encoder files
def tiny_policy(path, **changes):
    cfg = DTModelConfig(embed_dim=8, n_layer=1, n_head=1, context_len=2).for_task(18, 8, horizon=5)
    actor = make_dt_actor(cfg, observation_key="state")
    save_policy(path, kind="teacher", task="ClothFold", horizon=5, dt_config=cfg, actor=actor,
                observation_key="state", target_return=-1.0, rtg_scale=1.0)
    data = read_checkpoint(path)
    for key, value in changes.items():
        if key.startswith("dt_config."):
            data["dt_config"][key.split(".", 1)[1]] = value
        else:
            data[key] = value
    data.pop("format")
    save_checkpoint(path, data)
    return path


def tiny_encoder(path, **changes):
    enc = NormalizedEncoder(StateEncoder(18, channels=(2, 2, 2, 2), hidden_dim=4), torch.zeros(18), torch.ones(18))
    save_encoder(path, enc, task="ClothFold")
    data = read_checkpoint(path)
    data.pop("format")
    for key, value in changes.items():
        if key.startswith("encoder_kwargs."):
            data["encoder_kwargs"][key.split(".", 1)[1]] = value
        else:
            data[key] = value
    save_checkpoint(path, data)
    return path


@pytest.mark.parametrize("field, value", [("embed_dim", 40000), ("max_timestep", 10**12), ("context_len", 10**9),
                                          ("n_layer", 10**7), ("context_len", 6000)])
def test_absurd_policy_sizes_are_refused_before_allocation(tmp_path, field, value):
    """Failure 2: the sizes of a policy file's dt_config were allocated before any check."""
    path = tiny_policy(tmp_path / "policy.pt", **{f"dt_config.{field}": value})
    before = snapshot(tmp_path)
    with pytest.raises(FileFormatError, match=rf"policy.pt: dt_config.*({field}|parameters|activations)"):
        load_policy(path)
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("change", [{"ensemble": {"members": 10**6, "state_mirror": None}},
                                    {"encoder_kwargs.hidden_dim": 10**7}])
def test_absurd_encoder_sizes_are_refused_before_allocation(tmp_path, change):
    path = tiny_encoder(tmp_path / "encoder.pt", **change)
    with pytest.raises(FileFormatError, match=r"encoder.pt.*(members|parameters)"):
        load_encoder(path)


def test_the_parameter_limit_can_be_raised(tmp_path):
    path = tiny_policy(tmp_path / "policy.pt")
    with pytest.raises(FileFormatError, match=r"above the parameter limit .*--max-params"):
        load_policy(path, max_params=100)
    with pytest.raises(FileFormatError, match=r"a model of [\d,]+ parameters, more than the limit of 2,000 .*--max-params"):
        load_policy(path, max_params=2000)
    assert load_policy(path, max_params=10**6).kind == "teacher"
    enc = tiny_encoder(tmp_path / "encoder.pt")
    with pytest.raises(FileFormatError, match="more than the limit of 100"):
        load_encoder(enc, max_params=100)
    assert load_encoder(enc, max_params=10**6)[1]["kind"] == "encoder"


def test_zip_bomb_and_unknown_entries_are_refused(tmp_path):
    """Failure 3: an unused, highly compressed extra tensor was unpacked on load."""
    path = tiny_policy(tmp_path / "policy.pt")
    data = read_checkpoint(path)
    data["payload"] = torch.zeros(10_000_000)  # 40 MB of zeros: a few kB compressed
    buffer = io.BytesIO()
    torch.save(data, buffer)
    with zipfile.ZipFile(io.BytesIO(buffer.getvalue())) as src, \
            zipfile.ZipFile(tmp_path / "bomb.pt", "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            dst.writestr(info.filename, src.read(info.filename))
    assert (tmp_path / "bomb.pt").stat().st_size < 1_000_000
    with pytest.raises(FileFormatError, match=r"bomb.pt unpacks to \d+ bytes .* compressed archive bomb"):
        load_policy(tmp_path / "bomb.pt")
    data["payload"] = torch.zeros(3)  # stored plainly: an entry trakdis never writes
    save_checkpoint(tmp_path / "extra.pt", {k: v for k, v in data.items() if k != "format"})
    with pytest.raises(FileFormatError, match=r"extra.pt: unknown entries \['payload'\]"):
        load_policy(tmp_path / "extra.pt")
    with pytest.raises(ValueError, match="payload"):  # and the savers write none
        save_encoder(tmp_path / "e.pt", NormalizedEncoder(StateEncoder(18, channels=(2, 2, 2, 2), hidden_dim=4),
                                                          torch.zeros(18), torch.ones(18)),
                     task="ClothFold", extra={"payload": 1})


@pytest.mark.parametrize("env_kwargs, match", [
    ({"action_repeat": 10**7}, r"env_kwargs.action_repeat must be an int in \[1, 64\]"),
    ({"substeps": 10**6}, r"env_kwargs.substeps must be an int in \[1, 16\]"),
    ({"action_repeat": 64, "substeps": 16}, "1024 physics steps per env step"),
    ({"horizon": 10**6}, "env_kwargs.horizon is not an env option"),
    ({"action_repeat": True}, "env_kwargs.action_repeat must be an int"),
    ({"config_index": 0}, "env_kwargs.config_index is not an env option")])
def test_env_kwargs_outside_the_allow_list_are_refused(tmp_path, env_kwargs, match):
    """Failure 4: a policy's env_kwargs turned a 5-step evaluation into hours, and overrode --horizon."""
    path = tiny_policy(tmp_path / "policy.pt", env_kwargs=env_kwargs)
    with pytest.raises(FileFormatError, match=match):
        load_policy(path)


def test_the_horizon_wins_over_env_kwargs(tmp_path):
    path = tiny_policy(tmp_path / "policy.pt", env_kwargs={"action_repeat": 4})
    handle = load_policy(path, horizon=2)
    seen = {}

    import trakdis.policies.acting as acting

    def fake(task, **kw):
        seen.update(kw)
        return None

    original = acting.make_acting_env
    acting.make_acting_env = fake
    try:
        handle.make_env()
    finally:
        acting.make_acting_env = original
    assert seen["env_kwargs"] == {"action_repeat": 4, "horizon": 2}


@pytest.mark.parametrize("change, match", [
    ({"horizon": "100"}, r"'horizon' must be an int"), ({"horizon": True}, r"'horizon' must be an int"),
    ({"dt_config": [1, 2]}, "'dt_config' must be a dict"), ({"dt_config.n_head": "2"}, r"dt_config.n_head must be"),
    ({"dt_config.bogus": 1}, r"dt_config has unknown fields \['bogus'\]"), ({"actor": [1]}, "'actor' must be a dict"),
    ({"normalizer": {"loc": 1}}, "malformed policy file"), ({"rtg_scale": float("nan")}, "'rtg_scale' must be"),
    ({"task": "Nope"}, "'task' must be one of"), ({"encoder": {"kind": "encoder"}}, r"lacks \['encoder_kwargs'"),
    ({"proprio_dims": "abc"}, "'proprio_dims' must be"), ({"kind": torch.zeros(2)}, "'kind' must be a name")])
def test_malformed_policy_fields_name_the_file(tmp_path, change, match):
    path = tiny_policy(tmp_path / "policy.pt", **change)
    with pytest.raises(FileFormatError, match=rf"policy.pt.*{match}"):
        load_policy(path)


@pytest.mark.parametrize("change, match", [
    ({"encoder_kwargs": [1]}, "'encoder_kwargs' must be a dict"), ({"encoder_kwargs.channels": [2, 2]}, "4 conv"),
    ({"encoder_kwargs.head": 3}, "head must be"), ({"state_dict": {"x": torch.zeros(1)}}, "do not match"),
    ({"ensemble": {"members": 2, "state_mirror": [[0], [1.0]]}}, "state_mirror must be"),
    ({"render_version": torch.zeros(2)}, "'render_version' must be an int"),
    ({"task": torch.zeros(2)}, "'task' must be a name"),
    ({"encoder_kwargs.image_size": 4000, "encoder_kwargs.channels": [64] * 4, "encoder_kwargs.head": "keypoints"},
     "activations")])
def test_malformed_encoder_fields_name_the_file(tmp_path, change, match):
    path = tiny_encoder(tmp_path / "encoder.pt", **change)
    with pytest.raises(FileFormatError, match=rf"encoder.pt.*{match}"):
        load_encoder(path)


def test_random_bytes_and_a_fifo_as_checkpoints(tmp_path):
    (tmp_path / "random.pt").write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(FileFormatError, match="random.pt is not a valid checkpoint"):
        load_policy(tmp_path / "random.pt")
    os.mkfifo(tmp_path / "fifo.pt")
    with pytest.raises(FileFormatError, match=r"fifo.pt is not a regular file \(a FIFO\)"):
        load_policy(tmp_path / "fifo.pt")
    with pytest.raises(FileFormatError, match="missing.pt does not exist"):
        read_checkpoint(tmp_path / "missing.pt")


# --------------------------------------------------------------------------- workers and options
def test_workers_are_capped_by_the_work_and_the_cores(monkeypatch):
    """Failure 5: --num-envs 1000 started 1000 environments for 1 or 2 episodes."""
    monkeypatch.setattr(limits, "available_cores", lambda: 16)
    with pytest.warns(UserWarning, match="--num-envs 1000: starting 2 \\(there are 2 episodes\\)"):
        assert limits.cap_workers(1000, 2) == 2
    with pytest.warns(UserWarning, match="starting 16 \\(there are 16 CPU cores\\)"):
        assert limits.cap_workers(1000, 50) == 16
    assert limits.cap_workers(3, 50) == 3
    # a request up to MIN_CORE_CAP is kept on a smaller machine: the same command plays the same episodes
    monkeypatch.setattr(limits, "available_cores", lambda: 1)
    assert limits.cap_workers(2, 50) == 2 and limits.cap_workers(limits.MIN_CORE_CAP, 50) == limits.MIN_CORE_CAP
    with pytest.warns(UserWarning, match=f"starting {limits.MIN_CORE_CAP} "):
        assert limits.cap_workers(1000, 50) == limits.MIN_CORE_CAP
    told = []
    assert limits.cap_workers(8, 1, warn=told.append) == 1 and told


def test_collection_and_evaluation_use_the_cap(tmp_path, monkeypatch):
    import trakdis.data.loading as loading
    from trakdis.evaluation import EvalConfig

    seen = {}
    monkeypatch.setattr(loading, "collect_expert_dataset", lambda path, **kw: seen.update(kw))
    loading.ensure_dataset(loading.DataConfig(path=str(tmp_path / "ds"), episodes=2, num_envs=1000), task="ClothFold",
                           horizon=3, seed=0, pixels=False, log=lambda *a: None)
    assert seen["num_workers"] == 2
    cap = max(limits.available_cores(), limits.MIN_CORE_CAP)
    with pytest.warns(UserWarning, match="--num-envs 1000"):
        assert EvalConfig(num_envs=1000).num_envs == cap
    assert not (tmp_path / "ds").exists()


def test_negative_grad_clip_is_refused_before_the_run_directory(tmp_path, capsys):
    """Failure 6: --grad-clip -1 reversed the gradient (the loss climbed 39 -> 2390), exit code 0."""
    from trakdis.optim import Updater
    from trakdis.utils.run import Run
    from trakdis.utils.stages import import_recipe

    online_dt = import_recipe(RECIPES / "online_dt.py")

    with pytest.raises(SystemExit):
        Run.start("online_dt", online_dt.OnlineDTConfig, ["--grad-clip", "-1", "--root", str(tmp_path / "runs")])
    assert "--grad-clip must be a finite number >= 0, got -1.0" in plain(capsys.readouterr().err)
    assert not (tmp_path / "runs").exists()
    with pytest.raises(ValueError, match="grad_clip must be > 0"):
        Updater(torch.nn.Linear(2, 2), grad_clip=-1.0)


@pytest.mark.parametrize("recipe, args, flag", [
    ("online_dt", ["--batch-size", "0"], "--batch-size must be an int >= 1, got 0"),
    ("online_dt", ["--log-every", "0"], "--log-every must be an int >= 1"),
    ("online_dt", ["--checkpoint-every", "0"], "--checkpoint-every must be an int >= 1"),
    ("online_dt", ["--offline-updates", "-1"], "--offline-updates must be an int >= 0"),
    ("online_dt", ["--warmup-steps", "-5"], "--warmup-steps must be an int >= 0"),
    ("online_dt", ["--rtg-scale", "0"], "--rtg-scale must be a finite number > 0"),
    ("online_dt", ["--threads", "-1"], "--threads must be an int >= 0"),
    ("online_dt", ["--device", "bogus"], "--device 'bogus' is not a torch device"),
    ("online_dt", ["--seed", str(2**64)], "--seed must be an int >= 0 and < 9.22337e+18"),
    ("online_dt", ["--lr", "nan"], "--lr must be a finite number > 0"),
    ("evaluate", ["--trials", "0"], "--trials must be an int >= 1"),
    ("evaluate", ["--videos", "-1"], "--videos must be an int >= 0"),
    ("evaluate", ["--fps", "0"], "--fps must be a finite number > 0"),
    ("evaluate", ["--num-envs", "0"], "--num-envs must be an int >= 1"),
    ("train_encoder", ["--batch-size", "0"], "--batch-size must be an int >= 1"),
    ("train_encoder", ["--members", "1000"], "--members must be an int <= 64"),
    ("distill", ["--batch-size", "0"], "--batch-size must be an int >= 1"),
    ("distill", ["--grad-clip", "-1"], "--grad-clip must be a finite number >= 0"),
    ("collect", ["--episodes", "0"], "--episodes must be an int >= 1"),
    ("collect", ["--horizon", "100000"], "--horizon must be an int <= 10000")])
def test_option_ranges_are_checked_while_parsing(tmp_path, capsys, recipe, args, flag):
    """Each bad number ends at parse time, naming its flag, before a run directory (or dataset) exists."""
    from trakdis.utils.config import parse_config
    from trakdis.utils.stages import import_recipe

    module = import_recipe(RECIPES / f"{recipe}.py")
    cls = next(v for k, v in vars(module).items() if k.endswith("Config") and getattr(v, "__module__", "") == module.__name__)
    with pytest.raises(SystemExit):
        parse_config(cls, args + ["--root", str(tmp_path / "runs")])
    assert flag in plain(capsys.readouterr().err)
    assert not (tmp_path / "runs").exists()


def test_pipeline_checks_the_later_stages_options_first(tmp_path, capsys):
    from trakdis.utils.stages import Stages, import_recipe

    pipeline = import_recipe(RECIPES / "pipeline.py")

    class FakeRun:
        dir = tmp_path / "pipeline"

    for flag, args in (("--encoder-args", "--batch-size 0"), ("--student-args", "--no-such-option 1")):
        cfg = pipeline.parse_config(pipeline.PipelineConfig, [f"{flag}={args}"])
        with pytest.raises(SystemExit, match=f"pipeline.py {flag}='{args}': recipes/.* refuses these options"):
            pipeline.check_stage_args(Stages(FakeRun(), RECIPES), cfg)
    pipeline.check_stage_args(Stages(FakeRun(), RECIPES), pipeline.parse_config(pipeline.PipelineConfig, []))
    assert not FakeRun.dir.exists()


def test_gym_make_refuses_a_bool_horizon():
    import gymnasium as gym

    import trakdis.envs  # noqa: F401  (registers the ids)

    for kw in ({"horizon": True}, {"action_repeat": True}):
        with pytest.raises(ValueError, match="must be a positive int, got True"):
            gym.make("trakdis/ClothFold-v0", **kw)


# --------------------------------------------------------------------------- run directories
def _run_config():
    from dataclasses import dataclass

    from trakdis.utils.run import RunConfig

    @dataclass
    class Cfg(RunConfig):
        steps: int = 1

    return Cfg


def test_a_checkpoint_of_another_recipe_is_refused_on_resume(tmp_path):
    from trakdis.utils.run import Run, RunState

    Cfg = _run_config()
    run = Run.start("train_encoder", Cfg, ["--root", str(tmp_path), "--name", "x"])
    RunState(run, {"epoch": 0}, step_key="epoch").save()
    run.finish()
    other = tmp_path / "online_dt" / "x"
    other.mkdir(parents=True)
    for name in ("config.json", "checkpoint.pt"):
        (other / name).write_bytes((run.dir / name).read_bytes())
    with pytest.raises(FileFormatError, match="checkpoint.pt is a checkpoint of train_encoder, not of online_dt"):
        Run.start("online_dt", Cfg, ["--root", str(tmp_path), "--name", "x", "--resume"])
    # a checkpoint of the recipe that lacks its counters names the file
    save_checkpoint(run.dir / "checkpoint.pt", {"step": 0, "recipe": "train_encoder"})
    resumed = Run.start("train_encoder", Cfg, ["--root", str(tmp_path), "--name", "x", "--resume"])
    with pytest.raises(FileFormatError, match="checkpoint.pt has no 'counters' entry"):
        RunState(resumed, {"epoch": 0}, step_key="epoch")
    resumed.finish()


def test_corrupt_log_csv_on_resume_names_the_file(tmp_path):
    from trakdis.utils.logger import WideCSVLogger

    (tmp_path / "log.csv").write_bytes(b'step,a\n1,2\n"unterminated\n\xff\xfe,3,4,5\n')
    with pytest.raises(ValueError, match=r"log.csv (is not a readable CSV log|: its 'step' column)"):
        WideCSVLogger(tmp_path / "log.csv", resume=True)
    (tmp_path / "log.csv").write_text("step,a\nabc,2\n")
    with pytest.raises(ValueError, match="log.csv: its 'step' column holds values that are not step numbers"):
        WideCSVLogger(tmp_path / "log.csv", resume=True)


def test_temporary_files_of_a_killed_write_are_removed_at_the_next_start(tmp_path):
    from trakdis.utils.run import Run

    Cfg = _run_config()
    run = Run.start("r", Cfg, ["--root", str(tmp_path), "--name", "x"])
    run.finish()
    stale = [run.dir / ".checkpoint.pt.a1b2c3d4.tmp", run.dir / ".config.json.zz_09xyq.tmp"]
    for file in stale:
        file.write_bytes(b"partial")
    (run.dir / "mine.tmp").write_bytes(b"not a trakdis temporary")
    Run.start("r", Cfg, ["--root", str(tmp_path), "--name", "x", "--resume"]).finish()
    assert not any(file.exists() for file in stale) and (run.dir / "mine.tmp").exists()


@pytest.mark.parametrize("umask", [0o022, 0o077, 0o002])
def test_atomic_writes_follow_the_umask(tmp_path, umask):
    from trakdis.utils.checkpoint import atomic_write_bytes

    old = os.umask(umask)
    try:
        atomic_write_bytes(tmp_path / "f.json", b"{}")
        with open(tmp_path / "plain", "wb"):
            pass
    finally:
        os.umask(old)
    assert (tmp_path / "f.json").stat().st_mode & 0o777 == (tmp_path / "plain").stat().st_mode & 0o777 == 0o666 & ~umask
