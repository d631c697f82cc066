"""Expert datasets on disk and the offline-to-online trajectory replay buffer."""

from .buffer import TrajectoryReplayBuffer, WindowSampler

__all__ = ["TrajectoryReplayBuffer", "WindowSampler"]
