"""Where a cloth policy first closes its grippers (trakdis.evaluation.grasps)."""
import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from trakdis.evaluation import FAR_CLOSE_CM, grasp_report, summarize_grasps

TASK = "ClothFoldDiagonalUnpinned"  # one picker carrying corner c00 onto cNN


def _episode(picker_start, close_at, lift_cm=0.0, steps=6):
    """A toy [steps] episode: the picker moves from ``picker_start`` (m, relative to c00) straight onto
    c00 over the episode, closes from step ``close_at`` on (None: never), and c00 rises ``lift_cm``
    at the last step."""
    corners = np.array([[0.0, 0.0, 0.0], [0.0, 0.3, 0.0], [0.3, 0.0, 0.0], [0.3, 0.3, 0.0]])
    states, actions = [], []
    for t in range(steps):
        c = corners.copy()
        if t == steps - 1:
            c[0, 2] = lift_cm / 100.0
        picker = np.asarray(picker_start) * (1 - t / (steps - 1))
        states.append(np.concatenate([c.ravel(), c[0] + picker]))
        actions.append([0.0, 0.0, -1.0, 1.0 if close_at is not None and t >= close_at else -1.0])
    return TensorDict({"state": torch.tensor(np.array(states), dtype=torch.float32),
                       "action": torch.tensor(actions, dtype=torch.float32)}, batch_size=[steps])


def test_first_close_distance_and_lift():
    # 10 cm straight above the corner, closing at step 2 of 6 (6 cm away): a miss, the corner stays down
    miss = grasp_report(TASK, _episode([0.0, 0.0, 0.10], close_at=2))
    assert miss["picker0_first_close_cm"] == pytest.approx(6.0, abs=1e-4) and miss["picker0_corner_lifted"] is False
    # closing on the corner (step 5: distance 0) and the corner lifted 10 cm
    hit = grasp_report(TASK, _episode([0.0, 0.0, 0.10], close_at=5, lift_cm=10.0))
    assert hit["picker0_first_close_cm"] == pytest.approx(0.0, abs=1e-4) and hit["picker0_corner_lifted"] is True
    never = grasp_report(TASK, _episode([0.0, 0.0, 0.10], close_at=None, lift_cm=1.0))
    assert math.isnan(never["picker0_first_close_cm"]) and never["picker0_corner_lifted"] is False
    line = summarize_grasps(TASK, [miss, hit, never])
    assert line == (f"grasps: 1 of 2 first closes farther than {FAR_CLOSE_CM:g} cm from their corner; "
                    "a source corner never lifted in 2 of 3 episodes")


def test_two_pickers_and_bad_input():
    ep = TensorDict({"state": torch.zeros(4, 18), "action": torch.ones(4, 8)}, batch_size=[4])
    report = grasp_report("ClothFold", ep)
    assert set(report) == {"picker0_first_close_cm", "picker0_corner_lifted", "picker1_first_close_cm",
                           "picker1_corner_lifted"}
    assert grasp_report("ClothFold", TensorDict({"action": torch.ones(4, 8)}, batch_size=[4])) is None
    with pytest.raises(ValueError, match=r"state \[T, 18\]"):
        grasp_report("ClothFold", TensorDict({"state": torch.zeros(4, 15), "action": torch.ones(4, 8)}, batch_size=[4]))
