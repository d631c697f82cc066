"""Recipe support: dataclass CLI configs, run directories, CSV logs, OpenCV plots, atomic
checkpoints, videos and progress bars."""
from .checkpoint import (
    CheckpointError,
    atomic_write_bytes,
    capture_state,
    load_checkpoint,
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
from .evaluation import EpisodeResults, run_episodes, summarize, write_summary_table
from .logger import WideCSVLogger, latest_run_dir, make_run_dir
from .plot import plot_csv, plot_curves
from .progress import progress
from .run import Run, RunConfig, seed_everything
from .video import VideoWriter, side_by_side, write_video

__all__ = [
    "CheckpointError",
    "atomic_write_bytes",
    "capture_state",
    "load_checkpoint",
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
    "plot_csv",
    "plot_curves",
    "progress",
    "Run",
    "RunConfig",
    "seed_everything",
    "EpisodeResults",
    "run_episodes",
    "summarize",
    "write_summary_table",
    "VideoWriter",
    "side_by_side",
    "write_video",
]
