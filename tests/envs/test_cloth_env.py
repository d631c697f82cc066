"""Gymnasium-level behaviour of the cloth environments."""

import gymnasium as gym
import numpy as np
import pytest

import trakdis.envs  # noqa: F401  (registers the gym ids)
from trakdis.envs import ENV_CLASSES, TASKS, ClothEnv, expert_action, task_spec

SHORT = dict(horizon=5)


def _rollout(env, seed, steps, action_fn):
    obs, info = env.reset(seed=seed)
    out = [obs["state"].copy()]
    perfs = []
    for t in range(steps):
        obs, reward, term, trunc, info = env.step(action_fn(obs, t))
        out.append(obs["state"].copy())
        perfs.append(reward)
    return np.array(out), np.array(perfs), info


@pytest.mark.parametrize("task", TASKS)
def test_gym_make_spaces_and_first_step(task):
    env = gym.make(f"trakdis/{task}-v0", include_vertices=True, **SHORT)
    spec = task_spec(task)
    obs, info = env.reset(seed=0)
    assert obs["state"].shape == (spec.state_dim,) and obs["state"].dtype == np.float32
    assert obs["vertices"].shape == (12 * 12, 3)
    assert env.observation_space.contains(obs)
    assert info["normalized_performance"] == pytest.approx(0.0, abs=1e-6)
    assert info["performance"] < 0 and info["sim_unstable"] == False  # noqa: E712
    # corners in the reduced state are the grid corners of the vertex array
    n = 12
    np.testing.assert_allclose(obs["state"][:12].reshape(4, 3),
                               obs["vertices"][[0, n - 1, (n - 1) * n, n * n - 1]])
    obs, reward, term, trunc, info = env.step(env.action_space.sample())
    assert np.isfinite(reward) and reward <= 0 and not term
    env.close()


def test_horizon_truncates_and_step_after_end_raises():
    env = ClothEnv(task="ClothFoldDiagonalUnpinned", horizon=3)
    env.reset(seed=1)
    flags = [env.step(np.zeros(4, np.float32))[3] for _ in range(3)]
    assert flags == [False, False, True]
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(4, np.float32))


def test_bad_actions_raise_clear_errors():
    env = ClothEnv(task="ClothFold", **SHORT)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(8,\)"):
        env.step(np.zeros(4, np.float32))
    with pytest.raises(TypeError, match="floating"):
        env.step(np.zeros(8, np.int64))
    with pytest.raises(ValueError, match="non-finite"):
        env.step(np.array([np.nan] + [0.0] * 7, np.float32))
    with pytest.raises(ValueError, match="Unknown task"):
        ClothEnv(task="ClothFlip")
    with pytest.raises(ValueError, match="split"):
        ClothEnv(task="ClothFold", split="test")


def test_out_of_range_actions_are_clipped():
    kw = dict(task="ClothFoldDiagonalUnpinned", **SHORT)
    big = np.array([50.0, -7.0, 3.0, -2.0], np.float32)
    clipped = np.clip(big, -1, 1)
    a, _, _ = _rollout(ClothEnv(**kw), 3, 3, lambda o, t: big)
    b, _, _ = _rollout(ClothEnv(**kw), 3, 3, lambda o, t: clipped)
    np.testing.assert_array_equal(a, b)
    # the picker moved by 3 steps x 8 sub-steps x 0.0075 m along +x (within the workspace)
    assert a[-1, 12] - a[0, 12] == pytest.approx(3 * 8 * 0.0075, abs=1e-6)


def test_pickers_stay_in_workspace():
    env = ClothEnv(task="ClothFold", horizon=12)
    states, _, _ = _rollout(env, 0, 12, lambda o, t: np.array([1, 1, 1, -1, -1, -1, -1, -1], np.float32))
    pickers = states[:, 12:].reshape(-1, 2, 3)
    assert pickers.max() <= 0.4 + 1e-6 and pickers[..., 2].min() >= 0.0
    assert pickers[-1, 0, 2] == pytest.approx(0.3) and pickers[-1, 1, 2] == pytest.approx(0.0)


@pytest.mark.parametrize("task", TASKS)
def test_same_seed_same_episode_bit_for_bit(task):
    def policy(obs, t):
        return expert_action(task, obs["state"], t)

    a, pa, ia = _rollout(ClothEnv(task=task, horizon=30), 123, 30, policy)
    b, pb, ib = _rollout(ClothEnv(task=task, horizon=30), 123, 30, policy)
    c, _, ic = _rollout(ClothEnv(task=task, horizon=30), 124, 1, policy)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(pa, pb)
    assert ia["config_index"] == ib["config_index"]
    assert not np.array_equal(a[0], c[0])


