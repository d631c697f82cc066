"""The actions a policy learns from a dataset: recorded (executed) or the scripted expert's noise-free ones."""
import json
import shutil

import pytest
import torch
from tensordict import TensorDict

from trakdis.data import (DataConfig, DatasetError, collect_expert_dataset, expert_labels, expert_targets,
                          load_trajectories)
from trakdis.data.loading import load_offline_data
from trakdis.envs import expert_action, expert_version, task_spec
from trakdis.utils.phases import PhaseTimer

CLOTHFOLD_EXPERT = expert_version("ClothFold")


def _steps(lengths, horizon=4, task="ClothFold"):
    spec = task_spec(task)
    n = len(lengths)
    steps = TensorDict({"state": 0.1 * torch.randn(n, horizon, spec.state_dim),
                        "step_count": torch.arange(horizon).expand(n, horizon).unsqueeze(-1).clone(),
                        "action": torch.zeros(n, horizon, spec.action_dim)}, [n, horizon])
    meta = {"task": task, "config": {"expert_version": CLOTHFOLD_EXPERT, "custom_policy": False},
            "lengths": torch.tensor(lengths)}
    return steps, meta


def test_expert_labels_are_the_experts_actions_on_the_recorded_steps_and_zero_past_the_end():
    torch.manual_seed(0)
    steps, meta = _steps([4, 2])
    labels = expert_labels(steps, meta, path="ds")
    want = torch.as_tensor(expert_action("ClothFold", steps["state"].numpy(), steps["step_count"].numpy()))
    assert labels.shape == steps["action"].shape and labels.dtype == torch.float32
    torch.testing.assert_close(labels[0], want[0])
    torch.testing.assert_close(labels[1, :2], want[1, :2])
    assert (labels[1, 2:] == 0).all() and want[1, 2:].abs().sum() > 0


@pytest.mark.parametrize("config,match", [
    ({"custom_policy": True, "expert_version": CLOTHFOLD_EXPERT}, "custom policy"),
    ({"expert_version": CLOTHFOLD_EXPERT - 1}, f"version {CLOTHFOLD_EXPERT - 1}, this is version {CLOTHFOLD_EXPERT}"),
    ({}, f"version 1, this is version {CLOTHFOLD_EXPERT}"),  # older than the field: version 1, as ensure_dataset reads it
])
def test_a_dataset_this_expert_did_not_collect_is_not_relabelled(config, match):
    steps, meta = _steps([4])
    meta["config"] = config
    with pytest.raises(DatasetError, match=rf"^my/ds: .*{match}.*--data.action-labels executed"):
        expert_labels(steps, meta, path="my/ds")
    with pytest.raises(DatasetError, match=r"my/ds: no \['step_count'\] to relabel"):
        expert_labels(steps.exclude("step_count"), _steps([4])[1], path="my/ds")


def test_a_state_of_the_wrong_size_names_the_dataset():
    steps, meta = _steps([4])
    dim = task_spec("ClothFold").state_dim
    steps["state"] = steps["state"][..., :-2]
    with pytest.raises(DatasetError, match=rf"^my/ds: 'state' has {dim - 2} values per step, a ClothFold state has {dim}"):
        expert_labels(steps, meta, path="my/ds")


