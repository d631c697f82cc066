"""Where a policy closes its grippers: the diagnosis of a cloth policy's most common failure.

A picker that closes farther from its source corner than the env's grasp reach takes an inner
vertex or nothing; its corner then stays on the table, and a learned policy that does not open
again fails the episode (docs/recipes/online_dt.md, "Where the pipeline's teacher fails").
:func:`grasp_report` reads one played episode (its true ``"state"`` and its ``"action"``, as
:func:`~trakdis.evaluation.run_episodes` passes them to ``on_episode``) and tells, per picker,
how far from its corner it first closed and whether the corner was ever lifted; for a policy that
read an estimate of the state (``"state_estimate"``, a student), also how far it believed it was at
that step and how wrong that belief was: the encoder's error at the decision that matters.
"""
from __future__ import annotations

import math
import statistics
from typing import Sequence

from tensordict import TensorDictBase

from trakdis.envs.experts import fold_points
from trakdis.envs.specs import task_spec

# A first close farther than this from the source corner is a miss: the env's grasp reach
# (``ClothEnv.grasp_radius``, 4 cm) plus half a centimetre for the corner's own motion.
FAR_CLOSE_CM = 4.5
# A source corner counts as lifted once it rose this far above its target corner (a folded flap
# rises 10-20 cm; a corner dragged along the table stays within ~1 cm).
LIFTED_CM = 3.0
# The report's entries at the first close of a policy that read an estimate (grasp_report's docstring).
_ESTIMATE_FIELDS = ("close_estimate_cm", "close_offset_error_cm", "close_picker_error_cm",
                    "close_picker_height_error_cm", "close_corner_error_cm", "close_corner_rest_error_cm")


def grasp_report(task: str, episode: TensorDictBase) -> dict[str, float | bool] | None:
    """Per picker ``p``: ``picker{p}_first_close_cm`` (distance in cm between the picker and its
    source corner at the first step whose grasp command is > 0, the env's threshold; NaN if it never
    closed), ``picker{p}_first_close_height_cm`` (the picker's height in cm above its source corner at
    that step: a close 3 cm or more above the corner rarely lifts it, docs/recipes/online_dt.md),
    ``picker{p}_first_close_step`` (that step's index), ``picker{p}_corner_lifted`` (whether
    its source corner ever rose ``LIFTED_CM`` above its target corner), ``picker{p}_last_release_step``
    (the last step whose command opened a closed picker; NaN if it never opened after a close) and
    ``picker{p}_placement_cm`` (the horizontal distance in cm between its source corner and its target
    corner at the episode's last step: where the fold put the corner). ``episode``: ``[T]`` steps with
    ``"state"`` (the true reduced state) and ``"action"``. None if the episode carries no ``"state"``.

    With ``"state_estimate"`` (``[T, state_dim]``, what the policy read) also, at that first close,
    ``picker{p}_close_estimate_cm`` (the picker-to-corner distance the estimate showed) and
    ``picker{p}_close_offset_error_cm`` (the length of the estimate's error in the picker-to-corner
    vector, the quantity the grasp depends on: a far close with a small estimated distance is the
    encoder's fault, one with a large estimated distance the policy's), split into its two parts,
    ``picker{p}_close_picker_error_cm`` and ``picker{p}_close_corner_error_cm`` (the lengths of the errors
    in the picker's and in the source corner's position), with ``picker{p}_close_picker_height_error_cm``
    (the estimated minus the true picker height: below 0, the picker believed lower than it is), and
    ``picker{p}_close_corner_rest_error_cm``: the error of the mean of the source corner's estimates over
    the steps up to the close (the corner rests until a picker takes it, so this is what a filter that
    averages its views would read). NaN if it never closed."""
    if "state" not in episode.keys():
        return None
    spec = task_spec(task)
    state, action = episode.get("state"), episode.get("action")
    if state.shape[-1] != spec.state_dim or action.shape[-1] != spec.action_dim:
        raise ValueError(f"grasp_report: {task} episodes need state [T, {spec.state_dim}] and action "
                         f"[T, {spec.action_dim}], got {tuple(state.shape)} and {tuple(action.shape)}")
    pickers, corners, targets = fold_points(task, state)  # [T, P, 3] each
    estimate = episode.get("state_estimate", None)
    if estimate is not None and estimate.shape != state.shape:
        raise ValueError(f"grasp_report: {task} episode's state_estimate has shape {tuple(estimate.shape)}, "
                         f"its state {tuple(state.shape)}")
    offset = pickers - corners  # [T, P, 3]: the picker relative to its source corner
    if estimate is not None:
        pickers_hat, corners_hat, _ = fold_points(task, estimate)  # [T, P, 3] each
    closed = action.reshape(*action.shape[:-1], spec.num_pickers, 4)[..., 3] > 0  # [T, P]
    out: dict[str, float | bool] = {}
    for p in range(spec.num_pickers):
        closes = closed[:, p].nonzero()
        t = int(closes[0, 0]) if len(closes) else None
        out[f"picker{p}_first_close_cm"] = math.nan if t is None else 100.0 * float(offset[t, p].norm())
        out[f"picker{p}_first_close_height_cm"] = math.nan if t is None else 100.0 * float(offset[t, p, 2])
        out[f"picker{p}_first_close_step"] = math.nan if t is None else float(t)
        if estimate is not None:  # what the policy read at its first close (metres here, cm in the report)
            at_close = dict.fromkeys(_ESTIMATE_FIELDS, math.nan)
            if t is not None:
                offset_hat = pickers_hat[t, p] - corners_hat[t, p]
                picker_err = pickers_hat[t, p] - pickers[t, p]
                at_close = {k: 100.0 * float(v) for k, v in zip(_ESTIMATE_FIELDS, (
                    offset_hat.norm(), (offset_hat - offset[t, p]).norm(), picker_err.norm(), picker_err[2],
                    (corners_hat[t, p] - corners[t, p]).norm(),
                    (corners_hat[: t + 1, p].mean(0) - corners[t, p]).norm()))}
            out.update({f"picker{p}_{k}": v for k, v in at_close.items()})
        rise = corners[:, p, 2] - targets[:, p, 2]
        out[f"picker{p}_corner_lifted"] = bool(rise.max() * 100.0 >= LIFTED_CM)
        opens = (closed[:-1, p] & ~closed[1:, p]).nonzero()
        out[f"picker{p}_last_release_step"] = float(opens[-1, 0]) + 1.0 if len(opens) else math.nan
        out[f"picker{p}_placement_cm"] = 100.0 * float((corners[-1, p, :2] - targets[-1, p, :2]).norm())
    return out


