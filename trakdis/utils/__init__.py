"""Generic helpers that know nothing of trakdis's domain (no import from trakdis outside
``trakdis.utils``): dataclass CLI configs (tyro) and ``config.json``, run directories and the
``Run`` skeleton, wide CSV logs (a TorchRL ``Logger``; TensorBoard/W&B through TorchRL's
loggers), OpenCV plots, atomic writes and checkpoints, RNG state, phase timers, videos and
progress bars."""
from .checkpoint import (
    FileFormatError,
    atomic_write_bytes,
    capture_state,
    read_checkpoint,
    restore_state,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from .config import (
    apply_overrides,
    config_from_dict,
    config_to_dict,
    load_config,
    parse_config,
    save_config,
)
from .logger import WideCSVLogger, latest_run_dir, make_run_dir, make_torchrl_logger
from .plot import plot_csv, plot_curves
from .progress import progress
from .run import Run, RunConfig, seed_everything
from .video import VideoWriter, side_by_side, write_video

__all__ = [
    "FileFormatError",
    "atomic_write_bytes",
    "capture_state",
    "read_checkpoint",
    "restore_state",
    "rng_state",
    "save_checkpoint",
    "set_rng_state",
    "apply_overrides",
    "config_from_dict",
    "config_to_dict",
    "load_config",
    "parse_config",
    "save_config",
    "WideCSVLogger",
    "latest_run_dir",
    "make_run_dir",
    "make_torchrl_logger",
    "plot_csv",
    "plot_curves",
    "progress",
    "Run",
    "RunConfig",
    "seed_everything",
    "VideoWriter",
    "side_by_side",
    "write_video",
]
