import functools
import json

import pytest
import torch

from toy_pixel_env import make_toy_collect_env, make_toy_policy
from trakdis.data import DatasetError, TrajectoryReplayBuffer, collect_expert_dataset, load_expert_dataset, partial_path

H = 6


def _collect(path, num_episodes=5, num_workers=1, **kw):
    return collect_expert_dataset(
        path, "Toy", num_episodes=num_episodes, num_workers=num_workers, horizon=H, progress=False,
        make_env_fn=functools.partial(make_toy_collect_env, horizon=H, min_len=3, max_len=9),
        make_policy_fn=make_toy_policy, **kw,
    )


class _Killed(Exception):
    pass


def _check_episodes(steps, lengths):
    for i, n in enumerate(lengths.tolist()):
        assert steps["step_count"][i, :n, 0].tolist() == list(range(n))
        assert steps["done"][i, n - 1, 0] and not steps["done"][i, : n - 1].any()
        # after the end: zero padding
        assert (steps["state"][i, n:] == 0).all() and (steps["pixels"][i, n:] == 0).all()
        assert not steps["done"][i, n:].any()


def test_collect_load_and_format(tmp_path):
    path = _collect(tmp_path / "ds", num_episodes=4)
    steps, meta = load_expert_dataset(path)
    assert steps.batch_size == (4, H) and meta["lengths"].shape == (4,)
    assert meta["format"] == "trakdis-dataset" and meta["version"] == 1 and meta["horizon"] == H
    assert steps["pixels"].dtype == torch.uint8 and steps["pixels"].shape == (4, H, 8, 8, 3)
    assert steps["reward"].shape == (4, H, 1) and steps["action"].shape == (4, H, 2)
    assert meta["keys"]["pixels"] == {"shape": [8, 8, 3], "dtype": "uint8"}
    lengths = meta["lengths"]
    assert (lengths >= 3).all() and (lengths <= H).all() and (lengths < H).any()  # early terminations kept apart
    _check_episodes(steps, lengths)
    assert not partial_path(path).exists()
    # the dataset feeds the replay buffer directly
    rb = TrajectoryReplayBuffer(capacity=3, context_len=4, max_len=H, keys=("state", "pixels", "action"))
    rb.load_offline(steps, lengths)
    assert rb.sample(8)["pixels"].shape == (8, 4, 8, 8, 3)
    with pytest.raises(FileExistsError, match="already exists"):
        _collect(path, num_episodes=4)


def test_resume_after_kill_equals_uninterrupted(tmp_path):
    ref_steps, ref_meta = load_expert_dataset(_collect(tmp_path / "ref", num_episodes=5))

    seen = []

    def kill_after_two(done, total):
        seen.append(done)
        if done == 2:
            raise _Killed

    path = tmp_path / "ds"
    with pytest.raises(_Killed):
        _collect(path, num_episodes=5, callback=kill_after_two)
    assert not path.exists() and partial_path(path).exists()
    with pytest.raises(DatasetError, match="unfinished collection \\(2 episodes"):
        load_expert_dataset(path)
    with pytest.raises(DatasetError, match="other settings"):
        _collect(path, num_episodes=5, seed=1)

    _collect(path, num_episodes=5, callback=lambda d, t: seen.append(d))
    assert seen == [1, 2, 3, 4, 5]  # resumed at episode 3, nothing recollected
    steps, meta = load_expert_dataset(path)
    assert torch.equal(meta["lengths"], ref_meta["lengths"])
    assert (steps == ref_steps).all()
    assert meta["stats"] == ref_meta["stats"]