def test_load_trajectories_relabels_in_memory_only(tmp_path):
    """A real (tiny) dataset collected with movement noise: the expert labels differ from the executed
    actions in the movements only, equal the expert's action on each recorded step, and the files stay."""
    path = collect_expert_dataset(tmp_path / "ds", "ClothFoldDiagonalUnpinned", num_episodes=1, horizon=4,
                                  from_pixels=False, progress=False, noise=0.5, seed=3)
    files = {p.name: p.read_bytes() for p in path.iterdir() if p.is_file()}
    executed, lengths = load_trajectories(path, keys=("state", "action"))
    expert, lengths2 = load_trajectories(path, keys=("state", "action"), action_labels="expert")
    assert set(expert.keys()) == {"state", "action"} and torch.equal(lengths, lengths2)
    torch.testing.assert_close(expert["state"], executed["state"])
    steps, _ = load_trajectories(path)
    want = expert_action("ClothFoldDiagonalUnpinned", steps["state"].numpy(), steps["step_count"].numpy())
    torch.testing.assert_close(expert["action"], torch.as_tensor(want))
    moves, grasp = (expert["action"] - executed["action"])[..., :3], (expert["action"] - executed["action"])[..., 3]
    assert moves.abs().max() > 0.1 and (grasp == 0).all()
    # without "action" among the keys nothing is computed; the files are unchanged; a bad value is refused
    assert set(load_trajectories(path, keys=("state",), action_labels="expert")[0].keys()) == {"state"}
    assert {p.name: p.read_bytes() for p in path.iterdir() if p.is_file()} == files
    with pytest.raises(ValueError, match="action_labels must be one of"):
        load_trajectories(path, action_labels="clean")
    # the recipes' loader takes it from --data.action-labels
    moved = tmp_path / "copy"
    shutil.copytree(path, moved)
    meta = json.loads((moved / "meta.json").read_text())
    cfg = DataConfig(path=str(moved), action_labels="expert")
    data, _ = load_offline_data(cfg, phases=PhaseTimer(), task=meta["task"], horizon=4, seed=3, log=lambda *a: None,
                                progress=False)
    torch.testing.assert_close(data["action"], expert["action"])


def test_expert_targets_label_a_rollout_beside_its_executed_actions():
    """DAgger's labels: the expert's action at each step's state and step count, as a new entry; the
    executed actions stay; episodes [T] and batches [N, T] alike; missing entries are named."""
    torch.manual_seed(0)
    steps, _ = _steps([4, 4], task="ClothFoldDiagonalPinned")
    executed = steps["action"].clone()
    state, step_count = steps["state"].numpy(), steps["step_count"].numpy()
    want = torch.as_tensor(expert_action("ClothFoldDiagonalPinned", state, step_count))
    out = expert_targets(steps, "ClothFoldDiagonalPinned")
    assert out is steps and torch.equal(out["action"], executed)
    torch.testing.assert_close(out["expert_action"], want)
    assert want.abs().sum() > 0
    one = expert_targets(steps[1].exclude("expert_action"), "ClothFoldDiagonalPinned", out_key="target")
    torch.testing.assert_close(one["target"], want[1])
    with pytest.raises(KeyError, match=r"expert_targets: the episode has no \['step_count'\]"):
        expert_targets(steps.exclude("step_count"), "ClothFoldDiagonalPinned")
    cloth_fold = _steps([4, 4])[0].set("action", torch.zeros(2, 4, 4))  # a diagonal fold's action size
    with pytest.raises(ValueError, match=r"actions have shape \(2, 4, 8\), the episode's 'action' \(2, 4, 4\)"):
        expert_targets(cloth_fold, "ClothFold")


def test_a_dataset_collected_with_another_close_radius_is_labelled_with_it(tmp_path):
    """``close_radius``: the collecting expert's grasp radius is recorded in the dataset, its clean labels and DAgger's
    are that expert's; the task's default expert acts otherwise on the same steps (so the test can fail)."""
    path = collect_expert_dataset(tmp_path / "ds", "ClothFold", num_episodes=1, horizon=6, from_pixels=False,
                                  progress=False, close_radius=0.01)
    steps, _ = load_trajectories(path)
    meta = json.loads((path / "meta.json").read_text())
    assert meta["config"]["close_radius"] == 0.01
    state, step_count = steps["state"].numpy(), steps["step_count"].numpy()
    default = torch.as_tensor(expert_action("ClothFold", state, step_count))
    assert not torch.equal(default[..., [3, 7]], steps["action"][..., [3, 7]])  # the default expert closes earlier
    meta["lengths"] = torch.tensor([6])
    torch.testing.assert_close(expert_labels(steps, meta, path=path), steps["action"])  # noise-free: the recorded ones
    torch.testing.assert_close(expert_targets(steps.clone(), "ClothFold", close_radius=0.01)["expert_action"],
                               steps["action"])
    torch.testing.assert_close(expert_targets(steps.clone(), "ClothFold")["expert_action"], default)
    with pytest.raises(ValueError, match="close_radius"):
        collect_expert_dataset(tmp_path / "bad", "ClothFold", num_episodes=1, horizon=2, progress=False,
                               close_radius=0.0)
    assert not (tmp_path / "bad").exists()
