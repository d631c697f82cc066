"""Expert datasets on disk and the offline-to-online trajectory replay buffer."""

# ``import torchrl.envs`` imports mujoco, which fixes its GL backend at import time: choose it first
# (MUJOCO_GL=egl when unset) so that pixel collection works whatever the user imported before.
from trakdis.envs.rendering import configure_gl as _configure_gl

_configure_gl()

from .buffer import TrajectoryReplayBuffer, WindowSampler
from .dataset import (
    DATASET_FORMAT,
    DATASET_VERSION,
    DatasetError,
    collect_expert_dataset,
    load_dataset,
    partial_path,
)

__all__ = [
    "DATASET_FORMAT",
    "DATASET_VERSION",
    "DatasetError",
    "TrajectoryReplayBuffer",
    "WindowSampler",
    "collect_expert_dataset",
    "load_dataset",
    "partial_path",
]