def test_parallel_workers(tmp_path, monkeypatch):
    # fork: the workers need not re-import torch (spawn and pickling are covered in tests/transforms)
    import torchrl

    # as in a recipe: torchrl imported with 2 threads (its shutdown restores up to that), then 1 asked for
    monkeypatch.setattr(torchrl, "_THREAD_POOL_INIT", 2)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        steps, meta = load_expert_dataset(_collect(tmp_path / "par", num_episodes=3, num_workers=2, mp_start_method="fork"))
        # TorchRL's ParallelEnv shutdown raises the thread count; the collection puts it back
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(threads)
    assert steps.batch_size == (3, H) and meta["config"]["chunk_size"] == 2
    _check_episodes(steps, meta["lengths"])
    # different workers and chunks got different seeds
    first_states = steps["state"][:, 0]
    assert len({tuple(s.tolist()) for s in first_states}) == 3


def test_bad_datasets(tmp_path):
    with pytest.raises(DatasetError, match="no dataset at .*missing"):
        load_expert_dataset(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="no meta.json"):
        load_expert_dataset(tmp_path / "empty")
    path = _collect(tmp_path / "ds", num_episodes=1)
    meta = json.loads((path / "meta.json").read_text())
    (path / "meta.json").write_text(json.dumps(dict(meta, version=99)))
    with pytest.raises(DatasetError, match="version 99"):
        load_expert_dataset(path)
    (path / "meta.json").write_text(json.dumps(dict(meta, format="other")))
    with pytest.raises(DatasetError, match="format 'other'"):
        load_expert_dataset(path)
    (path / "meta.json").write_text(json.dumps(dict(meta, horizon=H + 1)))
    with pytest.raises(DatasetError, match="does not match meta.json"):
        load_expert_dataset(path)
    (path / "meta.json").write_text("{not json")
    with pytest.raises(DatasetError, match="not valid JSON"):
        load_expert_dataset(path)


def test_overwrite_replaces_only_when_complete(tmp_path):
    path = _collect(tmp_path / "ds", num_episodes=2)
    old_lengths = load_expert_dataset(path)[1]["lengths"]

    def kill(done, total):
        raise _Killed

    with pytest.raises(_Killed):
        _collect(path, num_episodes=3, seed=5, overwrite=True, callback=kill)
    assert torch.equal(load_expert_dataset(path)[1]["lengths"], old_lengths)  # the old dataset is untouched
    _collect(path, num_episodes=3, seed=5, overwrite=True)
    assert load_expert_dataset(path)[1]["num_episodes"] == 3 and not partial_path(path).exists()


def test_real_cloth_env_tiny(tmp_path):
    # the real task env and scripted expert, kept tiny (each MuJoCo cloth step costs tens of ms)
    path = collect_expert_dataset(
        tmp_path / "cloth", "ClothFoldDiagonalPinned", num_episodes=2, horizon=4, image_size=16, progress=False
    )
    steps, meta = load_expert_dataset(path)
    assert steps.batch_size == (2, 4) and steps["pixels"].shape == (2, 4, 16, 16, 3)
    assert steps["state"].shape == (2, 4, 15) and steps["action"].shape == (2, 4, 4)
    assert steps["truncated"][:, -1].all() and (meta["lengths"] == 4).all()
    assert "final_normalized_performance_mean" in meta["stats"]
    import mujoco

    assert meta["mujoco_version"] == mujoco.__version__  # the physics release that played the episodes
    assert steps["pixels"].float().std() > 0
    # a misled expert (aim_error): the same cloths and start, another aim; recorded in the config
    aimed = collect_expert_dataset(tmp_path / "aimed", "ClothFoldDiagonalPinned", num_episodes=2, horizon=4,
                                   image_size=16, progress=False, aim_error=0.05)
    aimed_steps, aimed_meta = load_expert_dataset(aimed)
    assert aimed_meta["config"]["aim_error"] == 0.05 and "aim_error" not in meta["config"]
    assert torch.equal(aimed_steps["state"][:, 0], steps["state"][:, 0])
    assert not torch.equal(aimed_steps["action"][:, 0], steps["action"][:, 0])
    for bad, kw in ((-0.01, {}), (0.05, {"make_policy_fn": make_toy_policy})):
        with pytest.raises(ValueError, match="aim_error"):
            collect_expert_dataset(tmp_path / "bad", "ClothFoldDiagonalPinned", num_episodes=1, horizon=2,
                                   progress=False, aim_error=bad, **kw)
    assert not (tmp_path / "bad").exists() and not partial_path(tmp_path / "bad").exists()


