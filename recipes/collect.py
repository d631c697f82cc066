"""Collect an expert dataset with the scripted expert (the paper: 8000 episodes x 100 steps per task).

    python recipes/collect.py --task ClothFold                        # 40 episodes, states + 32x32 images
    python recipes/collect.py --task ClothFold --episodes 8000        # the paper's size (hours on a CPU)
    python recipes/collect.py --task ClothFold --no-pixels            # states only

The dataset directory (default ``datasets/<task>_<N>ep_h<horizon>_noise<sigma>[_seed<k>][_px<size>]``, or
``--path``) is the on-disk format of :mod:`trakdis.data` (``meta.json`` + memory-mapped
TensorDict ``[episodes, horizon]``). Collection is resumable: run the same command again after
an interruption and it continues. ``online_dt.py``, ``train_encoder.py`` and ``distill.py`` collect
the dataset they need themselves when it is missing, with the same naming.
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from typing import Optional

import torch

from trakdis.data import DataConfig, ensure_dataset, load_trajectories
from trakdis.envs.specs import TaskName
from trakdis.utils.config import parse_config
from trakdis.utils.limits import MAX_HORIZON, cap_workers, check_option, check_options
from trakdis.utils.phases import available_workers


@dataclass
class CollectConfig:
    """Collect scripted-expert episodes into a dataset directory."""

    task: TaskName = "ClothFold"
    """cloth task"""
    horizon: int = 100
    """episode length"""
    pixels: bool = True
    """also store the 32x32 camera images (needed by train_encoder.py and distill.py --no-distill)"""
    image_size: int = 32
    """image side"""
    episodes: int = DataConfig.episodes
    """episodes to collect"""
    expert_noise: float = DataConfig.expert_noise
    """std of the Gaussian noise added to the expert's picker movements (the grasp command stays +-1)"""
    close_radius: Optional[float] = DataConfig.close_radius
    """metres: the expert closes a picker on a corner still on the table within this distance (default: the task's)"""
    path: Optional[str] = None
    """dataset directory (default: <root>/<task>_<episodes>ep_h<horizon>_noise<sigma>[_close<r>][_px<size>])"""
    root: str = DataConfig.root
    """where default dataset directories live"""
    num_envs: int = field(default_factory=available_workers)
    """environments stepped together, one worker process each when > 1 (default: the available cores, at most 2)"""
    seed: Optional[int] = None
    """seed of the expert noise and of the environments (default: 0, the default path's, as every recipe's data;
    when set, part of the default path, _seed<k>, as the recipes' --data.seed)"""
    threads: int = 1
    """torch CPU threads"""
    progress: bool = True
    """show a progress bar"""

    def __post_init__(self):  # while parsing (tyro), before anything is written
        check_options(self, sizes=("horizon", "episodes", "num_envs", "image_size"), counts=("threads", "seed"),
                      nonnegative=("expert_noise",), positive=("close_radius",))
        check_option("horizon", self.horizon, le=MAX_HORIZON, integer=True)


def main(argv=None):
    cfg = parse_config(CollectConfig, argv, description=__doc__)
    torch.set_num_threads(max(1, cfg.threads))
    t0 = time.time()
    num_envs = cap_workers(cfg.num_envs, cfg.episodes, what="--num-envs", warn=print)  # no idle worker processes
    data = DataConfig(path=cfg.path, root=cfg.root, episodes=cfg.episodes, expert_noise=cfg.expert_noise,
                      close_radius=cfg.close_radius, num_envs=num_envs, seed=cfg.seed)
    path = ensure_dataset(data, task=cfg.task, horizon=cfg.horizon, seed=0, pixels=cfg.pixels,
                          image_size=cfg.image_size, progress=cfg.progress)
    td, lengths = load_trajectories(path)
    rets = td["reward"].sum(dim=(-2, -1))
    perf = td["normalized_performance"][torch.arange(len(lengths)), lengths - 1].reshape(-1)
    print(f"dataset {path}: {td.shape[0]} episodes x {td.shape[1]} steps, keys {sorted(td.keys())}")
    print(f"  return {rets.mean():.3f} +- {rets.std():.3f}; final normalized performance {perf.mean():.3f} "
          f"+- {perf.std():.3f}; {time.time() - t0:.0f} s")
    return path


if __name__ == "__main__":
    main(sys.argv[1:])
