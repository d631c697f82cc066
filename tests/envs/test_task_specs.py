import numpy as np
import pytest

from trakdis.envs import TASKS, cloth_config, task_spec
from trakdis.envs.specs import CONFIG_POOL_SIZE, RANDOMIZATION


def test_task_names_and_shapes():
    assert TASKS == ("ClothFold", "ClothFoldDiagonalPinned", "ClothFoldDiagonalUnpinned")
    expected = {"ClothFold": (2, 18, 8), "ClothFoldDiagonalPinned": (1, 15, 4),
                "ClothFoldDiagonalUnpinned": (1, 15, 4)}
    for task, (pickers, sdim, adim) in expected.items():
        spec = task_spec(task)
        assert (spec.num_pickers, spec.state_dim, spec.action_dim, spec.horizon) == (pickers, sdim, adim, 100)
        assert spec.gym_id == f"trakdis/{task}-v0"
        assert spec.grasp_dims == ((3, 7) if pickers == 2 else (3,))


def test_unknown_task_error_names_choices():
    with pytest.raises(ValueError, match="ClothFoldDiagonalPinned"):
        task_spec("ClothFlip")


@pytest.mark.parametrize("task", TASKS)
def test_state_mirror_is_an_involution(task):
    perm, sign = task_spec(task).state_mirror
    perm, sign = np.array(perm), np.array(sign)
    state = np.random.default_rng(0).normal(size=(5, task_spec(task).state_dim))
    mirrored = state[:, perm] * sign
    assert sorted(perm.tolist()) == list(range(state.shape[1]))
    np.testing.assert_allclose(mirrored[:, perm] * sign, state)
    # only x coordinates change sign
    assert (sign[0::3] == -1).all() and (sign[1::3] == 1).all() and (sign[2::3] == 1).all()
    # corners c00 <-> cN0, c0N <-> cNN
    assert perm[:12].tolist() == [6, 7, 8, 9, 10, 11, 0, 1, 2, 3, 4, 5]


@pytest.mark.parametrize("task", TASKS)
def test_config_pools_are_deterministic_disjoint_and_in_range(task):
    train = [cloth_config(task, "train", i).as_array() for i in range(200)]
    evals = [cloth_config(task, "eval", i).as_array() for i in range(200)]
    np.testing.assert_array_equal(train[7], cloth_config(task, "train", 7).as_array())
    assert not {tuple(a) for a in train} & {tuple(a) for a in evals}
    cfgs = [cloth_config(task, s, i) for s in ("train", "eval") for i in range(200)]
    lo, hi = RANDOMIZATION["size"]
    assert all(lo <= c.size_x <= hi and lo <= c.size_y <= hi for c in cfgs)
    if task != "ClothFold":
        assert all(c.size_x == c.size_y for c in cfgs)
    lo, hi = RANDOMIZATION["rotation_deg"]
    assert all(np.radians(lo) <= c.rotation <= np.radians(hi) for c in cfgs)
    for key in ("mass", "young", "damping", "friction"):
        lo, hi = RANDOMIZATION[key]
        vals = np.array([getattr(c, key) for c in cfgs])
        assert (vals >= lo).all() and (vals <= hi).all() and vals.std() > 0


def test_config_errors():
    with pytest.raises(ValueError, match="split"):
        cloth_config("ClothFold", "test", 0)
    with pytest.raises(ValueError, match="config index"):
        cloth_config("ClothFold", "train", CONFIG_POOL_SIZE)


def test_state_error_groups_in_centimetres():
    import torch

    spec = task_spec("ClothFold")
    err = torch.zeros(5, spec.state_dim)
    err[:, :12] = 0.01
    err[:, 12:] = 0.03
    out = spec.state_error_cm(err)
    assert out["corners_cm"] == pytest.approx(1.0) and out["pickers_cm"] == pytest.approx(3.0)
    assert out["mae"] == pytest.approx((12 * 0.01 + 6 * 0.03) / 18)
    assert task_spec("ClothFoldDiagonalPinned").state_groups["pickers"] == slice(12, 15)
    with pytest.raises(ValueError, match="18 dims"):
        spec.state_error_cm(torch.zeros(3, 15))