_KILL_SCRIPT = """
import functools, os, signal, sys
sys.path.insert(0, {toy_dir!r})
import torch
from toy_pixel_env import make_toy_collect_env, make_toy_policy
from trakdis.data import collect_expert_dataset

def die(done, total):
    if done == 3:
        os.kill(os.getpid(), signal.SIGKILL)  # no cleanup, no finally blocks, no flush

collect_expert_dataset({path!r}, "Toy", num_episodes=5, num_workers=1, horizon={H}, progress=False,
    make_env_fn=functools.partial(make_toy_collect_env, horizon={H}, min_len=3, max_len=9),
    make_policy_fn=make_toy_policy, callback=die)
"""


def test_resume_after_sigkill(tmp_path):
    import os
    import subprocess
    import sys

    import toy_pixel_env

    path = tmp_path / "ds"
    script = _KILL_SCRIPT.format(toy_dir=os.path.dirname(toy_pixel_env.__file__), path=str(path), H=H)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=240)
    assert proc.returncode == -9, proc.stderr[-2000:]
    assert not path.exists()
    assert json.loads((partial_path(path) / "progress.json").read_text())["episodes_done"] == 3
    seen = []
    _collect(path, num_episodes=5, callback=lambda d, t: seen.append(d))
    assert seen == [4, 5]
    ref_steps, ref_meta = load_expert_dataset(_collect(tmp_path / "ref", num_episodes=5))
    steps, meta = load_expert_dataset(path)
    assert torch.equal(meta["lengths"], ref_meta["lengths"]) and (steps == ref_steps).all()


