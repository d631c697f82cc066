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
    assert miss["picker0_first_close_step"] == 2 and math.isnan(miss["picker0_last_release_step"])
    assert miss["picker0_first_close_height_cm"] == pytest.approx(6.0, abs=1e-4)  # straight above: all height
    # 6 cm to the side and level with the corner: as far, but no height
    side = grasp_report(TASK, _episode([0.10, 0.0, 0.0], close_at=2))
    assert side["picker0_first_close_cm"] == pytest.approx(6.0, abs=1e-4)
    assert side["picker0_first_close_height_cm"] == pytest.approx(0.0, abs=1e-4)
    # c00 ends where it started, its target cNN 30 cm away in x and y
    assert miss["picker0_placement_cm"] == pytest.approx(30.0 * math.sqrt(2.0), abs=1e-3)
    # closing on the corner (step 5: distance 0) and the corner lifted 10 cm
    hit = grasp_report(TASK, _episode([0.0, 0.0, 0.10], close_at=5, lift_cm=10.0))
    assert hit["picker0_first_close_cm"] == pytest.approx(0.0, abs=1e-4) and hit["picker0_corner_lifted"] is True
    never = grasp_report(TASK, _episode([0.0, 0.0, 0.10], close_at=None, lift_cm=1.0))
    assert math.isnan(never["picker0_first_close_cm"]) and never["picker0_corner_lifted"] is False
    assert math.isnan(never["picker0_first_close_step"]) and math.isnan(never["picker0_first_close_height_cm"])
    line = summarize_grasps(TASK, [miss, hit, never])
    assert line == (f"grasps: 1 of 2 first closes farther than {FAR_CLOSE_CM:g} cm from their corner; "
                    "a source corner never lifted in 2 of 3 episodes; median first close at step 3.5, 3.0 cm above its corner, "
                    "source corners end 42.4 cm from their targets (median)")


def test_release_step_and_placement():
    # closed at steps 1-2, opened at 3, closed again at 4, opened at 5: the last release is step 5
    ep = _episode([0.0, 0.0, 0.10], close_at=1)
    ep["action"][[3, 5], 3] = -1.0
    # the source corner carried onto its target (cNN) by the last step, 1 cm short in x
    ep["state"][-1, 0:2] = torch.tensor([0.29, 0.30])
    report = grasp_report(TASK, ep)
    assert report["picker0_first_close_step"] == 1 and report["picker0_last_release_step"] == 5
    assert report["picker0_placement_cm"] == pytest.approx(1.0, abs=1e-4)


def test_two_pickers_and_bad_input():
    ep = TensorDict({"state": torch.zeros(4, 18), "action": torch.ones(4, 8)}, batch_size=[4])
    report = grasp_report("ClothFold", ep)
    assert set(report) == {f"picker{p}_{k}" for p in (0, 1) for k in (
        "first_close_cm", "first_close_height_cm", "first_close_step", "corner_lifted", "last_release_step",
        "placement_cm")}
    assert grasp_report("ClothFold", TensorDict({"action": torch.ones(4, 8)}, batch_size=[4])) is None
    with pytest.raises(ValueError, match=r"state \[T, 18\]"):
        grasp_report("ClothFold", TensorDict({"state": torch.zeros(4, 15), "action": torch.ones(4, 8)}, batch_size=[4]))


def test_the_estimate_at_the_first_close():
    # the policy read the picker 5 cm off in x: at its first close (6 cm above the corner) it believed
    # sqrt(6^2 + 5^2) cm, and its error in the picker-to-corner vector is the 5 cm shift
    ep = _episode([0.0, 0.0, 0.10], close_at=2)
    estimate = ep["state"].clone()
    estimate[:, 12] += 0.05
    ep["state_estimate"] = estimate
    report = grasp_report(TASK, ep)
    assert report["picker0_first_close_cm"] == pytest.approx(6.0, abs=1e-4)
    assert report["picker0_close_estimate_cm"] == pytest.approx(math.hypot(6.0, 5.0), abs=1e-4)
    assert report["picker0_close_offset_error_cm"] == pytest.approx(5.0, abs=1e-4)
    assert report["picker0_close_picker_error_cm"] == pytest.approx(5.0, abs=1e-4)
    assert report["picker0_close_picker_height_error_cm"] == pytest.approx(0.0, abs=1e-4)
    assert report["picker0_close_corner_error_cm"] == pytest.approx(0.0, abs=1e-4)
    assert report["picker0_close_corner_rest_error_cm"] == pytest.approx(0.0, abs=1e-4)
    # an estimate that put the picker on the corner: a far close the encoder caused
    onto = ep["state"].clone()
    onto[:, 12:15] = onto[:, 0:3]
    ep["state_estimate"] = onto
    fooled = grasp_report(TASK, ep)
    assert fooled["picker0_close_estimate_cm"] == pytest.approx(0.0, abs=1e-4)
    assert fooled["picker0_close_offset_error_cm"] == pytest.approx(6.0, abs=1e-4)
    # the picker believed 6 cm lower than it is (on the corner, which rests)
    assert fooled["picker0_close_picker_height_error_cm"] == pytest.approx(-6.0, abs=1e-4)
    assert fooled["picker0_close_corner_error_cm"] == pytest.approx(0.0, abs=1e-4)
    never = _episode([0.0, 0.0, 0.10], close_at=None)
    never["state_estimate"] = never["state"].clone()
    assert math.isnan(grasp_report(TASK, never)["picker0_close_estimate_cm"])
    line = summarize_grasps(TASK, [report, fooled, grasp_report(TASK, never)])
    assert line.startswith(f"grasps: 2 of 2 first closes farther than {FAR_CLOSE_CM:g} cm from their corner "
                           "(1 of them within it in the estimate);")
    bad = _episode([0.0, 0.0, 0.10], close_at=2)
    bad["state_estimate"] = torch.zeros(6, 12)
    with pytest.raises(ValueError, match="state_estimate has shape"):
        grasp_report(TASK, bad)


def test_the_corner_estimate_averaged_over_its_rest():
    # the source corner read 2 cm off in +y at steps 0-1 and 2 cm off in -y at step 2 (the close):
    # the estimate at the close is 2 cm off, the mean of the three views 2/3 cm
    ep = _episode([0.0, 0.0, 0.10], close_at=2)
    estimate = ep["state"].clone()
    estimate[:2, 1] += 0.02
    estimate[2, 1] -= 0.02
    ep["state_estimate"] = estimate
    report = grasp_report(TASK, ep)
    assert report["picker0_close_corner_error_cm"] == pytest.approx(2.0, abs=1e-4)
    assert report["picker0_close_corner_rest_error_cm"] == pytest.approx(2.0 / 3.0, abs=1e-4)
    assert report["picker0_close_offset_error_cm"] == pytest.approx(2.0, abs=1e-4)
    assert report["picker0_close_picker_error_cm"] == pytest.approx(0.0, abs=1e-4)
