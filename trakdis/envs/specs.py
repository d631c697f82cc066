"""Task names, shapes and the domain-randomization configuration pools.

Everything here is pure Python/numpy (no MuJoCo import) so that other parts of the package
(models, data, augmentation) can ask for shapes without touching the simulator.
"""

from __future__ import annotations

import dataclasses
import math
import typing

import numpy as np

TaskName = typing.Literal["ClothFold", "ClothFoldDiagonalPinned", "ClothFoldDiagonalUnpinned"]
"""The task names as a type (the recipes' ``--task`` choices)."""
TASKS = typing.get_args(TaskName)
SPLITS = ("train", "eval")

# Number of distinct domain-randomization configurations per split. The train and eval pools are
# generated from different random streams (different ``split`` salt), so they are disjoint sets of
# continuous parameter vectors; ``tests/envs/test_randomization.py`` checks it.
CONFIG_POOL_SIZE = 1000

# Corner order of the reduced state, as grid indices (ix, iy) of the N x N vertex grid
# (MuJoCo flexcomp grid index = ix * N + iy; ix runs along the cloth's local x axis).
CORNERS = ("c00", "c0N", "cN0", "cNN")


def check_task(task: str) -> str:
    """Return ``task`` if it is a known task name, else raise a ``ValueError`` naming the choices."""
    if task not in TASKS:
        raise ValueError(f"Unknown task {task!r}; expected one of {TASKS}.")
    return task


def check_split(split: str) -> str:
    if split not in SPLITS:
        raise ValueError(f"Unknown split {split!r}; expected one of {SPLITS}.")
    return split


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """Static facts about a task.

    Attributes:
        name: task name (one of :data:`TASKS`).
        num_pickers: number of pickers (2 for ClothFold, 1 for the diagonal folds).
        state_dim: 12 (four corners xyz) + 3 * num_pickers.
        action_dim: 4 * num_pickers, ``[dx, dy, dz, pick]`` per picker in [-1, 1].
        horizon: episode length (truncation).
        state_mirror: ``(perm, sign)``; the reduced state of the horizontally flipped image is
            ``state[..., perm] * sign``. The camera sits in the plane x = 0 with its image x axis
            along world +x, so a horizontal image flip is the world reflection x -> -x; the cloth
            reflected that way has its grid index ix reversed (corners c00 <-> cN0, c0N <-> cNN)
            and, for two pickers, picker 0 <-> picker 1 (picker 0 always works on the ix = 0 side).
        gym_id: gymnasium id ``trakdis/<name>-v0``.
    """

    name: str
    num_pickers: int
    state_dim: int
    action_dim: int
    horizon: int
    state_mirror: tuple[tuple[int, ...], tuple[float, ...]]
    gym_id: str

    @property
    def grasp_dims(self) -> tuple[int, ...]:
        """The action dims of the pickers' grasp commands (``pick``, the 4th of each picker's 4)."""
        return tuple(range(3, self.action_dim, 4))

    @property
    def state_groups(self) -> dict[str, slice]:
        """The reduced state's parts: ``corners`` (dims 0-11) and ``pickers`` (the rest), xyz each."""
        return {"corners": slice(0, 12), "pickers": slice(12, self.state_dim)}

    def state_error_cm(self, abs_error) -> dict[str, float]:
        """Mean absolute error ``[..., state_dim]`` (metres) per state group, in centimetres
        (``corners_cm``, ``pickers_cm``), and over all dims in state units (``mae``)."""
        if abs_error.shape[-1] != self.state_dim:
            raise ValueError(f"state_error_cm: {self.name} states have {self.state_dim} dims, got shape {tuple(abs_error.shape)}")
        out = {f"{name}_cm": 100.0 * float(abs_error[..., dims].mean()) for name, dims in self.state_groups.items()}
        out["mae"] = float(abs_error.mean())
        return out