def _files(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("name,cut", [("steps/state.memmap", 4), ("steps/pixels.memmap", 100), ("length.memmap", 8),
                                      ("steps/action.memmap", -4)])
def test_file_of_the_wrong_size_is_refused_and_left_as_it_is(tmp_path, name, cut):
    path = _collect(tmp_path / "ds", num_episodes=2)
    file = path / "data" / name
    data = file.read_bytes()
    file.write_bytes(data[:-cut] if cut > 0 else data + bytes(-cut))  # truncated, or too long
    before = _files(path)
    with pytest.raises(DatasetError, match=rf"{name.split('/')[-1]} does not match meta.json: it holds "
                                           rf"{len(data) - cut} bytes.*{len(data)} bytes \(the file is "):
        load_expert_dataset(path)
    assert _files(path) == before  # nothing padded or rewritten


def test_loaded_dataset_is_read_only_on_disk(tmp_path):
    path = _collect(tmp_path / "ds", num_episodes=2)
    before = _files(path)
    steps, meta = load_expert_dataset(path)
    steps["state"][0] = 123.0  # stays in this process's memory
    steps["done"][:] = True
    assert _files(path) == before
    again, _ = load_expert_dataset(path)
    assert (again["state"][0] != 123.0).all() and torch.equal(again["step_count"], steps["step_count"])


def test_malformed_meta_json_names_file_and_key(tmp_path):
    path = _collect(tmp_path / "ds", num_episodes=1)
    meta = json.loads((path / "meta.json").read_text())
    bad = {
        "list": ([meta], "holds a JSON list"),
        "null": (None, "holds a JSON NoneType"),
        "no task": ({k: v for k, v in meta.items() if k != "task"}, "'task' is missing"),
        "no horizon": ({k: v for k, v in meta.items() if k != "horizon"}, "'horizon' is missing"),
        "no keys": ({k: v for k, v in meta.items() if k != "keys"}, "'keys' is missing"),
        "float episodes": (dict(meta, num_episodes=1.5), "'num_episodes' must be an int >= 1"),
        "keys a list": (dict(meta, keys=["state"]), "'keys' must map"),
        "key spec null": (dict(meta, keys={**meta["keys"], "state": None}), "'keys.state' must be"),
        "bad shape": (dict(meta, keys={**meta["keys"], "state": {"shape": "2", "dtype": "float32"}}), "'keys.state.shape'"),
        "bad dtype": (dict(meta, keys={**meta["keys"], "state": {"shape": [2], "dtype": "object"}}), "'keys.state.dtype'"),
        "path as key": (dict(meta, keys={**meta["keys"], "../x": {"shape": [], "dtype": "uint8"}}), "'keys.../x' is not a plain"),
    }
    for label, (content, message) in bad.items():
        (path / "meta.json").write_text(json.dumps(content))
        with pytest.raises(DatasetError, match="meta.json.*" + message.replace("(", r"\(").replace(".", r"\.")):
            load_expert_dataset(path)
    (path / "meta.json").write_text(json.dumps(dict(meta, keys={k: v for k, v in meta["keys"].items() if k != "action"})))
    with pytest.raises(DatasetError, match=r"lacks the per-step keys \['action'\]"):
        load_expert_dataset(path)


def test_second_collection_into_the_same_path_is_refused(tmp_path):
    import fcntl
    import os

    def kill(done, total):
        raise _Killed

    path = tmp_path / "ds"
    with pytest.raises(_Killed):
        _collect(path, num_episodes=3, callback=kill)
    before = _files(partial_path(path))
    fd = os.open(partial_path(path), os.O_RDONLY)  # another collection at work holds this lock
    fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        with pytest.raises(DatasetError, match=rf"another collection is writing .*{path.name}"):
            _collect(path, num_episodes=3)
        with pytest.raises(DatasetError, match="another collection is writing"):
            _collect(path, num_episodes=3, seed=1)  # refused before its settings are even compared
        assert _files(partial_path(path)) == before and not path.exists()
    finally:
        os.close(fd)
    assert load_expert_dataset(_collect(path, num_episodes=3))[0].batch_size == (3, H)  # free again: it resumes


def test_no_progress_env_var_wins_over_progress_true(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("TRAKDIS_NO_PROGRESS", "1")
    _collect_bar = functools.partial(collect_expert_dataset, task="Toy", num_episodes=1, horizon=H, progress=True,
                                     make_env_fn=functools.partial(make_toy_collect_env, horizon=H, min_len=3, max_len=9),
                                     make_policy_fn=make_toy_policy)
    _collect_bar(tmp_path / "quiet")
    assert "collect Toy" not in capsys.readouterr().err
    monkeypatch.setenv("TRAKDIS_NO_PROGRESS", "0")
    _collect_bar(tmp_path / "loud")
    assert "collect Toy" in capsys.readouterr().err


def test_a_full_disk_is_an_error_naming_it_before_any_mapped_write(tmp_path, monkeypatch):
    """A memory-mapped write to a full disk kills the process with SIGBUS: the space is checked first."""
    import collections

    import trakdis.data.dataset as dataset

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(dataset.shutil, "disk_usage", lambda p: usage(10**6, 10**6 - 100, 100))
    with pytest.raises(DatasetError, match=r"needs [\d.,]+ MiB more on the disk of .*ds.partial, which has 0.0 MiB free"):
        _collect(tmp_path / "ds", num_episodes=2)
    assert not list((tmp_path / "ds.partial").glob("data/**/*.memmap"))  # nothing mapped
    monkeypatch.undo()
    steps, meta = load_expert_dataset(_collect(tmp_path / "ds", num_episodes=2))  # resumes once there is space
    assert steps.batch_size == (2, H)


def test_leftover_temporary_files_are_removed_when_the_collection_resumes(tmp_path):
    part = partial_path(tmp_path / "ds")
    part.mkdir()
    (part / ".progress.json.abcd1234.tmp").write_text("{")
    (part / "keep.tmp").write_text("not ours")
    _collect(tmp_path / "ds", num_episodes=2)
    assert not (tmp_path / "ds" / ".progress.json.abcd1234.tmp").exists()
    assert (tmp_path / "ds" / "keep.tmp").exists()
