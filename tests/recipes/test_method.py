"""trakdis.method: the one definition of the method's stages, read by recipes/pipeline.py and benchmarks/table1.py."""
import pytest

from trakdis.method import (ENCODER_ARGS, STUDENT_ARGS, TEACHER_ARGS, encoder_stage_args, student_stage_args,
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
    assert (teacher.state_noise, teacher.state_scale_floor, teacher.online_rounds) == (0.01, 0.02, 0)
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
    """trakdis.method.DATA_ARGS: on ClothFold every stage (and Table I's image baselines) reads demonstrations whose
    grasps close within 1 cm, not the task expert's 2 cm (docs/recipes/pipeline.md); the diagonal folds' the
    default; a caller's option still wins."""
    from trakdis.method import DATA_ARGS, baseline_stage_args, data_args

    assert DATA_ARGS == {"ClothFold": "--data.close-radius 0.01"} and data_args("ClothFoldDiagonalPinned") == []
    recipes = {"online_dt": "OnlineDTConfig", "train_encoder": "TrainEncoderConfig", "distill": "DistillConfig",
               "bc_image": "BCImageConfig", "dt_image": "DTImageConfig"}
    configs = {name: getattr(load_recipe(name), cls) for name, cls in recipes.items()}
    stages = {"online_dt": teacher_stage_args("ClothFold"), "train_encoder": encoder_stage_args("ClothFold", "t.pt"),
              "distill": student_stage_args("ClothFold", "t.pt", "e.pt"),
              "bc_image": baseline_stage_args("ClothFold"), "dt_image": baseline_stage_args("ClothFold", "--updates 3")}
    for name, args in stages.items():
        assert parse_config(configs[name], args).data.close_radius == 0.01, name
    assert parse_config(configs["dt_image"], stages["dt_image"]).updates == 3
    assert parse_config(configs["bc_image"], baseline_stage_args("ClothFoldDiagonalPinned")).eval_episodes == 0
    assert parse_config(configs["online_dt"], teacher_stage_args("ClothFoldDiagonalUnpinned")).data.close_radius is None
    overridden = teacher_stage_args("ClothFold", TEACHER_ARGS + " --data.close-radius 0.02")
    assert parse_config(configs["online_dt"], overridden).data.close_radius == 0.02
