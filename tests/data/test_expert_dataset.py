import functools
import json

import pytest
import torch

from toy_pixel_env import make_toy_collect_env, make_toy_policy
from trakdis.data import DatasetError, TrajectoryReplayBuffer, collect_expert_dataset, load_dataset, partial_path

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
    steps, meta = load_dataset(path)
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
    ref_steps, ref_meta = load_dataset(_collect(tmp_path / "ref", num_episodes=5))

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
        load_dataset(path)
    with pytest.raises(DatasetError, match="other settings"):
        _collect(path, num_episodes=5, seed=1)

    _collect(path, num_episodes=5, callback=lambda d, t: seen.append(d))
    assert seen == [1, 2, 3, 4, 5]  # resumed at episode 3, nothing recollected
    steps, meta = load_dataset(path)
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
        steps, meta = load_dataset(_collect(tmp_path / "par", num_episodes=3, num_workers=2, mp_start_method="fork"))
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
        load_dataset(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="no meta.json"):
        load_dataset(tmp_path / "empty")
    path = _collect(tmp_path / "ds", num_episodes=1)
    meta = json.loads((path / "meta.json").read_text())
    (path / "meta.json").write_text(json.dumps(dict(meta, version=99)))
    with pytest.raises(DatasetError, match="version 99"):
        load_dataset(path)
    (path / "meta.json").write_text(json.dumps(dict(meta, format="other")))
    with pytest.raises(DatasetError, match="format 'other'"):
        load_dataset(path)
    (path / "meta.json").write_text(json.dumps(dict(meta, horizon=H + 1)))
    with pytest.raises(DatasetError, match="does not match meta.json"):
        load_dataset(path)
    (path / "meta.json").write_text("{not json")
    with pytest.raises(DatasetError, match="not valid JSON"):
        load_dataset(path)


def test_overwrite_replaces_only_when_complete(tmp_path):
    path = _collect(tmp_path / "ds", num_episodes=2)
    old_lengths = load_dataset(path)[1]["lengths"]

    def kill(done, total):
        raise _Killed

    with pytest.raises(_Killed):
        _collect(path, num_episodes=3, seed=5, overwrite=True, callback=kill)
    assert torch.equal(load_dataset(path)[1]["lengths"], old_lengths)  # the old dataset is untouched
    _collect(path, num_episodes=3, seed=5, overwrite=True)
    assert load_dataset(path)[1]["num_episodes"] == 3 and not partial_path(path).exists()


def test_real_cloth_env_tiny(tmp_path):
    # the real task env and scripted expert, kept tiny (each MuJoCo cloth step costs tens of ms)
    path = collect_expert_dataset(
        tmp_path / "cloth", "ClothFoldDiagonalPinned", num_episodes=2, horizon=4, image_size=16, progress=False
    )
    steps, meta = load_dataset(path)
    assert steps.batch_size == (2, 4) and steps["pixels"].shape == (2, 4, 16, 16, 3)
    assert steps["state"].shape == (2, 4, 15) and steps["action"].shape == (2, 4, 4)
    assert steps["truncated"][:, -1].all() and (meta["lengths"] == 4).all()
    assert "final_normalized_performance_mean" in meta["stats"]
    assert steps["pixels"].float().std() > 0


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
    ref_steps, ref_meta = load_dataset(_collect(tmp_path / "ref", num_episodes=5))
    steps, meta = load_dataset(path)
    assert torch.equal(meta["lengths"], ref_meta["lengths"]) and (steps == ref_steps).all()
