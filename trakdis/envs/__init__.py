"""MuJoCo cloth-folding tasks (gymnasium), scripted experts, the TorchRL factory and batched envs.

Importing this package sets ``MUJOCO_GL=egl`` if no GL backend is chosen (before MuJoCo is
imported) and registers the gymnasium ids ``trakdis/<Task>-v0``.
"""

from trakdis.envs.rendering import configure_gl

configure_gl()

import gymnasium as _gym  # noqa: E402

from trakdis.envs.cloth_env import (  # noqa: E402
    ClothEnv,
    ClothFoldDiagonalPinnedEnv,
    ClothFoldDiagonalUnpinnedEnv,
    ClothFoldEnv,
    ENV_CLASSES,
)
from trakdis.envs.experts import EXPERT_VERSION, ExpertPolicy, add_movement_noise, expert_action, expert_version  # noqa: E402
from trakdis.envs.model import PICKER_MARKER_RADIUS, camera_fovy, render_version  # noqa: E402
from trakdis.envs.specs import TASKS, ClothConfig, TaskName, TaskSpec, cloth_config, task_spec  # noqa: E402
from trakdis.envs.task_defaults import TASK_DEFAULTS, TaskDefaults, task_defaults  # noqa: E402
from trakdis.envs.torchrl_env import ClothInfoReader, make_env, with_contract_keys  # noqa: E402
from trakdis.envs.batched import SleepWaitParallelEnv, close_env, make_batched_env, start_in_background  # noqa: E402

for _task, _cls in ENV_CLASSES.items():
    _id = f"trakdis/{_task}-v0"
    if _id not in _gym.registry:
        _gym.register(id=_id, entry_point=f"{_cls.__module__}:{_cls.__name__}")

__all__ = [
    "EXPERT_VERSION",
    "camera_fovy",
    "render_version",
    "PICKER_MARKER_RADIUS",
    "add_movement_noise",
    "TASKS",
    "TaskName",
    "TaskSpec",
    "ClothConfig",
    "task_spec",
    "TaskDefaults",
    "TASK_DEFAULTS",
    "task_defaults",
    "cloth_config",
    "ClothEnv",
    "ClothFoldEnv",
    "ClothFoldDiagonalPinnedEnv",
    "ClothFoldDiagonalUnpinnedEnv",
    "ExpertPolicy",
    "expert_action",
    "expert_version",
    "make_env",
    "ClothInfoReader",
    "with_contract_keys",
    "make_batched_env",
    "SleepWaitParallelEnv",
    "close_env",
    "start_in_background",
]
