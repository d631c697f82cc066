"""Expert datasets on disk, the episode layout, and the offline-to-online trajectory replay buffer.

* :mod:`.layout`: the per-step keys of an episode, the valid-step mask, rollout -> dataset layout;
* :mod:`.dataset`: collection and the on-disk format (memory-mapped, versioned, atomic, resumable);
* :mod:`.labels`: the actions a policy learns (recorded, or the scripted expert's noise-free ones);
* :mod:`.buffer`: ``TrajectoryReplayBuffer`` (left-padded windows, hindsight return-to-go);
* :mod:`.loading`: the recipes' ``--data.*`` section, finding or collecting a dataset, loading it,
  making a buffer (a teacher's buffer of states and its options: ``StateBufferConfig``; an encoder's training
  and validation steps and theirs: ``EncoderDataConfig``).
"""

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
from .labels import ACTION_LABELS, ActionLabels, expert_labels, expert_targets
from .layout import (ACTING_KEYS, REQUIRED_KEYS, STEP_KEYS, encode_trajectories, episode_to_trajectory, real_steps,
                     split_episodes_train_val, valid_mask)
from .loading import (DataConfig, EncoderDataConfig, TrainValSteps, default_dataset_path, ensure_dataset, ensure_dataset_timed,
                      load_encoded_dataset, load_offline_data, load_train_val_steps, load_trajectories, make_buffer,
                      offline_state_buffer, StateBufferConfig, student_buffer)

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
    "ACTION_LABELS",
    "ActionLabels",
    "expert_labels",
    "expert_targets",
    "ACTING_KEYS",
    "REQUIRED_KEYS",
    "STEP_KEYS",
    "encode_trajectories",
    "episode_to_trajectory",
    "real_steps",
    "split_episodes_train_val",
    "valid_mask",
    "DataConfig",
    "EncoderDataConfig",
    "TrainValSteps",
    "default_dataset_path",
    "ensure_dataset",
    "ensure_dataset_timed",
    "load_encoded_dataset",
    "load_offline_data",
    "load_train_val_steps",
    "load_trajectories",
    "make_buffer",
    "offline_state_buffer",
    "StateBufferConfig",
    "student_buffer",
]
