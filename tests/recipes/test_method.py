"""trakdis.method: the one definition of the method's stages, read by recipes/pipeline.py and benchmarks/table1.py."""
import json
from pathlib import Path

import pandas as pd
import pytest

from trakdis.method import (CANDIDATE_SEED_STRIDE, ENCODER_ARGS, STUDENT_ARGS, TEACHER_ARGS, encoder_stage_args,
                            no_distill_stage_args, student_stage_args, teacher_candidates, teacher_stage,
                            teacher_stage_args)
from trakdis.utils.config import parse_config

from .conftest import load_recipe
from .test_baselines import load_benchmark


def test_stage_args_parse_in_their_recipes_with_the_methods_defaults():
    """Each stage's default arguments are valid options of its recipe and say what the method runs: the teacher
    on noisy states without evaluations, the encoder on the teacher's weight-copied student with three members
    and the copy's selection, the student reading that encoder; a caller's options come last and win."""
    teacher = parse_config(load_recipe("online_dt").OnlineDTConfig, teacher_stage_args("ClothFoldDiagonalPinned"))
    assert (teacher.task, teacher.collect_pixels, teacher.eval_episodes) == ("ClothFoldDiagonalPinned", True, 0)
    assert (teacher.train_state_noise, teacher.state_scale_floor, teacher.online_rounds) == (0.01, 0.02, 0)
    # not the main job's (online_dt.py's defaults): the encoder's 40 demonstrations, DTModelConfig's log-std floor
    assert (teacher.data.episodes, teacher.model.log_std_min, teacher.online_labels) == (40, -2.5, "executed")
    online_dt = load_recipe("online_dt")
    for preset in ("--preset cpu", "--preset=cpu"):  # a preset given to the stage is not overridden by those resets
        cpu = parse_config(online_dt.OnlineDTConfig, teacher_stage_args("ClothFold", f"{preset} --seed 3"),
                           presets=online_dt.PRESETS)
        assert (cpu.data.episodes, cpu.model.log_std_min, cpu.online_labels, cpu.seed) == (200, -2.5, "expert", 3)
    for name, preset in online_dt.PRESETS.items():  # which is why: each preset sets all three itself
        assert "episodes" in preset["data"] and "log_std_min" in preset["model"] and "online_labels" in preset, name
    mine = parse_config(online_dt.OnlineDTConfig, teacher_stage_args(
        "ClothFold", f"{TEACHER_ARGS} --data.episodes 200 --online-labels expert --model.log-std-min -1.5"))
    assert (mine.data.episodes, mine.model.log_std_min, mine.online_labels) == (200, -1.5, "expert")  # a caller's win
    encoder = parse_config(load_recipe("train_encoder").TrainEncoderConfig,
                           encoder_stage_args("ClothFold", "runs/online_dt/t/policy.pt"))
    assert (encoder.teacher, encoder.members, encoder.select_episodes, encoder.extra_noise, encoder.parallel) == (
        "runs/online_dt/t/policy.pt", 3, 30, (0.5,), True)
    distill = load_recipe("distill").DistillConfig
    student = parse_config(distill, student_stage_args("ClothFoldDiagonalPinned", "t.pt", "e.pt", "--eval-episodes 5",
                                                       parallel=False))
    assert (student.teacher, student.encoder, student.eval_episodes, student.parallel) == ("t.pt", "e.pt", 5, False)
    assert parse_config(distill, student_stage_args("ClothFold", "t.pt", "e.pt")).eval_episodes == 0
    masked = encoder_stage_args("ClothFoldDiagonalPinned", "t.pt", "--epochs 2", parallel=False,
                                mask_unseen_pickers=True)
    assert masked == ["--task", "ClothFoldDiagonalPinned", "--teacher", "t.pt", "--mask-unseen-pickers",
                      "--epochs", "2"]
    assert "--mask-unseen-pickers" in teacher_stage_args("ClothFold", mask_unseen_pickers=True)