def summarize_grasps(task: str, reports: Sequence[dict[str, float | bool]]) -> str:
    """One line over the episodes' :func:`grasp_report` s: the first closes farther than
    ``FAR_CLOSE_CM`` from their corner (and, for a policy that read an estimate, how many of those
    the estimate showed within that distance: the encoder's misses), the episodes with a source
    corner never lifted, the median first-close step and height and the median placement."""
    pickers = range(task_spec(task).num_pickers)
    closes = [(r[f"picker{p}_first_close_cm"], r.get(f"picker{p}_close_estimate_cm")) for r in reports for p in pickers]
    closed = [(d, e) for d, e in closes if not math.isnan(d)]
    far = [e for d, e in closed if d > FAR_CLOSE_CM]
    unlifted = sum(not all(r[f"picker{p}_corner_lifted"] for p in pickers) for r in reports)
    believed = ""
    if far and all(e is not None for e in far):
        believed = f" ({sum(e <= FAR_CLOSE_CM for e in far)} of them within it in the estimate)"
    steps = [r[f"picker{p}_first_close_step"] for r in reports for p in pickers]
    steps = [s for s in steps if not math.isnan(s)]
    heights = [r[f"picker{p}_first_close_height_cm"] for r in reports for p in pickers]
    heights = [h for h in heights if not math.isnan(h)]
    placed = [r[f"picker{p}_placement_cm"] for r in reports for p in pickers]
    when = (f"median first close at step {statistics.median(steps):g}, "
            f"{statistics.median(heights):.1f} cm above its corner, " if steps else "")
    return (f"grasps: {len(far)} of {len(closed)} first closes farther than {FAR_CLOSE_CM:g} cm from their "
            f"corner{believed}; a source corner never lifted in {unlifted} of {len(reports)} episodes; "
            f"{when}source corners end {statistics.median(placed):.1f} cm from their targets (median)")
