"""Scripted experts: closed-loop, stateless functions of (reduced state, step count).

Each picker folds one "source" corner onto a "target" corner:

* ClothFold: picker 0 carries c0N onto c00, picker 1 carries cNN onto cN0 (far half onto near).
* Diagonal folds: picker 0 carries c00 onto cNN.

The mode of a picker is read from the state alone, so the expert needs no memory and recovers
from a dropped corner:

* *approach*: the picker is not at its source corner -> move above it, then down onto it.
* *carry*: the picker is at the source corner (so it holds it) -> on the unpinned diagonal fold first
  straight up while the corner still lies on the table (``DEFAULT_GRASP_LIFT``), then along the semicircle that
  an inextensible flap hinged half way to the target would follow. The circle is fitted to the
  current picker position (it passes through the target and the picker, centre on the table
  line through both), the picker advances ``dphi`` along it per step; two pickers share the
  slower one's angle so the folded edge stays straight.
* *done*: the source corner lies on the target corner -> release and lift. A released corner
  that settles within ``placed_radius`` of its target stays done (the picker keeps away): without
  this hysteresis the expert re-grasped a corner that sprang back a few millimetres past
  ``done_radius`` every 3-5 steps until the episode ended, a chattering grasp signal that a
  learner had to imitate (the pinned fold keeps a smaller radius: re-grasping helps there).

At ``step_count >= release_step`` every picker releases (the episode is scored at its end).
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from trakdis.envs.specs import check_task, task_spec

# A released corner this close to its target (horizontally) is left alone. The pinned diagonal fold
# pulls a released corner back by 3-6 cm: re-grasping it then still improves the fold (docs/tasks.md).
DEFAULT_PLACED_RADIUS = {
    "ClothFold": 0.08,
    "ClothFoldDiagonalPinned": 0.04,
    "ClothFoldDiagonalUnpinned": 0.08,
}

# Bumped whenever the expert's behaviour changes; recorded in datasets (``config.expert_version``), per task
# (``expert_version``): a task whose expert did not change keeps its datasets.
# 2: placed corners stay placed (no re-grasp chattering); noise on the movements only.
# 3: the unpinned diagonal fold's grasp lifts its corner straight up first (``DEFAULT_GRASP_LIFT``);
#    ClothFold's pickers close within 2 cm of their corners instead of 1 cm (``DEFAULT_CLOSE_RADIUS``).
EXPERT_VERSIONS = {
    "ClothFold": 3,
    "ClothFoldDiagonalPinned": 2,
    "ClothFoldDiagonalUnpinned": 3,
}
EXPERT_VERSION = max(EXPERT_VERSIONS.values())  # the newest version, of some task's expert


def expert_version(task: str) -> int:
    """The version of ``task``'s scripted expert (recorded in its datasets and cached scores)."""
    return EXPERT_VERSIONS[check_task(task)]

# (source corner, target corner) per picker; corners are blocks 0..3 of the state: c00, c0N, cN0, cNN
FOLD_PLAN = {
    "ClothFold": ((1, 0), (3, 2)),
    "ClothFoldDiagonalPinned": ((0, 3),),
    "ClothFoldDiagonalUnpinned": ((0, 3),),
}

# First carry step, while the grasped corner still lies on the table: the picker rises straight up by this
# much (m) instead of stepping along the fold arc (0: along the arc). On the diagonal folds that first arc
# step lifts the picker by ~5 cm in the step that closes it, so a policy unsure of the closing step (a
# teacher trained on noisy states) averaged the two and moved a still-open picker away from its corner:
# the close then came 5-8 cm off. Measured gain on the unpinned fold's teachers, not on the pinned fold's
# (docs/tasks.md); ClothFold's pickers wait for each other at that step anyway.
DEFAULT_GRASP_LIFT = {
    "ClothFold": 0.0,
    "ClothFoldDiagonalPinned": 0.0,
    "ClothFoldDiagonalUnpinned": 0.008,
}

# A picker closes on a source corner still on the table once it is this close to it (m). At 1 cm, ClothFold's
# teachers hovered 1-2 cm above their corners, where the expert's labels flip between close and descend with
# each centimetre of height; they learned to close at a fixed step instead (20-30 steps late) and DAgger made
# it worse. Within 2 cm the expert scores the same and the teachers close on arrival (docs/tasks.md).
DEFAULT_CLOSE_RADIUS = {
    "ClothFold": 0.02,
    "ClothFoldDiagonalPinned": 0.01,
    "ClothFoldDiagonalUnpinned": 0.01,
}

