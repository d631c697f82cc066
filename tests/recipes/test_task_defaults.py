"""The method's per-task rules live in one table (trakdis.envs.task_defaults): every task has an entry, and
every recipe's default resolves to the table's value (a given option still wins)."""
import dataclasses
import json

import pytest

from trakdis.envs import TASKS, task_spec
from trakdis.envs.task_defaults import TASK_DEFAULTS, TaskDefaults, task_defaults
from trakdis.method import TEACHER_ARGS, data_args, teacher_candidates, teacher_stage_args
from trakdis.modules import recipe_hidden_action_dims
from trakdis.utils.config import parse_config

from .conftest import load_recipe


def test_every_task_has_its_defaults():
    assert set(TASK_DEFAULTS) == set(TASKS)
    assert all(isinstance(d, TaskDefaults) for d in TASK_DEFAULTS.values())
    with pytest.raises(dataclasses.FrozenInstanceError):
        task_defaults("ClothFold").expert_coef = 0.5
    with pytest.raises(ValueError, match="Unknown task"):
        task_defaults("NoSuchTask")


def test_the_measured_values():
    cf, pinned, unpinned = (task_defaults(t) for t in ("ClothFold", "ClothFoldDiagonalPinned",
                                                       "ClothFoldDiagonalUnpinned"))
    assert (cf.select_episodes, pinned.select_episodes, unpinned.select_episodes) == (0, 30, 30)
    assert (cf.expert_coef, pinned.expert_coef, unpinned.expert_coef) == (1.0, 0.0, 0.0)
    assert (cf.test_time_flip, pinned.test_time_flip, unpinned.test_time_flip) == (True, False, False)
    assert (cf.hidden_grasp, pinned.hidden_grasp, unpinned.hidden_grasp) == (True, False, False)
    assert (cf.teacher_candidates, pinned.teacher_candidates, unpinned.teacher_candidates) == (1, 3, 3)
    assert (cf.close_radius, pinned.close_radius, unpinned.close_radius) == (0.01, None, None)
    assert (cf.grasp_head, pinned.grasp_head, unpinned.grasp_head) == (False, True, False)
    assert (cf.hold_radius, pinned.hold_radius, unpinned.hold_radius) == (0.0, 0.03, 0.0)


@pytest.mark.parametrize("task", TASKS)
def test_each_recipe_resolves_the_tables_default(task):
    defaults = task_defaults(task)
    distill = load_recipe("distill").DistillConfig
    cfg = parse_config(distill, ["--teacher", "t.pt", "--encoder", "e.pt", "--episodes-per-round", "0"])
    assert cfg.expert_actions and cfg.resolved_expert_coef(task) == defaults.expert_coef
    assert cfg.resolved_select_episodes(task) == defaults.select_episodes
    assert cfg.odometry and cfg.resolved_hold_radius(task) == defaults.hold_radius
    assert parse_config(distill, ["--hold-radius", "0.02"]).resolved_hold_radius(task) == 0.02
    assert parse_config(distill, ["--picker-odometry", "off"]).resolved_hold_radius(task) == 0.0
    given = parse_config(distill, ["--teacher", "t.pt", "--encoder", "e.pt", "--expert-coef", "0.5",
                                   "--select-episodes", "7"])
    assert given.resolved_expert_coef(task) == 0.5 and given.resolved_select_episodes(task) == 7
    rollouts = parse_config(distill, ["--teacher", "t.pt", "--encoder", "e.pt", "--episodes-per-round", "1"])
    assert rollouts.resolved_expert_coef(task) == 0.0  # not the expert's own actions: no expert term

    encoder = load_recipe("train_encoder").TrainEncoderConfig
    assert parse_config(encoder, ["--task", task]).flips == defaults.test_time_flip
    assert parse_config(encoder, ["--task", task, "--test-time-flip", "on"]).flips
    assert not parse_config(encoder, ["--task", task, "--test-time-flip", "on", "--no-aug"]).flips

    assert recipe_hidden_action_dims(task) == (task_spec(task).grasp_dims if defaults.hidden_grasp else ())
    assert teacher_candidates(task) == defaults.teacher_candidates and teacher_candidates(task, 2) == 2
    online_dt = load_recipe("online_dt").OnlineDTConfig
    assert parse_config(online_dt, teacher_stage_args(task)).model.grasp_head == defaults.grasp_head
    assert not parse_config(online_dt, teacher_stage_args(task, TEACHER_ARGS + " --model.no-grasp-head")).model.grasp_head
    assert data_args(task) == ([] if defaults.close_radius is None
                               else ["--data.close-radius", str(defaults.close_radius)])


