import os
import random

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from trakdis.utils.checkpoint import (
    FileFormatError,
    capture_state,
    read_checkpoint,
    restore_state,
    save_checkpoint,
)


def test_roundtrip_model_optimizer_rng(tmp_path):
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    model(torch.randn(4, 3)).sum().backward()
    opt.step()
    state = capture_state({"model": model, "optim": opt}, step=7, counters={"episodes": 3})
    path = save_checkpoint(tmp_path / "ck.pt", state)
    expected = (random.random(), np.random.rand(), torch.rand(1).item())

    model2 = torch.nn.Linear(3, 2)
    opt2 = torch.optim.Adam(model2.parameters(), lr=1e-2)
    loaded = read_checkpoint(path, required=("model", "step"))
    restore_state(loaded, {"model": model2, "optim": opt2})
    assert loaded["step"] == 7 and loaded["counters"] == {"episodes": 3}
    assert torch.equal(model.weight, model2.weight)
    assert opt2.state_dict()["state"][0]["step"] == opt.state_dict()["state"][0]["step"]
    assert (random.random(), np.random.rand(), torch.rand(1).item()) == expected


def test_atomic_no_temp_left_and_overwrite(tmp_path):
    p = tmp_path / "ck.pt"
    save_checkpoint(p, {"step": 1})
    save_checkpoint(p, {"step": 2})
    assert read_checkpoint(p)["step"] == 2
    assert sorted(os.listdir(tmp_path)) == ["ck.pt"]


def test_failed_write_keeps_old_file(tmp_path):
    p = tmp_path / "ck.pt"
    save_checkpoint(p, {"step": 1})

    class Bad:
        def __reduce__(self):
            raise RuntimeError("unpicklable")

    with pytest.raises(RuntimeError):
        save_checkpoint(p, {"step": 2, "bad": Bad()})
    assert read_checkpoint(p)["step"] == 1
    assert sorted(os.listdir(tmp_path)) == ["ck.pt"]


def test_clear_errors(tmp_path):
    with pytest.raises(FileFormatError, match="does not exist"):
        read_checkpoint(tmp_path / "none.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"garbage")
    with pytest.raises(FileFormatError, match="bad.pt"):
        read_checkpoint(bad)
    torch.save({"x": 1}, tmp_path / "plain.pt")
    with pytest.raises(FileFormatError, match="not a trakdis checkpoint"):
        read_checkpoint(tmp_path / "plain.pt")
    save_checkpoint(tmp_path / "ok.pt", {"step": 1})
    with pytest.raises(FileFormatError, match="optimizer"):
        read_checkpoint(tmp_path / "ok.pt", required=("optimizer",))
    with pytest.raises(FileFormatError, match="'model'"):
        restore_state({"step": 1}, {"model": torch.nn.Linear(1, 1)})
    with pytest.raises(FileFormatError, match="restoring 'model'"):
        restore_state({"model": torch.nn.Linear(2, 2).state_dict()}, {"model": torch.nn.Linear(1, 1)})


class _Payload:
    """Unpickling this runs code: it creates ``marker`` (what a crafted policy.pt would do)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return exec, (f"open({self.marker!r}, 'w').close()",)


def _crafted(path, marker, **entries):
    # written with plain torch.save, as an attacker would, with save_checkpoint's format entry
    torch.save({"format": "trakdis-checkpoint", **entries, "payload": _Payload(marker)}, path)
    return path


def test_crafted_file_runs_no_code(tmp_path):
    from trakdis.policies import load_encoder, load_policy

    marker = tmp_path / "pwned"
    policy = _crafted(tmp_path / "policy.pt", marker, kind="teacher", task="ClothFold", dt_config={}, actor={},
                      observation_key="state")
    encoder = _crafted(tmp_path / "encoder.pt", marker, kind="encoder")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    for load in (lambda: load_policy(policy), lambda: load_encoder(encoder), lambda: read_checkpoint(policy),
                 lambda: read_checkpoint(policy, numpy_arrays=True)):  # the resume checkpoint's loader too
        with pytest.raises(FileFormatError, match=r"(policy|encoder)\.pt was refused.*weights_only"):
            load()
    assert not marker.exists()
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_resume_checkpoint_loads_with_weights_only(tmp_path):
    """What a recipe checkpoints (optimizer, scheduler, replay buffer, RNG states, counters) loads
    with torch.load(weights_only=True) and nothing allow-listed."""
    from trakdis.data import TrajectoryReplayBuffer

    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0)
    model(torch.randn(4, 3)).sum().backward()
    opt.step()
    sched.step()
    rb = TrajectoryReplayBuffer(capacity=2, context_len=2, max_len=3, keys=("state", "action"), seed=0)
    rb.add_trajectory(TensorDict({"state": torch.randn(3, 2), "action": torch.zeros(3, 1), "reward": torch.zeros(3, 1)}, [3]))
    np.random.seed(5)
    state = capture_state({"model": model, "optim": opt, "sched": sched, "buffer": rb},
                          counters={"updates": 3, "best": None, "normalizer": {"loc": torch.zeros(2), "keys": ["state"]}})
    expected = np.random.rand(3)
    path = save_checkpoint(tmp_path / "ck.pt", state)
    torch.load(path, weights_only=True)  # no allow-list needed
    np.random.seed(0)
    restore_state(read_checkpoint(path), {})  # the NumPy RNG state round-trips exactly through plain types
    assert np.array_equal(np.random.rand(3), expected)


def test_old_resume_checkpoint_with_numpy_rng_state(tmp_path):
    # written before rng_state() stored plain types: NumPy's legacy tuple (an ndarray inside)
    path = tmp_path / "old.pt"
    np.random.seed(3)
    torch.save({"format": "trakdis-checkpoint", "step": 4,
                "rng": {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}},
               path)
    expected = np.random.rand(2)
    with pytest.raises(FileFormatError, match="old.pt was refused"):
        read_checkpoint(path)  # policy and encoder files never need NumPy arrays
    ck = read_checkpoint(path, numpy_arrays=True)
    np.random.seed(0)
    restore_state(ck, {})
    assert ck["step"] == 4 and np.array_equal(np.random.rand(2), expected)


def test_rng_state_is_torchrl_global_rng_state_and_the_earlier_layout_still_restores(tmp_path):
    """rng_state() is torchrl.checkpoint.GlobalRNGState's; a resume checkpoint of the layout before it
    (keys "torch" / "cuda", NumPy's state as get_state(legacy=False)'s dict with a tensor key) restores
    the same streams."""
    from torchrl.checkpoint import GlobalRNGState

    from trakdis.utils.checkpoint import rng_state, set_rng_state

    random.seed(1), np.random.seed(2), torch.manual_seed(3)
    assert set(rng_state()) == set(GlobalRNGState().state_dict()) and "torch_cpu" in rng_state()
    np_state = np.random.get_state(legacy=False)
    np_state["state"] = {**np_state["state"], "key": torch.from_numpy(np_state["state"]["key"].astype(np.int64))}
    earlier = {"python": random.getstate(), "numpy": np_state, "torch": torch.get_rng_state()}
    save_checkpoint(tmp_path / "earlier.pt", {"rng": earlier, "new": rng_state()})
    expected = (random.random(), np.random.rand(3).tolist(), torch.rand(3).tolist())
    loaded = read_checkpoint(tmp_path / "earlier.pt")
    for key in ("rng", "new"):
        random.seed(0), np.random.seed(0), torch.manual_seed(0)
        set_rng_state(loaded[key])
        assert (random.random(), np.random.rand(3).tolist(), torch.rand(3).tolist()) == expected, key