# Approach: the picker aims ``APPROACH_HEIGHT`` above its source corner until it is within ``ALIGN_RADIUS`` of it
# horizontally, then straight down (``expert_action(..., approach_slope=)`` > 0: down a cone instead; measured no
# better for the teachers, docs/recipes/online_dt.md).
APPROACH_HEIGHT = 0.02  # m above the source corner
ALIGN_RADIUS = 0.008  # m, horizontally: aligned above the corner (approach_slope 0)

# Carry speed (radians of fold arc per step), tuned on eval seeds 2000-2005 (docs/tasks.md):
# the two-picker half fold is best slower, the diagonal folds faster.
DEFAULT_DPHI = {
    "ClothFold": np.pi / 14,
    "ClothFoldDiagonalPinned": np.pi / 10,
    "ClothFoldDiagonalUnpinned": np.pi / 10,
}


def expert_action(
    task: str,
    state: np.ndarray,
    step_count: np.ndarray | int = 0,
    *,
    step_size: float = 0.06,
    dphi: float | None = None,
    layer_height: float = 0.006,
    release_step: int = 95,
    hold_radius: float = 0.05,
    close_radius: float | None = None,
    done_radius: float = 0.02,
    placed_radius: float | None = None,
    grasp_lift: float | None = None,
    approach_slope: float = 0.0,
) -> np.ndarray:
    """Expert action for ``state`` of shape ``[*B, state_dim]`` -> ``[*B, action_dim]`` float32.

    Args:
        task: task name.
        state: reduced state(s).
        step_count: steps since reset, broadcastable to ``[*B]`` (a trailing dim of 1 is fine).
        step_size: the env's maximum picker move per step (``action_repeat * move_per_substep``).
        dphi: carry speed, radians of the fold arc per step (default: per task, ``DEFAULT_DPHI``).
        layer_height: height above the target corner where the source corner is laid (m).
        release_step: from this step on every picker releases and lifts.
        hold_radius: a picker this close to its lifted source corner is taken to hold it.
        close_radius: a picker this close to its source corner still on the table closes on it (default:
            per task, ``DEFAULT_CLOSE_RADIUS``).
        done_radius: a held source corner is released when this close (horizontally) to the target.
        placed_radius: a source corner that is not held counts as placed (nothing left to do) when
            this close (horizontally) to the target and low (default: per task, ``DEFAULT_PLACED_RADIUS``).
        grasp_lift: while a held source corner still lies on the table, the picker rises straight up by
            this much (m) instead of stepping along the fold arc (default: per task, ``DEFAULT_GRASP_LIFT``;
            0: along the arc from the first step).
        approach_slope: an approaching picker aims this many times its horizontal distance above its source corner
            (at most 2 cm), descending as it closes in (0, the default: 2 cm above the corner until within 8 mm of it
            horizontally, then straight down).
    """
    check_task(task)
    spec = task_spec(task)
    if dphi is None:
        dphi = DEFAULT_DPHI[task]
    if placed_radius is None:
        placed_radius = DEFAULT_PLACED_RADIUS[task]
    if grasp_lift is None:
        grasp_lift = DEFAULT_GRASP_LIFT[task]
    if close_radius is None:
        close_radius = DEFAULT_CLOSE_RADIUS[task]
    if not close_radius > 0:  # also NaN
        raise ValueError(f"close_radius must be > 0 (metres), got {close_radius}")
    if not grasp_lift >= 0:  # also NaN
        raise ValueError(f"grasp_lift must be >= 0 (metres), got {grasp_lift}")
    if not approach_slope >= 0:  # also NaN
        raise ValueError(f"approach_slope must be >= 0, got {approach_slope}")
    state = np.asarray(state, dtype=np.float64)
    if state.shape[-1] != spec.state_dim:
        raise ValueError(f"{task}: state must have last dim {spec.state_dim}, got shape {state.shape}")
    batch = state.shape[:-1]
    t = np.asarray(step_count)
    if t.ndim == len(batch) + 1 and t.shape[-1] == 1:
        t = t[..., 0]
    t = np.broadcast_to(t, batch)
    pickers, src, tgt = fold_points(task, state)  # [*B, P, 3] each
    tgt_top = tgt + np.array([0.0, 0.0, layer_height])

    d_src = np.linalg.norm(pickers - src, axis=-1)  # [*B, P]
    src_tgt_xy = np.linalg.norm((src - tgt)[..., :2], axis=-1)
    src_low = src[..., 2] - tgt[..., 2] < 0.025
    src_on_tgt = (src_tgt_xy < done_radius) & src_low
    src_placed = (src_tgt_xy < placed_radius) & src_low
    # The MuJoCo grasp constraint is soft: a lifted corner hangs up to ~4 cm below/behind the
    # picker. A corner still on the table is held only with the picker on it, within ``close_radius`` (the
    # approach comes from straight above, so the vertex grasped then is the corner itself); a lifted corner
    # within ``hold_radius`` of the picker is taken to be held.
    lifted = src[..., 2] > tgt[..., 2] + 0.008
    holding = (d_src < close_radius) | (lifted & (d_src < hold_radius))
    releasing = (t >= release_step)[..., None]
    done = src_on_tgt | (src_placed & ~holding) | releasing
    carry = holding & ~done
    approach = ~holding & ~done

    # --- carry along the fitted semicircle -------------------------------------------------
    rel = pickers - tgt
    d = np.maximum(np.linalg.norm(rel[..., :2], axis=-1), 1e-6)
    z = np.maximum(rel[..., 2], 0.0)
    length = np.clip((d**2 + z**2) / d, 0.05, 1.0)  # flap length of the circle through both points
    u = rel[..., :2] / d[..., None]
    phi = np.arctan2(z, d - 0.5 * length)  # 0 = flat and unfolded, pi = laid on the target
    step_phi = np.full(phi.shape, dphi)
    if spec.num_pickers > 1:
        # Pickers fold together: the slower one sets the common angle, and a picker that holds
        # its corner waits (in place) while another one is still approaching its own.
        both = carry.all(axis=-1, keepdims=True)
        phi = np.where(both, phi.min(axis=-1, keepdims=True), phi)
        waiting = approach.any(axis=-1, keepdims=True)
        step_phi = np.where(waiting, 0.0, step_phi)
    phi_next = np.minimum(phi + step_phi, np.pi)
    radius = 0.5 * length
    arc = np.concatenate([
        tgt[..., :2] + (radius * (1.0 + np.cos(phi_next)))[..., None] * u,
        (tgt[..., 2] + radius * np.sin(phi_next) + layer_height)[..., None],
    ], axis=-1)
    close = (d < 0.03)[..., None]
    carry_target = np.where(close, tgt_top, arc)
    if grasp_lift > 0:  # the corner still on the table: straight up first (DEFAULT_GRASP_LIFT)
        carry_target = np.where((carry & ~lifted)[..., None], pickers + np.array([0.0, 0.0, grasp_lift]), carry_target)

    # --- approach / done targets -----------------------------------------------------------
    # approach from straight above so that the first vertex within reach is the corner itself
    horizontal = np.linalg.norm((pickers - src)[..., :2], axis=-1)
    if approach_slope > 0:  # down a cone onto the corner
        height = np.minimum(approach_slope * horizontal, APPROACH_HEIGHT)[..., None]
        approach_target = src + height * np.array([0.0, 0.0, 1.0])
    else:
        above = src + np.array([0.0, 0.0, APPROACH_HEIGHT])
        approach_target = np.where((horizontal < ALIGN_RADIUS)[..., None], src, above)
    lift = pickers.copy()
    lift[..., 2] = np.maximum(pickers[..., 2], 0.0) + step_size
    target = np.where(carry[..., None], carry_target, np.where(approach[..., None], approach_target, lift))
    move = np.clip((target - pickers) / step_size, -1.0, 1.0)
    pick = np.where(carry, 1.0, -1.0)
    action = np.concatenate([move, pick[..., None]], axis=-1)
    return action.reshape(*batch, spec.action_dim).astype(np.float32)


