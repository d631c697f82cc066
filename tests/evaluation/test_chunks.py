"""trakdis.evaluation.chunks: an evaluation cut into parts (by episode, by noise level) plays the whole
evaluation's episodes, and the merged files are the whole evaluation's, value for value."""
import importlib.util
import sys
from pathlib import Path

import pandas as pd
import pytest

from trakdis.evaluation import evaluation_parts, merge_evaluations

RECIPE = Path(__file__).resolve().parents[2] / "recipes" / "evaluate.py"


@pytest.fixture(scope="module")
def evaluate():
    spec = importlib.util.spec_from_file_location("_chunks_evaluate", RECIPE)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_parts_of_an_evaluation():
    parts = evaluation_parts(100, 30, num_envs=2)
    assert [p[1] for p in parts.args] == ["0", "30", "60", "90"] and [p[3] for p in parts.args] == ["30"] * 3 + ["10"]
    assert "--videos" not in parts.args[0] and parts.args[1][-2:] == ("--videos", "0")
    assert [p[1] for p in evaluation_parts(20, 5, num_envs=2).args] == ["0", "6", "12", "18"]  # rounded up to 6
    assert evaluation_parts(20, 0) is None and evaluation_parts(20, 20) is None
    assert evaluation_parts(20, 10, noise_levels=(1e-3,)) is None  # a noisy level draws noise per step: whole
    ladder = evaluation_parts(20, 0, noise_levels=(0.0, 1e-3))
    assert ladder.args == (("--noise-levels", "0.0"), ("--noise-levels", "0.001")) and ladder.merge is merge_evaluations


def test_parts_play_the_whole_evaluations_episodes(evaluate, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    common = ["--policy", "expert", "--task", "ClothFold", "--horizon", "4", "--num-envs", "2", "--videos", "0",
              "--no-progress", "--threads", "1"]
    evaluate.main(["--name", "whole", "--trials", "6", *common])
    parts = evaluation_parts(6, 2, num_envs=2)
    for i, extra in enumerate(parts.args):  # the arguments appended after the stage's, as a scheduler does
        evaluate.main(["--name", f"part{i}", "--trials", "6", *common, *extra])
    runs = tmp_path / "runs" / "evaluate"
    assert merge_evaluations([runs / f"part{i}" for i in range(3)], runs / "merged")
    for name in ("episodes.csv", "summary.csv", "summary.md"):
        assert (runs / "merged" / name).read_text() == (runs / "whole" / name).read_text(), name
    assert len(set(pd.read_csv(runs / "whole" / "episodes.csv")["final_normalized_performance"])) > 1
    # a noise ladder, by level
    evaluate.main(["--name", "ladder", "--trials", "2", "--noise-levels", "0", "0.01", *common])
    ladder = evaluation_parts(2, 0, noise_levels=(0.0, 0.01))
    for i, extra in enumerate(ladder.args):
        evaluate.main(["--name", f"level{i}", "--trials", "2", "--noise-levels", "0", "0.01", *common, *extra])
    assert merge_evaluations([runs / "level0", runs / "level1"], runs / "ladder-merged")
    for name in ("episodes.csv", "summary.csv"):
        assert (runs / "ladder-merged" / name).read_text() == (runs / "ladder" / name).read_text(), name


def test_a_part_after_an_episode_that_ended_early_is_refused(tmp_path):
    row = {"state_noise": 0.0, "final_normalized_performance": 0.5, "return": 0.0, "sim_unstable": False}
    for name, lengths, first in (("a", [4, 3], 0), ("b", [4, 4], 2)):  # episode 1 ended early (unstable)
        (tmp_path / name).mkdir()
        pd.DataFrame([{**row, "episode": first + k, "length": n} for k, n in enumerate(lengths)]).to_csv(
            tmp_path / name / "episodes.csv", index=False)
        pd.DataFrame([{"task": "ClothFold", "policy": "expert"}]).to_csv(tmp_path / name / "summary.csv", index=False)
    assert not merge_evaluations([tmp_path / "a", tmp_path / "b"], tmp_path / "m")
    assert not (tmp_path / "m").exists()
