"""Recipe dataset glue: default dataset names and the scripted-expert version check."""
import json

import pytest

from trakdis.data import DatasetError
from trakdis.envs import EXPERT_VERSION
from trakdis.utils.datasets import DataConfig, default_dataset_path, ensure_dataset


def _fake_dataset(path, expert_version):
    path.mkdir(parents=True)
    config = {"task": "ClothFold"}
    if expert_version is not None:
        config["expert_version"] = expert_version
    (path / "meta.json").write_text(json.dumps({"format": "trakdis-dataset", "version": 1, "config": config}))


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