def test_grasp_moves_the_corner_and_release_drops_it():
    task = "ClothFoldDiagonalUnpinned"
    env = ClothEnv(task=task, horizon=40)
    obs, _ = env.reset(seed=5)
    for t in range(20):  # expert approaches corner c00 and grasps it
        obs, *_ = env.step(expert_action(task, obs["state"], t))
        if env._grasped[0] >= 0:
            break
    assert env._grasped[0] == 0  # the grasped vertex is the corner c00 (grid index 0)
    for _ in range(3):
        obs, *_ = env.step(np.array([0, 0, 1, 1], np.float32))
    lifted = obs["state"][2]
    assert lifted > 0.08  # lifted corner (3 steps x 6 cm up, hanging a little below the picker)
    for _ in range(8):
        obs, *_ = env.step(np.array([0, 0, 0, -1], np.float32))
    assert obs["state"][2] < 0.04 and obs["state"][14] > 0.15  # released: fell, picker stayed up


def test_pixels_shape_dtype_and_content():
    env = ClothEnv(task="ClothFold", from_pixels=True, image_size=48, **SHORT)
    obs, _ = env.reset(seed=0)
    img = obs["pixels"]
    assert img.shape == (48, 48, 3) and img.dtype == np.uint8
    blue = (img[..., 2].astype(int) - img[..., 0]) > 60  # cloth pixels
    assert 0.05 < blue.mean() < 0.6
    obs2, *_ = env.step(np.zeros(8, np.float32))
    assert obs2["pixels"].shape == (48, 48, 3)
    env.close()


@pytest.mark.parametrize("speed", [1e6, 1e12])
def test_unstable_physics_truncates_without_nan(speed):
    env = ClothEnv(task="ClothFold", from_pixels=True, **SHORT)
    obs0, info0 = env.reset(seed=0)
    env.inject_velocity(speed)
    obs, reward, term, trunc, info = env.step(np.zeros(8, np.float32))
    assert trunc and not term and info["sim_unstable"]
    assert np.isfinite(obs["state"]).all() and np.isfinite(reward)
    assert np.isfinite(info["normalized_performance"])
    np.testing.assert_array_equal(obs["state"], obs0["state"])
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(8, np.float32))
    obs, info = env.reset(seed=1)  # a reset recovers
    assert not info["sim_unstable"] and np.isfinite(obs["state"]).all()


def test_env_classes_fix_their_task():
    for task, cls in ENV_CLASSES.items():
        assert cls(**SHORT).task == task


def test_bad_construction_and_reset_options_are_refused():
    # each used to pass: NaN left the env with sim_unstable=False, 3.7 was truncated to 3, and
    # resolutions 31-40 (documented as valid) failed at reset with MuJoCo XML or memory errors
    from trakdis.envs.cloth_env import MAX_RESOLUTION

    for kwargs, message in [
        (dict(move_per_substep=float("nan")), "move_per_substep must be a finite number > 0"),
        (dict(move_per_substep=-0.01), "move_per_substep"),
        (dict(grasp_radius=float("inf")), "grasp_radius"),
        (dict(config_index=3.7), r"config_index must be an int in \[0, 1000\), got 3.7"),
        (dict(config_index=True), "config_index"),
        (dict(config_index=1000), "config_index"),
        (dict(resolution=MAX_RESOLUTION + 1), r"resolution must be an int in \[4, 30\], got 31"),
        (dict(resolution=40), "resolution"),
        (dict(resolution=3), "resolution"),
        (dict(resolution=12.0), "resolution"),
    ]:
        with pytest.raises(ValueError, match=message):
            ClothEnv(task="ClothFold", **kwargs, **SHORT)
    env = ClothEnv(task="ClothFold", config_index=np.int64(3), **SHORT)
    assert env.reset(seed=0)[1]["config_index"] == 3
    with pytest.raises(ValueError, match=r"reset option config_index must be an int .* got 3.7"):
        env.reset(seed=0, options={"config_index": 3.7})
    with pytest.raises(ValueError, match="picker_pos must be finite"):
        env.reset(seed=0, options={"picker_pos": [(0.0, float("nan"), 0.1), (0.1, 0.0, 0.1)]})


def test_finest_allowed_resolution_resets_and_steps():
    from trakdis.envs.cloth_env import MAX_RESOLUTION

    # the smallest cloth of the train pool (0.24 m): the case that fails above the limit
    env = ClothEnv(task="ClothFold", resolution=MAX_RESOLUTION, config_index=893, horizon=2)
    obs, _ = env.reset(seed=0)
    obs, *_, info = env.step(np.zeros(8, np.float32))
    assert np.isfinite(obs["state"]).all() and not info["sim_unstable"]