def test_pipeline_and_table1_run_the_same_method():
    """The pipeline's and Table I's stage options default to trakdis.method's, so the TraKDis of the table is
    the pipeline's (Table I adds only its curves' evaluations to the student)."""
    pipeline = load_recipe("pipeline").PipelineConfig()
    table1 = load_benchmark().Table1Config()
    assert pipeline.teacher_args == table1.teacher_args == TEACHER_ARGS
    assert pipeline.encoder_args == table1.encoder_args == ENCODER_ARGS
    assert pipeline.student_args == STUDENT_ARGS and "--eval-episodes" in table1.student_args


@pytest.mark.parametrize("bad", ["--members 0", "--select-episodes 5 --members 1"])
def test_a_bad_encoder_option_is_refused_while_parsing(bad, capsys):
    with pytest.raises(SystemExit):
        parse_config(load_recipe("train_encoder").TrainEncoderConfig, encoder_stage_args("ClothFold", "t.pt", bad))
    captured = capsys.readouterr()
    assert "--members" in captured.out + captured.err


def test_every_stage_reads_the_same_expert_data_per_task():
    """TaskDefaults.close_radius (trakdis.method.data_args): on ClothFold every stage (and Table I's image baselines) reads demonstrations whose
    grasps close within 1 cm, not the task expert's 2 cm (docs/recipes/pipeline.md); the diagonal folds' the
    default; a caller's option still wins."""
    from trakdis.method import baseline_stage_args, data_args

    assert data_args("ClothFold") == ["--data.close-radius", "0.01"] and data_args("ClothFoldDiagonalPinned") == []
    recipes = {"online_dt": "OnlineDTConfig", "train_encoder": "TrainEncoderConfig", "distill": "DistillConfig",
               "bc_image": "BCImageConfig", "dt_image": "DTImageConfig"}
    configs = {name: getattr(load_recipe(name), cls) for name, cls in recipes.items()}
    stages = {"online_dt": teacher_stage_args("ClothFold"), "train_encoder": encoder_stage_args("ClothFold", "t.pt"),
              "distill": student_stage_args("ClothFold", "t.pt", "e.pt"),
              "bc_image": baseline_stage_args("ClothFold"), "dt_image": baseline_stage_args("ClothFold", "--updates 3")}
    for name, args in stages.items():
        assert parse_config(configs[name], args).data.close_radius == 0.01, name
    assert parse_config(configs["online_dt"], stages["online_dt"]).data.episodes == parse_config(
        configs["train_encoder"], stages["train_encoder"]).data.episodes  # one dataset for both stages
    assert parse_config(configs["dt_image"], stages["dt_image"]).updates == 3
    assert parse_config(configs["bc_image"], baseline_stage_args("ClothFoldDiagonalPinned")).eval_episodes == 0
    assert parse_config(configs["online_dt"], teacher_stage_args("ClothFoldDiagonalUnpinned")).data.close_radius is None
    overridden = teacher_stage_args("ClothFold", TEACHER_ARGS + " --data.close-radius 0.02")
    assert parse_config(configs["online_dt"], overridden).data.close_radius == 0.02


class FakeStages:
    """Records the stages run (nothing trained); a teacher candidate's selection episodes score ``scores[i]``."""

    def __init__(self, root: Path, scores: list[list[float]]):
        self.root, self.scores, self.calls, self.printed = root, scores, [], []
        self.pipeline = type("Pipeline", (), {"dir": root, "print": lambda _, line: self.printed.append(line)})()

    def run(self, recipe, run_name, output, args, *, seed=None, **scheduling):
        self.calls.append((recipe, run_name, list(args), seed))
        directory = self.root / recipe / run_name
        directory.mkdir(parents=True, exist_ok=True)
        if recipe == "evaluate" and run_name.endswith("-select"):  # the candidate whose policy this one plays
            policy = Path(args[args.index("--policy") + 1]).name
            i = int(policy.rsplit("-c", 1)[1]) if "-teacher-c" in policy else 0
            pd.DataFrame({"state_noise": 0.0, "final_normalized_performance": self.scores[i]}).to_csv(
                directory / "episodes.csv", index=False)
        return directory

    submit = run  # queued evaluations: recorded like the others

    def first_of(self, group, *args, **kwargs):
        return self.run(*args, **kwargs)

    def wait(self, directory):
        return directory


