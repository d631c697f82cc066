"""The grasp head (``--model.grasp-head``) through the recipes: a teacher trained with it offline and online
(DAgger's rollouts sample from it), saved, distilled into a student that keeps it, and the student evaluated."""
import pandas as pd
import torch
from tensordict import TensorDict

from trakdis.modules import GraspConditionedTanhNormal, find_dt_actor
from trakdis.policies import load_policy

from .conftest import distill_args, online_dt_args, run_recipe


def _window(config) -> TensorDict:
    k = config.context_len
    return TensorDict({"state": torch.zeros(1, k, config.state_dim), "action": torch.zeros(1, k, config.action_dim),
                       "return_to_go": torch.zeros(1, k, 1), "timestep": torch.zeros(1, k, dtype=torch.long),
                       "mask": torch.ones(1, k, dtype=torch.bool)}, [1, k])


def test_a_grasp_head_teacher_and_its_student(workdir, dataset, encoder):
    # ClothFold hides its grasp commands from the action tokens by default; the grasp head must read them
    run_recipe(workdir, "online_dt", *online_dt_args("grasp-teacher", "--model.grasp-head", "--eval-every", 2,
                                                     "--model.hidden-action-dims"))
    teacher = load_policy(workdir / "runs" / "online_dt" / "grasp-teacher")
    config = find_dt_actor(teacher.actor).config
    assert config.grasp_head and config.grasp_dims == (3, 7)  # ClothFold's two pick commands
    assert isinstance(teacher.actor.get_dist(_window(config)), GraspConditionedTanhNormal)
    log = pd.read_csv(workdir / "runs" / "online_dt" / "grasp-teacher" / "log.csv")
    assert log["train/loss_nll"].notna().sum() >= 3 and log["online/normalized_performance"].notna().sum() == 2

    args = distill_args("grasp-student")
    args[args.index("--teacher") + 1] = "runs/online_dt/grasp-teacher"
    run_recipe(workdir, "distill", *args)
    student = load_policy(workdir / "runs" / "distill" / "grasp-student")
    assert find_dt_actor(student.actor).config.grasp_head
    assert student.picker_odometry and student.hold_radius == 0.0  # ClothFold's default: no held corner
    # --hold-radius: the saved student acting with the held corner (PickerOdometry), a grasp head's closes included
    run_recipe(workdir, "evaluate", "--name", "grasp-eval", "--policy", "runs/distill/grasp-student", "--trials", 2,
               "--videos", 0, "--threads", 1, "--hold-radius", 0.9)
    episodes = pd.read_csv(workdir / "runs" / "evaluate" / "grasp-eval" / "episodes.csv")
    assert len(episodes) == 2 and episodes["final_normalized_performance"].notna().all()