def _mirror(num_pickers: int) -> tuple[tuple[int, ...], tuple[float, ...]]:
    # blocks of 3 (xyz): corners c00, c0N, cN0, cNN, then pickers
    corner_perm = [2, 3, 0, 1]
    picker_perm = list(range(num_pickers))[::-1]
    blocks = corner_perm + [4 + p for p in picker_perm]
    perm = tuple(3 * b + k for b in blocks for k in range(3))
    sign = tuple(-1.0 if k == 0 else 1.0 for _ in blocks for k in range(3))
    return perm, sign


def task_spec(task: str, horizon: int = 100) -> TaskSpec:
    """Shapes and constants of ``task`` (see :class:`TaskSpec`)."""
    check_task(task)
    num_pickers = 2 if task == "ClothFold" else 1
    return TaskSpec(
        name=task,
        num_pickers=num_pickers,
        state_dim=12 + 3 * num_pickers,
        action_dim=4 * num_pickers,
        horizon=horizon,
        state_mirror=_mirror(num_pickers),
        gym_id=f"trakdis/{task}-v0",
    )


# ---------------------------------------------------------------------------------------------
# Domain randomization
# ---------------------------------------------------------------------------------------------
# Ranges (uniform unless marked log-uniform). Distributions are symmetric under x -> -x so that
# mirrored configurations are as likely as the originals (flip augmentation stays in-distribution).
RANDOMIZATION = {
    # cloth side lengths in metres (ClothFold: independent width/length; diagonal: square)
    "size": (0.24, 0.34),
    # rotation about the vertical axis, degrees (|angle| < 45 keeps corner identities unambiguous
    # in an image of a uniformly coloured cloth)
    "rotation_deg": (-30.0, 30.0),
    # cloth centre offset on the table, metres (x and y)
    "offset": (-0.02, 0.02),
    # total cloth mass, kg (log-uniform)
    "mass": (0.05, 0.2),
    # bending stiffness: Young's modulus of the shell bending model, Pa (log-uniform)
    "young": (2e3, 2e4),
    # stretch stiffness: time constant of the inextensibility (edge equality) constraint, s
    "stretch_timeconst": (0.015, 0.04),
    # edge damping (stretch damping), N s / m (log-uniform)
    "damping": (5e-4, 5e-3),
    # sliding friction of cloth contacts (cloth-table and cloth-cloth)
    "friction": (0.6, 1.2),
}


@dataclasses.dataclass(frozen=True)
class ClothConfig:
    """One domain-randomization draw (all lengths in metres, angles in radians)."""

    size_x: float
    size_y: float
    rotation: float
    offset_x: float
    offset_y: float
    mass: float
    young: float
    stretch_timeconst: float
    damping: float
    friction: float

    def as_array(self) -> np.ndarray:
        return np.array(dataclasses.astuple(self), dtype=np.float64)


def _uniform(rng, key):
    lo, hi = RANDOMIZATION[key]
    return float(rng.uniform(lo, hi))


def _loguniform(rng, key):
    lo, hi = RANDOMIZATION[key]
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def cloth_config(task: str, split: str, index: int) -> ClothConfig:
    """The ``index``-th configuration of the ``split`` pool of ``task`` (deterministic)."""
    check_task(task)
    check_split(split)
    if not 0 <= index < CONFIG_POOL_SIZE:
        raise ValueError(f"config index must be in [0, {CONFIG_POOL_SIZE}), got {index}")
    rng = np.random.default_rng([TASKS.index(task), SPLITS.index(split), index, 20240125])
    size_x = _uniform(rng, "size")
    size_y = _uniform(rng, "size") if task == "ClothFold" else size_x
    return ClothConfig(
        size_x=size_x,
        size_y=size_y,
        rotation=math.radians(_uniform(rng, "rotation_deg")),
        offset_x=_uniform(rng, "offset"),
        offset_y=_uniform(rng, "offset"),
        mass=_loguniform(rng, "mass"),
        young=_loguniform(rng, "young"),
        stretch_timeconst=_uniform(rng, "stretch_timeconst"),
        damping=_loguniform(rng, "damping"),
        friction=_uniform(rng, "friction"),
    )