def test_teacher_stage_keeps_the_candidate_that_folds_best_on_the_train_split(tmp_path):
    """Candidate i: its own run and seed (0: the plain stage); all play the same train-split episodes; the kept one
    and every score recorded; one candidate: the plain stage alone, nothing played."""
    good, collapsed = [0.8, 0.85, 0.75, 0.9], [0.1, 0.3, 0.0, 0.2]
    stages = FakeStages(tmp_path, [collapsed, good, [0.5, 0.6, 0.4, 0.5]])
    args = teacher_stage_args("ClothFoldDiagonalPinned")
    teacher, kept = teacher_stage(stages, "p-teacher", args, seed=3, candidates=3, select_episodes=4, parallel=False)
    assert kept == 1 and teacher == tmp_path / "online_dt" / "p-teacher-c1"
    trained = [(name, seed) for recipe, name, a, seed in stages.calls if recipe == "online_dt"]
    assert trained == [("p-teacher", 3), ("p-teacher-c1", 3 + CANDIDATE_SEED_STRIDE),
                       ("p-teacher-c2", 3 + 2 * CANDIDATE_SEED_STRIDE)]
    assert all(a == args for recipe, _, a, _ in stages.calls if recipe == "online_dt")
    selections = [(a, seed) for recipe, _, a, seed in stages.calls if recipe == "evaluate"]
    assert len(selections) == 3 and {seed for _, seed in selections} == {3}  # the same configurations
    for a, _ in selections:
        assert a[a.index("--split") + 1] == "train" and a[a.index("--trials") + 1] == "4" and "--parallel" not in a
    record = json.loads((tmp_path / "p-teacher-selection.json").read_text())
    assert record["kept"] == 1 and record["scores"][1] == good and record["teachers"][1] == str(teacher)
    assert "p-teacher-c1 kept" in stages.printed[-1]
    # the best mean by default; with a margin, candidate 0 within that many standard errors of the best stays
    close = [0.85, 0.8, 0.8, 0.9]
    stages = FakeStages(tmp_path / "b", [good, close])
    assert teacher_stage(stages, "q-teacher", args, seed=0, candidates=2, select_episodes=4)[1] == 1
    assert teacher_stage(stages, "q-teacher", args, seed=0, candidates=2, select_episodes=4, margin=1.0)[1] == 0
    stages = FakeStages(tmp_path / "c", [good])
    assert teacher_stage(stages, "r-teacher", args, seed=5) == (tmp_path / "c" / "online_dt" / "r-teacher", 0)
    assert [c[0] for c in stages.calls] == ["online_dt"] and not (tmp_path / "c" / "r-teacher-selection.json").exists()
    for bad in ({"candidates": 0}, {"candidates": 2, "select_episodes": 1}):
        with pytest.raises(ValueError, match="candidates"):
            teacher_stage(stages, "s-teacher", args, seed=0, **bad)


def test_the_papers_no_distill_is_a_fresh_dt_on_the_experts_actions_with_the_teachers_offline_recipe():
    """no_distill_stage_args after a student stage's: no weight copy, the expert's actions (no teacher label, no
    expert-action term), the last round kept, and the teacher's offline updates, windows and optimiser spread over the
    student's rounds (rounded up), whatever the two stages' own options say."""
    online_dt, distill = load_recipe("online_dt"), load_recipe("distill")

    def arm(teacher_extra: str, student_extra: str):
        teacher = parse_config(online_dt.OnlineDTConfig, teacher_stage_args("ClothFold", teacher_extra),
                               presets=online_dt.PRESETS)
        args = student_stage_args("ClothFold", "t.pt", "e.pt", student_extra)
        student = parse_config(distill.DistillConfig, args, presets=distill.PRESETS)
        return teacher, parse_config(distill.DistillConfig, [*args, *no_distill_stage_args(teacher, student)],
                                     presets=distill.PRESETS)

    teacher, paper = arm(TEACHER_ARGS, "--lr 3e-4 --select-episodes 30 --batch-size 16")
    assert (paper.weight_copy, paper.distill, paper.expert_actions, paper.episodes_per_round) == (False, False, False, 0)
    assert paper.select_episodes == 0 and paper.rounds == 10 and paper.rounds * paper.updates_per_round == 1500
    for option in ("batch_size", "optimizer", "lr", "weight_decay", "warmup_steps", "grad_clip", "min_lr_fraction"):
        assert getattr(paper, option) == getattr(teacher, option), option
    assert (paper.lr, paper.min_lr_fraction) == (1e-3, 0.1)  # decayed as the teacher's offline phase
    teacher, paper = arm("--preset paper", "--preset paper")  # 5000 updates of 256 windows over 60 rounds
    assert (paper.rounds, paper.updates_per_round, paper.batch_size, paper.optimizer, paper.lr) == (
        60, 84, 256, "lamb", 1e-4)
    assert arm(TEACHER_ARGS, "--rounds 0")[1].updates_per_round == 1500  # no rounds: the budget in one


