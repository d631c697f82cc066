import os
import random

import numpy as np
import pytest
import torch

from trakdis.utils.checkpoint import (
    CheckpointError,
    capture_state,
    load_checkpoint,
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
    loaded = load_checkpoint(path, required=("model", "step"))
    restore_state(loaded, {"model": model2, "optim": opt2})
    assert loaded["step"] == 7 and loaded["counters"] == {"episodes": 3}
    assert torch.equal(model.weight, model2.weight)
    assert opt2.state_dict()["state"][0]["step"] == opt.state_dict()["state"][0]["step"]
    assert (random.random(), np.random.rand(), torch.rand(1).item()) == expected


def test_atomic_no_temp_left_and_overwrite(tmp_path):
    p = tmp_path / "ck.pt"
    save_checkpoint(p, {"step": 1})
    save_checkpoint(p, {"step": 2})
    assert load_checkpoint(p)["step"] == 2
    assert sorted(os.listdir(tmp_path)) == ["ck.pt"]


def test_failed_write_keeps_old_file(tmp_path):
    p = tmp_path / "ck.pt"
    save_checkpoint(p, {"step": 1})

    class Bad:
        def __reduce__(self):
            raise RuntimeError("unpicklable")

    with pytest.raises(RuntimeError):
        save_checkpoint(p, {"step": 2, "bad": Bad()})
    assert load_checkpoint(p)["step"] == 1
    assert sorted(os.listdir(tmp_path)) == ["ck.pt"]


def test_clear_errors(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "none.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="bad.pt"):
        load_checkpoint(bad)
    torch.save({"x": 1}, tmp_path / "plain.pt")
    with pytest.raises(CheckpointError, match="not a trakdis checkpoint"):
        load_checkpoint(tmp_path / "plain.pt")
    save_checkpoint(tmp_path / "ok.pt", {"step": 1})
    with pytest.raises(CheckpointError, match="optimizer"):
        load_checkpoint(tmp_path / "ok.pt", required=("optimizer",))
    with pytest.raises(CheckpointError, match="'model'"):
        restore_state({"step": 1}, {"model": torch.nn.Linear(1, 1)})
    with pytest.raises(CheckpointError, match="restoring 'model'"):
        restore_state({"model": torch.nn.Linear(2, 2).state_dict()}, {"model": torch.nn.Linear(1, 1)})
