"""How mirror-symmetric each task's expert states are: whether the encoder's flip shows the task's own states.

    python benchmarks/mirror_symmetry.py                       # the method's expert dataset of every task
    python benchmarks/mirror_symmetry.py --root datasets --tasks ClothFoldDiagonalPinned

The horizontal flip is label-exact (``TaskSpec.state_mirror``), but a flipped image is one of the task's own states
only where mirrored states are as likely as the originals. Per task, from the reduced states of the method's expert
dataset (the data every stage of ``trakdis.method`` reads; it must exist, e.g. after ``pipeline.py``):

* each corner's travel: its largest distance from where it started, mean over episodes, then the same for the
  mirrored states (a symmetric task shows the same numbers with the corners swapped);
* per corner, the distance between the mean state trajectory and the mean mirrored one, averaged over the steps
  (near 0 for a symmetric task).

The numbers and what they decide: docs/table1.md, "No-Aug on the diagonal folds' current stages".
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from trakdis.data import DataConfig  # noqa: E402
from trakdis.data.loading import default_dataset_path, load_trajectories  # noqa: E402
from trakdis.envs import TASKS, task_defaults, task_spec  # noqa: E402
from trakdis.transforms import mirror_state  # noqa: E402


def mirror_gap(states: torch.Tensor, state_mirror) -> dict[str, list[float]]:
    """``states`` ``[episodes, T, D]`` (corners in dims 0-11, metres): per corner c00, c0N, cN0, cNN, in cm, its mean
    largest travel from the start (``travel``), the same for the mirrored states (``travel_mirrored``), and the mean
    over steps of the distance between the mean state and the mean mirrored state (``mean_gap``)."""
    mirrored = mirror_state(states, *state_mirror)

    def travel(x):
        corners = x[..., :12].unflatten(-1, (4, 3))
        return ((corners - corners[:, :1]).norm(dim=-1).amax(1).mean(0) * 100).tolist()

    gap = (states.mean(0) - mirrored.mean(0))[:, :12].unflatten(-1, (4, 3)).norm(dim=-1).mean(0) * 100
    return {"travel": travel(states), "travel_mirrored": travel(mirrored), "mean_gap": gap.tolist()}


def main(argv=None) -> dict[str, dict]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", choices=TASKS, default=list(TASKS))
    parser.add_argument("--root", default="datasets", help="where the method's datasets live")
    args = parser.parse_args(argv)
    out = {}
    for task in args.tasks:
        data = DataConfig(root=args.root, close_radius=task_defaults(task).close_radius)  # trakdis.method.data_args
        path = default_dataset_path(data, task=task, horizon=100, pixels=True)
        if not path.exists():
            raise SystemExit(f"{task}: no expert dataset at {path}; collect it "
                             f"(python recipes/pipeline.py --task {task})")
        steps, _ = load_trajectories(path, ["state"])
        out[task] = gap = mirror_gap(steps["state"].double(), task_spec(task).state_mirror)
        fmt = lambda xs: " / ".join(f"{x:.1f}" for x in xs)  # noqa: E731
        print(f"{task} ({path}): corner travel c00 / c0N / cN0 / cNN {fmt(gap['travel'])} cm, mirrored "
              f"{fmt(gap['travel_mirrored'])} cm; mean state against mean mirrored state {fmt(gap['mean_gap'])} cm")
    return out


if __name__ == "__main__":
    main()
