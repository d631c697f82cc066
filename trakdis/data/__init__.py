"""Expert datasets on disk and the offline-to-online trajectory replay buffer."""

# The GL backend for pixel collection is chosen by ``trakdis/__init__.py`` (imported before this
# subpackage) and, if mujoco was loaded earlier, by ``trakdis.envs.rendering.adopt_configured_backend``.
from .buffer import TrajectoryReplayBuffer, WindowSampler
from .dataset import (
    DATASET_FORMAT,
    DATASET_VERSION,
    DatasetError,
    collect_expert_dataset,
    load_expert_dataset,
    partial_path,
    read_meta,
)

__all__ = [
    "DATASET_FORMAT",
    "DATASET_VERSION",
    "DatasetError",
    "TrajectoryReplayBuffer",
    "WindowSampler",
    "collect_expert_dataset",
    "load_expert_dataset",
    "partial_path",
    "read_meta",
]