def fold_points(task: str, state):
    """``(pickers, source corners, target corners)`` of reduced states ``[*B, state_dim]`` (numpy or
    torch), each ``[*B, num_pickers, 3]``: picker ``p`` carries its source corner onto its target
    (``FOLD_PLAN``)."""
    batch = state.shape[:-1]
    corners = state[..., :12].reshape(*batch, 4, 3)
    pickers = state[..., 12:].reshape(*batch, task_spec(task).num_pickers, 3)
    plan = FOLD_PLAN[task]
    return pickers, corners[..., [s for s, _ in plan], :], corners[..., [g for _, g in plan], :]


def add_movement_noise(action: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    """Add Gaussian noise of std ``noise`` to the picker movements ``[dx, dy, dz]`` of ``action``
    ``[..., num_pickers * 4]`` in place (then clip them to [-1, 1]) and return it; the grasp
    commands stay as they are."""
    moves = action.reshape(*action.shape[:-1], -1, 4)[..., :3]  # a view into ``action``
    moves += noise * rng.standard_normal(moves.shape)
    np.clip(moves, -1.0, 1.0, out=moves)
    return action


class ExpertPolicy(TensorDictModuleBase):
    """Scripted expert as a TensorDict module: reads ``"state"``, ``"step_count"``; writes ``"action"``.

    Stateless and batched (any leading batch shape), so it runs inside ``SerialEnv``/``ParallelEnv``
    rollouts and TorchRL collectors. ``noise`` is the std of Gaussian noise added to the picker
    movements ``[dx, dy, dz]`` (then clipped to [-1, 1]), drawn from a generator seeded with
    ``seed``. The grasp command stays exactly +-1: the env thresholds it at 0, so noise on it
    changes no behaviour, but it turned a binary target into a spread of values near +-1 whose
    tanh-Gaussian fit had a pre-tanh std of ~3 (a sampled action then released the cloth).

    ``aim_error`` (metres, default 0: off) misleads the expert: each source corner it reads is moved
    horizontally by a Gaussian offset of that std per axis, drawn when an episode starts (a step with
    ``step_count`` 0; every call without ``"step_count"``) and held for the episode. The expert then
    aims at the wrong spot, closes there, takes another vertex or nothing, and carries on as if it held
    its corner: the failed grasps of a student whose state estimate is biased, in images labelled with
    the true state (``train_encoder.py --extra-aim-error``). The env, the state and the labels are
    untouched; only what the expert aims at moves.
    """

    def __init__(self, task: str, noise: float = 0.0, seed: int | None = None, aim_error: float = 0.0,
                 **expert_kwargs):
        super().__init__()
        self.task = check_task(task)
        if not noise >= 0:  # also NaN
            raise ValueError(f"noise must be >= 0, got {noise}")
        if not aim_error >= 0:  # also NaN
            raise ValueError(f"aim_error must be >= 0 (metres), got {aim_error}")
        # the expert's own options checked now, not at the first step of a rollout: one action on a flat state
        expert_action(self.task, np.zeros(task_spec(self.task).state_dim), 0, **expert_kwargs)
        self.noise = float(noise)
        self.aim_error = float(aim_error)
        self.expert_kwargs = expert_kwargs
        self.in_keys = ["state", "step_count"]
        self.out_keys = ["action"]
        self._rng = np.random.default_rng(seed)
        self._aim = None  # [*batch, num_pickers, 2]: this episode's misplacement of each source corner

    def _misplaced(self, state: np.ndarray, step) -> np.ndarray:
        """``state`` with each source corner moved by its episode's offset (drawn anew where an episode starts)."""
        plan = FOLD_PLAN[self.task]
        batch = state.shape[:-1]
        step = np.asarray(step)
        if step.ndim == len(batch) + 1:  # the env's step_count is [*batch, 1]
            step = step[..., 0]
        start = np.broadcast_to(step == 0, batch)
        shape = (*batch, len(plan), 2)
        if self._aim is None or self._aim.shape != shape:
            self._aim = self._rng.normal(0.0, self.aim_error, shape)
        elif start.any():
            self._aim[start] = self._rng.normal(0.0, self.aim_error, shape)[start]
        state = state.copy()
        for p, (source, _) in enumerate(plan):
            state[..., 3 * source:3 * source + 2] += self._aim[..., p, :]
        return state

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        state = tensordict.get("state")
        step = tensordict.get("step_count", None)
        step_np = 0 if step is None else step.detach().cpu().numpy()
        state_np = state.detach().cpu().numpy()
        if self.aim_error > 0:
            state_np = self._misplaced(state_np, step_np)
        action = expert_action(self.task, state_np, step_np, **self.expert_kwargs)
        if self.noise > 0:
            add_movement_noise(action, self.noise, self._rng)
        tensordict.set("action", torch.as_tensor(action, dtype=torch.float32, device=state.device))
        return tensordict
