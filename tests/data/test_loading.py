"""Finding and checking the recipes' datasets: default dataset names and the scripted-expert version check."""
import json

import pytest

from trakdis.data import DataConfig, DatasetError, default_dataset_path, ensure_dataset
from trakdis.envs import EXPERT_VERSION, RENDER_VERSION


def _fake_dataset(path, expert_version, task="ClothFold", horizon=100, render_version=RENDER_VERSION):
    path.mkdir(parents=True)
    config = {"task": task, "render_version": render_version}
    if expert_version is not None:
        config["expert_version"] = expert_version
    (path / "meta.json").write_text(json.dumps({"format": "trakdis-dataset", "version": 1, "task": task,
                                                "num_episodes": 3, "horizon": horizon, "keys": {}, "config": config}))


def test_default_name():
    cfg = DataConfig(root="d", episodes=7, expert_noise=0.1)
    assert default_dataset_path(cfg, task="ClothFold", horizon=50, pixels=True).as_posix() == "d/ClothFold_7ep_h50_noise0.1_px32"
    assert default_dataset_path(DataConfig(path="x/y"), task="ClothFold", horizon=50, pixels=False).as_posix() == "x/y"


@pytest.mark.parametrize("found", [None, EXPERT_VERSION - 1])
def test_default_dataset_of_an_older_expert_is_refused(tmp_path, found):
    cfg = DataConfig(root=str(tmp_path), episodes=3)
    path = default_dataset_path(cfg, task="ClothFold", horizon=100, pixels=True)
    _fake_dataset(path, found)
    with pytest.raises(DatasetError, match=rf"{path.name}.*version {found or 1} of the scripted expert.*--data.path"):
        ensure_dataset(cfg, task="ClothFold", horizon=100, seed=0, pixels=True)
    # an explicit --data.path is used as it is
    explicit = DataConfig(path=str(path))
    assert ensure_dataset(explicit, task="ClothFold", horizon=100, seed=0, pixels=True) == path


def test_default_dataset_of_the_current_expert_is_used(tmp_path):
    cfg = DataConfig(root=str(tmp_path), episodes=3)
    path = default_dataset_path(cfg, task="ClothFold", horizon=100, pixels=True)
    _fake_dataset(path, EXPERT_VERSION)
    assert ensure_dataset(cfg, task="ClothFold", horizon=100, seed=0, pixels=True) == path