@pytest.mark.parametrize("bad", [["--teacher-candidates", "0"],
                                 ["--teacher-candidates", "2", "--teacher-select-episodes", "1"],
                                 ["--teacher-select-margin", "-1"]])
def test_a_bad_teacher_candidates_option_is_refused_while_parsing(bad):
    for config in (load_recipe("pipeline").PipelineConfig, load_benchmark().Table1Config):
        with pytest.raises((ValueError, SystemExit)):
            parse_config(config, bad)


def test_table1_names_the_stages_after_the_kept_teacher(tmp_path):
    """--teacher-candidates 2: the encoder, the students and their evaluations of a seed whose candidate 1 is kept
    are named <...>-c1-...; the baselines and the expert, which do not depend on the teacher, keep their names."""
    bench = load_benchmark()
    methods = ["teacher", "trakdis", "no_distill", "bc_image"]
    cfg = parse_config(bench.Table1Config, ["--teacher-candidates", "2", "--noise-levels", "--methods", *methods])
    stages = FakeStages(tmp_path, [[0.0, 0.1, 0.0], [0.8, 0.9, 0.7]])
    evals, _, students = bench.run_task_seed(stages, cfg, "t", "ClothFold", 1)
    names = [name for _, name, _, _ in stages.calls]
    assert {"t-ClothFold-s1-c1-encoder", "t-ClothFold-s1-c1-trakdis", "t-ClothFold-s1-c1-no_distill_paper",
            "t-ClothFold-s1-c1-eval-teacher", "t-ClothFold-s1-bc_image", "t-ClothFold-s1-eval-bc_image"} <= set(names)
    assert not any(n.endswith("-s1-encoder") for n in names)
    encoder = next(a for r, n, a, _ in stages.calls if r == "train_encoder")
    assert encoder[encoder.index("--teacher") + 1] == str(tmp_path / "online_dt" / "t-ClothFold-s1-teacher-c1")
    assert students["trakdis"] == tmp_path / "distill" / "t-ClothFold-s1-c1-trakdis"
    assert evals["teacher"] == tmp_path / "evaluate" / "t-ClothFold-s1-c1-eval-teacher"


def test_the_teacher_candidates_default_is_the_tasks(tmp_path):
    """No --teacher-candidates: three on the diagonal folds, one on ClothFold (TaskDefaults.teacher_candidates);
    a number given is used on every task; --quick stays at one."""
    assert [teacher_candidates(t) for t in ("ClothFold", "ClothFoldDiagonalPinned", "ClothFoldDiagonalUnpinned")] \
        == [1, 3, 3]
    assert teacher_candidates("ClothFoldDiagonalPinned", 1) == 1 and teacher_candidates("ClothFold", 2) == 2
    bench = load_benchmark()
    cfg = parse_config(bench.Table1Config, ["--noise-levels", "--methods", "teacher"])
    for task, trained in (("ClothFold", 1), ("ClothFoldDiagonalUnpinned", 3)):
        stages = FakeStages(tmp_path / task, [[0.5, 0.6], [0.1, 0.2], [0.7, 0.9]])
        bench.run_task_seed(stages, cfg, "t", task, 0)
        assert sum(recipe == "online_dt" for recipe, *_ in stages.calls) == trained
    quick = parse_config(bench.Table1Config, ["--preset", "quick"], presets=bench.PRESETS)
    assert quick.teacher_candidates == 1
    pipeline = load_recipe("pipeline").PipelineConfig
    assert parse_config(pipeline, []).teacher_candidates is None
    with pytest.raises((ValueError, SystemExit)):  # the task's three need episodes to compare them
        parse_config(pipeline, ["--teacher-select-episodes", "1"])