@pytest.mark.parametrize("recipe,cls,old,new,value", [
    ("online_dt", "OnlineDTConfig", "state_noise", "train_state_noise", 0.01),
    ("distill", "DistillConfig", "state_noise", "estimate_noise", 1e-3),
    ("evaluate", "EvaluateConfig", "state_noise", "noise_levels", [0.0, 1e-3]),
])
def test_a_config_saved_with_the_old_noise_option_still_loads(tmp_path, recipe, cls, old, new, value):
    """--state-noise had three meanings (online_dt: on the true state while training; distill: on the estimate
    while training; evaluate: the acting noise levels); each has its own name now, and an earlier run's
    config.json (SAVED_AS) resumes with its value under the new one."""
    from trakdis.utils.config import config_to_dict, load_config, save_config

    config = getattr(load_recipe(recipe), cls)
    saved = config_to_dict(config())
    saved[old] = saved.pop(new)
    saved[old] = value
    (tmp_path / "config.json").write_text(json.dumps(saved))
    loaded = load_config(config, tmp_path / "config.json")
    assert getattr(loaded, new) == (tuple(value) if isinstance(value, list) else value)
    assert load_config(config, save_config(loaded, tmp_path / "again.json")) == loaded
    # one name, one meaning: the old flag is not an option of any of the three any more
    flag = "--" + new.replace("_", "-")
    values = [str(v) for v in (value if isinstance(value, list) else [value])]
    assert getattr(parse_config(config, [flag, *values]), new) == getattr(loaded, new)
    with pytest.raises(SystemExit):
        parse_config(config, ["--state-noise", *values])


@pytest.mark.parametrize("load", ["pipeline", "table1"])
def test_stage_options_saved_with_the_old_noise_flag_resume_with_the_new_one(load):
    """pipeline.py and table1.py save the options they pass to each stage; an earlier run's --teacher-args and
    --student-args name --state-noise, read as online_dt's --train-state-noise and distill's --estimate-noise."""
    from trakdis.utils.config import config_from_dict, config_to_dict

    from .test_baselines import load_benchmark

    config = load_recipe("pipeline").PipelineConfig if load == "pipeline" else load_benchmark().Table1Config
    saved = {**config_to_dict(config()), "teacher_args": "--state-noise 0.01 --state-scale-floor 0.02",
             "student_args": "--rounds 2 --state-noise=1e-3"}
    loaded = config_from_dict(config, saved)
    assert loaded.teacher_args == "--train-state-noise 0.01 --state-scale-floor 0.02"
    assert loaded.student_args == "--rounds 2 --estimate-noise=1e-3"
    assert config_from_dict(config, config_to_dict(loaded)) == loaded


def test_table1_loads_the_old_train_noise():
    from trakdis.utils.config import config_from_dict, config_to_dict

    from .test_baselines import load_benchmark

    config = load_benchmark().Table1Config
    saved = config_to_dict(config())
    saved.pop("estimate_noise")
    assert config_from_dict(config, {**saved, "train_noise": 0.002}).estimate_noise == 0.002
    # such a run's "no_distill" was the weight-copy arm: it resumes and reports as no_distill_copy
    old = {**saved, "train_noise": 0.001, "methods": ["expert", "teacher", "trakdis", "no_distill"]}
    assert config_from_dict(config, old).methods == ("expert", "teacher", "trakdis", "no_distill_copy")
    assert "no_distill" in config_from_dict(config, saved).methods  # a run saved since: the paper's arm


def test_the_held_corner_needs_the_picker_odometry(capsys):
    distill = load_recipe("distill").DistillConfig
    for flags in (["--picker-odometry", "off"], ["--proprio-pickers"]):
        with pytest.raises(SystemExit):
            parse_config(distill, ["--hold-radius", "0.02", *flags])
        assert "--hold-radius 0.02: the held corner is part of the picker odometry" in _message(capsys)
    with pytest.raises(SystemExit):
        parse_config(distill, ["--hold-radius", "-0.01"])
    assert "--hold-radius must be a finite number >= 0 and < 1, got -0.01" in _message(capsys)


def _message(capsys) -> str:  # tyro's error box, its lines joined
    return " ".join(capsys.readouterr().err.replace("│", " ").split())