@pytest.mark.parametrize("task,horizon", [("ClothFoldDiagonalPinned", 100), ("ClothFold", 20)])
def test_dataset_of_another_task_or_horizon_is_refused(tmp_path, task, horizon):
    """A pinned dataset must not train a policy labelled unpinned, nor horizon-20 data a horizon-30 run."""
    path = tmp_path / "data"
    _fake_dataset(path, EXPERT_VERSION, task=task, horizon=horizon)
    before = (path / "meta.json").read_bytes()
    with pytest.raises(DatasetError, match=rf"dataset {path} \(--data.path\) holds task {task} with horizon {horizon}, "
                                           rf"but this run asks for --task ClothFoldDiagonalUnpinned --horizon 30"):
        ensure_dataset(DataConfig(path=str(path)), task="ClothFoldDiagonalUnpinned", horizon=30, seed=0, pixels=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"] and (path / "meta.json").read_bytes() == before


@pytest.mark.parametrize("content", ["[]", "null", '{"format": "trakdis-dataset", "version": 1, "task": "ClothFold"}'])
def test_malformed_meta_is_a_dataset_error(tmp_path, content):
    path = tmp_path / "data"
    path.mkdir()
    (path / "meta.json").write_text(content)
    with pytest.raises(DatasetError, match="meta.json"):
        ensure_dataset(DataConfig(path=str(path)), task="ClothFold", horizon=100, seed=0, pixels=True)


def test_horizon_below_one_is_refused(tmp_path):
    with pytest.raises(ValueError, match="--horizon 0"):
        ensure_dataset(DataConfig(root=str(tmp_path)), task="ClothFold", horizon=0, seed=0, pixels=True)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("found", [None, RENDER_VERSION - 1])
def test_default_pixel_dataset_of_an_older_rendering_is_refused(tmp_path, found):
    cfg = DataConfig(root=str(tmp_path), episodes=3)
    path = default_dataset_path(cfg, task="ClothFold", horizon=100, pixels=True)
    _fake_dataset(path, EXPERT_VERSION, render_version=found)
    with pytest.raises(DatasetError, match="rendering version"):
        ensure_dataset(cfg, task="ClothFold", horizon=100, seed=0, pixels=True)


def test_ensure_dataset_timed_books_the_collected_episodes(tmp_path, monkeypatch):
    from trakdis.data import DataConfig, ensure_dataset_timed, loading
    from trakdis.utils.phases import PhaseTimer

    def fake_ensure(cfg, *, task, horizon, pixels, **kwargs):  # "collects" by writing meta.json
        path = loading.default_dataset_path(cfg, task=task, horizon=horizon, pixels=pixels)
        path.mkdir(parents=True, exist_ok=True)
        (path / "meta.json").write_text("{}")
        return path

    monkeypatch.setattr(loading, "ensure_dataset", fake_ensure)
    cfg = DataConfig(root=str(tmp_path), episodes=3, num_envs=1)
    phases, lines = PhaseTimer(), []
    path = ensure_dataset_timed(cfg, phases=phases, task="ClothFold", horizon=5, seed=0, pixels=False, log=lines.append)
    assert (path / "meta.json").exists() and phases.records["dataset collection"]["episodes"] == 3
    assert len(lines) == 1 and lines[0].startswith("collected 3 episodes in")
    ensure_dataset_timed(cfg, phases=phases, task="ClothFold", horizon=5, seed=0, pixels=False, log=lines.append)
    assert phases.records["dataset collection"]["episodes"] == 3 and len(lines) == 1  # found: nothing collected


@pytest.mark.parametrize("with_pixels", [False, True])
def test_load_offline_data_prefers_an_existing_pixel_dataset_and_prints_its_returns(tmp_path, monkeypatch, with_pixels):
    import torch
    from tensordict import TensorDict

    from trakdis.data import load_offline_data, loading
    from trakdis.utils.phases import PhaseTimer

    cfg = DataConfig(root=str(tmp_path), episodes=2, num_envs=1)
    if with_pixels:  # found: used as it is, although this run asks for no images
        _fake_dataset(default_dataset_path(cfg, task="ClothFold", horizon=3, pixels=True), EXPERT_VERSION, horizon=3)
    asked = []
    monkeypatch.setattr(loading, "ensure_dataset_timed", lambda cfg, *, pixels, **kw: asked.append(pixels) or tmp_path / "d")
    steps = TensorDict({"state": torch.zeros(2, 3, 4), "action": torch.zeros(2, 3, 2), "pixels": torch.zeros(2, 3, 1),
                        "reward": torch.tensor([[[-1.0], [-1.0], [0.0]], [[-0.5], [0.0], [0.0]]]),
                        "normalized_performance": torch.tensor([[[0.1], [0.2], [0.3]], [[0.5], [0.7], [0.0]]])},
                       batch_size=[2, 3])
    monkeypatch.setattr(loading, "load_expert_dataset", lambda path: (steps, {"lengths": torch.tensor([3, 2])}))
    lines = []
    trajectories, lengths = load_offline_data(cfg, phases=PhaseTimer(), task="ClothFold", horizon=3, seed=0,
                                              log=lines.append)
    assert asked == [with_pixels] and lengths.tolist() == [3, 2]
    assert set(trajectories.keys()) == {"state", "action", "reward", "normalized_performance"}
    assert lines == [f"offline data: 2 episodes from {tmp_path / 'd'}; return -1.250 (best -0.500); "
                     "final normalized performance 0.500"]
