"""The expert-score cache: a hit returns what was written, a changed setting misses (and leaves the
old file alone), a damaged file is an error naming it."""
import json

import numpy as np
import pytest

from trakdis.evaluation import (ExpertScoreError, expert_score_key, expert_score_path, read_expert_scores,
                                         write_expert_scores)


def key(**kw):
    return expert_score_key(**{"task": "ClothFold", "split": "eval", "horizon": 100, "episodes": 3, "seed": 10_000,
                               "num_envs": 2, **kw})


def test_miss_then_hit(tmp_path):
    k = key()
    path = expert_score_path(tmp_path, k)
    assert path.parent == tmp_path / "expert_scores" and path.name.startswith("ClothFold_eval_h100_3ep_")
    assert read_expert_scores(path, k) is None  # miss: nothing cached yet
    write_expert_scores(path, k, [0.8, 0.9, 0.7], returns=[-5.0, -4.0, -6.0], seconds=12.5)
    scores, returns = read_expert_scores(path, k)
    np.testing.assert_allclose(scores, [0.8, 0.9, 0.7])
    np.testing.assert_allclose(returns, [-5.0, -4.0, -6.0])
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left behind
    data = json.loads(path.read_text())
    assert data["format"] == "trakdis-expert-scores" and data["key"] == k and data["seconds"] == 12.5


@pytest.mark.parametrize("change", [{"episodes": 4}, {"seed": 10_001}, {"num_envs": 1}, {"split": "train"},
                                    {"horizon": 50}, {"expert_noise": 0.1}, {"task": "ClothFoldDiagonalPinned"}])
def test_changed_eval_configuration_misses_and_keeps_the_old_file(tmp_path, change):
    k = key()
    old = write_expert_scores(expert_score_path(tmp_path, k), k, [0.8, 0.9, 0.7], returns=[-5.0, -4.0, -6.0])
    k2 = key(**change)
    new = expert_score_path(tmp_path, k2)
    assert new != old and read_expert_scores(new, k2) is None
    assert read_expert_scores(old, k) is not None


def test_new_expert_version_invalidates(tmp_path, monkeypatch):
    import trakdis.envs

    k = key()
    write_expert_scores(expert_score_path(tmp_path, k), k, [0.8, 0.9, 0.7], returns=[-5.0, -4.0, -6.0])
    monkeypatch.setitem(trakdis.envs.experts.EXPERT_VERSIONS, k["task"], k["expert_version"] + 1)
    k2 = key()
    assert k2["expert_version"] == k["expert_version"] + 1
    assert read_expert_scores(expert_score_path(tmp_path, k2), k2) is None


@pytest.mark.parametrize("content,message", [
    ("{not json", "not valid JSON"),
    ("[1, 2]", "format"),
    (json.dumps({"format": "other"}), "format 'other'"),
    (json.dumps({"format": "trakdis-expert-scores", "version": 99}), "version 99"),
    ("KEY_MISMATCH", "'key' is"),
    ("SHORT", "'scores' must be a list of 3 finite numbers"),
    ("NAN", "'scores' must be a list of 3 finite numbers"),
    ("NO_RETURNS", "'returns' must be a list"),
])
def test_damaged_file_is_an_error_naming_it(tmp_path, content, message):
    k = key()
    path = expert_score_path(tmp_path, k)
    good = {"format": "trakdis-expert-scores", "version": 1, "key": k, "scores": [0.8, 0.9, 0.7],
            "returns": [-5.0, -4.0, -6.0]}
    if content == "KEY_MISMATCH":
        content = json.dumps({**good, "key": {**k, "seed": 1}})
    elif content == "SHORT":
        content = json.dumps({**good, "scores": [0.8]})
    elif content == "NAN":
        content = json.dumps({**good, "scores": [0.8, float("nan"), 0.7]})
    elif content == "NO_RETURNS":
        content = json.dumps({k_: v for k_, v in good.items() if k_ != "returns"})
    path.parent.mkdir(parents=True)
    path.write_text(content)
    with pytest.raises(ExpertScoreError, match=message) as err:
        read_expert_scores(path, k)
    assert str(path) in str(err.value) and "delete the file" in str(err.value)


def test_write_checks_the_count(tmp_path):
    k = key()
    with pytest.raises(ValueError, match="2 scores"):
        write_expert_scores(expert_score_path(tmp_path, k), k, [0.8, 0.9], returns=[-5.0, -4.0])
