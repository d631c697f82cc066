"""Gymnasium cloth-folding environments on MuJoCo flex cloth (SoftGym/DMfD task semantics).

Action, per picker, ``[dx, dy, dz, pick]`` in [-1, 1] (values outside are clipped):
the picker moves by ``action[:3] * move_per_substep`` metres in each of ``action_repeat``
sub-steps, clipped to the workspace box; ``pick > 0`` grasps the nearest free cloth vertex within
``grasp_radius`` of the picker (if not already holding one) and keeps holding it; ``pick <= 0``
releases. Observation: ``{"state": float32 (state_dim,)}`` (corners c00, c0N, cN0, cNN xyz, then
picker xyz), plus ``"pixels"`` (uint8 H x W x 3) with ``from_pixels=True`` and ``"vertices"``
(float32 N*N x 3) with ``include_vertices=True``. Reward = task performance (<= 0, 0 optimal);
``info`` holds ``performance``, ``normalized_performance``, ``sim_unstable``, ``config_index``.
"""

from __future__ import annotations

import numpy as np

from trakdis.envs.rendering import configure_gl

configure_gl()

import gymnasium as gym  # noqa: E402
import mujoco  # noqa: E402

from trakdis.envs.model import PhysicsOptions, build_mjcf, pinned_gridrange  # noqa: E402
from trakdis.envs.rendering import FrameRenderer  # noqa: E402
from trakdis.envs.specs import (  # noqa: E402
    CONFIG_POOL_SIZE,
    check_split,
    check_task,
    cloth_config,
    task_spec,
)

#: Cloth grid resolutions that work for every configuration of every task. Measured (MuJoCo 4.0):
#: at 31 the smallest cloths (0.24 m) overflow MuJoCo's 32 MB arena at the first step (ClothFold),
#: and from 32 on their vertex spacing falls below the vertices' collision diameter (an XML error
#: at reset); 30 ran full scripted-expert episodes on the smallest and largest cloths.
MAX_RESOLUTION = 30
MIN_RESOLUTION = 4

WORKSPACE_LOW = np.array([-0.4, -0.4, 0.0])
WORKSPACE_HIGH = np.array([0.4, 0.4, 0.3])
# Physics is declared unstable above this vertex speed (m/s); the pickers move at <= 1 m/s.
MAX_SPEED = 20.0
_BAD_WARNINGS = (mujoco.mjtWarning.mjWARN_BADQACC, mujoco.mjtWarning.mjWARN_BADQPOS,
                 mujoco.mjtWarning.mjWARN_BADQVEL)


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _check_config_index(value, name: str) -> int:
    """``value`` as an int in ``[0, CONFIG_POOL_SIZE)``; a float such as 3.7 is refused, not truncated."""
    if not _is_int(value) or not 0 <= value < CONFIG_POOL_SIZE:
        raise ValueError(f"{name} must be an int in [0, {CONFIG_POOL_SIZE}), got {value!r}")
    return int(value)


class ClothEnv(gym.Env):
    """One of the :data:`~trakdis.envs.TASKS` (pick with ``task=``; subclasses fix it).

    Args:
        task: task name.
        from_pixels: add ``"pixels"`` to the observation.
        image_size: side of the square image.
        split: ``"train"`` or ``"eval"``: which configuration pool resets draw from.
        horizon: episode length (then ``truncated=True``).
        include_vertices: add ``"vertices"`` (all cloth vertex positions) to the observation.
        resolution, timestep, substeps, iterations, solver, tolerance, selfcollide: physics (see
            :class:`~trakdis.envs.model.PhysicsOptions`).
        action_repeat: picker sub-steps per env step (SoftGym: 8).
        move_per_substep: metres moved per sub-step for an action of 1 (SoftGym: 0.01 m for
            cloths about 1.4x larger than ours, so 0.0075 m here).
        grasp_radius: pick reaches vertices within this distance of the picker centre (m).
        render_supersample: render at ``image_size * k`` and area-downsample.
        config_index: pin every reset to one configuration of the pool (debugging); default
            draws it from the reset seed.

    ``resolution`` must lie in ``[4, 30]`` (:data:`MAX_RESOLUTION`: finer grids fail in MuJoCo on
    the smallest cloths); ``move_per_substep`` and ``grasp_radius`` must be finite and > 0 and
    ``config_index`` an int in the pool: anything else is a ``ValueError`` at construction.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 12}

    def __init__(
        self,
        task: str = "ClothFold",
        from_pixels: bool = False,
        image_size: int = 32,
        split: str = "train",
        horizon: int = 100,
        include_vertices: bool = False,
        resolution: int = 12,
        timestep: float = 0.01,
        substeps: int = 1,
        iterations: int = 20,
        solver: str = "CG",
        tolerance: float = 1e-6,
        selfcollide: str = "auto",
        action_repeat: int = 8,
        move_per_substep: float = 0.0075,
        grasp_radius: float = 0.04,
        render_supersample: int = 2,
        config_index: int | None = None,
        render_mode: str | None = None,
    ):
        super().__init__()
        self.task = check_task(task)
        self.split = check_split(split)
        if not (_is_int(horizon) and horizon >= 1):  # True is an int to Python, never an episode length
            raise ValueError(f"horizon must be a positive int, got {horizon!r}")
        if not (_is_int(action_repeat) and action_repeat >= 1):
            raise ValueError(f"action_repeat must be a positive int, got {action_repeat!r}")
        if config_index is not None:
            config_index = _check_config_index(config_index, "config_index")
        if not (_is_int(resolution) and MIN_RESOLUTION <= resolution <= MAX_RESOLUTION):
            raise ValueError(
                f"resolution must be an int in [{MIN_RESOLUTION}, {MAX_RESOLUTION}], got {resolution!r} (finer grids "
                f"fail in MuJoCo on the smallest cloths: vertex spacing below the collision size, or out of memory)")
        for name, value in (("move_per_substep", move_per_substep), ("grasp_radius", grasp_radius)):
            if not (isinstance(value, (int, float, np.floating, np.integer)) and np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        self.task_spec = task_spec(task, horizon=horizon)
        self.num_pickers = self.task_spec.num_pickers
        self.horizon = horizon
        self.from_pixels = bool(from_pixels)
        self.include_vertices = bool(include_vertices)
        self.physics = PhysicsOptions(resolution=resolution, timestep=timestep, substeps=substeps,
                                      iterations=iterations, solver=solver, tolerance=tolerance,
                                      selfcollide=selfcollide)
        self.action_repeat = action_repeat
        self.move_per_substep = float(move_per_substep)
        self.grasp_radius = float(grasp_radius)
        self.fixed_config_index = config_index
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self.image_size = image_size
        self._renderer = FrameRenderer(image_size, render_supersample) if (from_pixels or render_mode) else None

        n = resolution
        self._corner_ids = np.array([0, n - 1, (n - 1) * n, n * n - 1])
        self._setup_metric(n)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (self.task_spec.action_dim,), np.float32)
        obs = {"state": gym.spaces.Box(-np.inf, np.inf, (self.task_spec.state_dim,), np.float32)}
        if self.from_pixels:
            obs["pixels"] = gym.spaces.Box(0, 255, (image_size, image_size, 3), np.uint8)
        if self.include_vertices:
            obs["vertices"] = gym.spaces.Box(-np.inf, np.inf, (n * n, 3), np.float32)
        self.observation_space = gym.spaces.Dict(obs)

        self.model = None
        self.data = None
        self.config = None
        self.config_index = None
        self._t = 0
        self._done = True

    # ------------------------------------------------------------------ metric
    def _setup_metric(self, n: int) -> None:
        grid = np.arange(n * n).reshape(n, n)  # grid[ix, iy] = vertex index
        if self.task == "ClothFold":
            # Fold the far half (iy > (N-1)/2) onto the near half; A = moved half, B = mirror rows.
            half = n // 2
            self._group_a = grid[:, n - half:][:, ::-1].reshape(-1)
            self._group_b = grid[:, :half].reshape(-1)
        else:
            # Fold corner c00 onto cNN across the diagonal through c0N and cN0: vertex (i, j)
            # lands on (N-1-j, N-1-i). Left edge (0, j) <-> top edge (N-1-j, N-1); bottom edge
            # (i, 0) <-> right edge (N-1, N-1-i).
            j = np.arange(n)
            self._edge_l = grid[0, j]
            self._edge_t = grid[n - 1 - j, n - 1]
            self._edge_b = grid[j, 0]
            self._edge_r = grid[n - 1, n - 1 - j]
        self._pinned = np.zeros(n * n, dtype=bool)
        if self.task == "ClothFoldDiagonalPinned":
            ix0, iy0, ix1, iy1 = pinned_gridrange(n)
            self._pinned[grid[ix0:ix1 + 1, iy0:iy1 + 1].reshape(-1)] = True

    def performance(self, verts: np.ndarray | None = None) -> float:
        """Task performance of vertex positions ``verts`` (default: the current cloth); <= 0."""
        x = self.vertices() if verts is None else np.asarray(verts, dtype=np.float64)
        if self.task == "ClothFold":
            fold = np.linalg.norm(x[self._group_a] - x[self._group_b], axis=1).mean()
            drag = np.linalg.norm(x[self._group_b] - self._b_init, axis=1).mean()
            return float(-fold - 1.2 * drag)
        return float(-(np.linalg.norm(x[self._edge_l] - x[self._edge_t])
                       + np.linalg.norm(x[self._edge_b] - x[self._edge_r])))

    # ------------------------------------------------------------------ simulation
    def vertices(self) -> np.ndarray:
        """Current cloth vertex positions, float64 ``(N*N, 3)``, grid index ``ix * N + iy``."""
        if self.data is None:
            raise RuntimeError("call reset() first")
        return self.data.flexvert_xpos.copy()

    def _refresh_positions(self) -> None:
        # After mj_step, flexvert_xpos is one step stale: recompute kinematics + flex vertices
        # only (no collision detection, unlike mj_forward).
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_flex(self.model, self.data)

    def _initial_pickers(self, rng: np.random.Generator) -> list[tuple[float, float, float]]:
        # Distributions symmetric under x -> -x with picker 0 <-> picker 1.
        if self.num_pickers == 2:
            return [(float(sx * 0.12 + rng.uniform(-0.02, 0.02)), float(rng.uniform(-0.12, -0.04)),
                     float(rng.uniform(0.06, 0.1))) for sx in (-1.0, 1.0)]
        return [(float(rng.uniform(-0.05, 0.05)), float(rng.uniform(-0.12, -0.04)),
                 float(rng.uniform(0.06, 0.1)))]

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode. ``options`` (debugging/tests): ``config_index`` (int) picks a pool
        entry; ``config`` (:class:`~trakdis.envs.ClothConfig`) and ``picker_pos`` (xyz per picker)
        override the draw."""
        super().reset(seed=seed)
        rng = self.np_random
        options = dict(options or {})
        unknown = set(options) - {"config_index", "config", "picker_pos"}
        if unknown:
            raise ValueError(f"unknown reset option(s) {sorted(unknown)}; expected config_index, config, picker_pos")
        if "config_index" in options:
            index = _check_config_index(options["config_index"], "reset option config_index")
        elif self.fixed_config_index is not None:
            index = self.fixed_config_index
        else:
            index = int(rng.integers(CONFIG_POOL_SIZE))
        self.config_index = index
        self.config = options.get("config") or cloth_config(self.task, self.split, index)
        pickers = self._initial_pickers(rng)
        if "picker_pos" in options:
            pickers = [tuple(float(v) for v in p) for p in options["picker_pos"]]
            if len(pickers) != self.num_pickers or any(len(p) != 3 for p in pickers):
                raise ValueError(f"picker_pos must be {self.num_pickers} xyz triple(s), got {options['picker_pos']}")
            if not np.isfinite(pickers).all():  # NaN would leave the env with sim_unstable=False
                raise ValueError(f"reset option picker_pos must be finite, got {options['picker_pos']}")
        self.picker_pos0 = pickers
        render_size = self._renderer.render_size if self._renderer is not None else 64
        xml = build_mjcf(self.task, self.config, self.physics, pickers, render_size)
        self.model = mujoco.MjModel.from_xml_string(xml)
        self.data = mujoco.MjData(self.model)
        m = self.model
        adr = m.flex_vertadr[0]
        self._vert_body = m.flex_vertbodyid[adr: adr + m.flex_vertnum[0]].copy()
        self._grasp_eq = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_EQUALITY, f"grasp{i}")
                                   for i in range(self.num_pickers)])
        self._grasped = np.full(self.num_pickers, -1)
        # settle on the table
        for _ in range(10):
            mujoco.mj_step(m, self.data)
        self._refresh_positions()
        self._b_init = self.data.flexvert_xpos[self._group_b].copy() if self.task == "ClothFold" else None
        self._perf0 = self.performance()
        if self._renderer is not None:
            self._renderer.bind(m)
        self._t = 0
        self._done = False
        self._last_obs = self._observation()
        self._last_perf = self._perf0
        return self._last_obs, self._info(self._perf0, False)

    def _observation(self) -> dict:
        x = self.data.flexvert_xpos
        state = np.concatenate([x[self._corner_ids].reshape(-1), self.data.mocap_pos.reshape(-1)])
        obs = {"state": state.astype(np.float32)}
        if self.from_pixels:
            obs["pixels"] = self._renderer.render(self.data)
        if self.include_vertices:
            obs["vertices"] = x.astype(np.float32)
        return obs

    def _info(self, perf: float, unstable: bool) -> dict:
        norm = (perf - self._perf0) / (0.0 - self._perf0)
        return {"performance": np.float32(perf), "normalized_performance": np.float32(norm),
                "sim_unstable": np.bool_(unstable), "config_index": self.config_index}

    def _check_action(self, action) -> np.ndarray:
        a = np.asarray(action)
        if a.dtype.kind != "f":
            raise TypeError(f"{self.task}: action must be a floating-point array of shape "
                            f"({self.task_spec.action_dim},) (float32), got dtype {a.dtype}")
        if a.shape != (self.task_spec.action_dim,):
            raise ValueError(f"{self.task}: action must have shape ({self.task_spec.action_dim},) = "
                             f"{self.num_pickers} picker(s) x [dx, dy, dz, pick], got {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"{self.task}: action contains non-finite values: {a}")
        # out-of-range actions are clipped to [-1, 1] (documented behaviour)
        return np.clip(a.astype(np.float64), -1.0, 1.0).reshape(self.num_pickers, 4)

    def _update_grasps(self, picks: np.ndarray) -> None:
        # Grasp = a MuJoCo ``connect`` equality between the picker (mocap body) and the vertex,
        # retargeted at run time (no recompile). A kinematic grasp (setting the vertex's joints to
        # the picker every step, like SoftGym's zero inverse mass) was tried and rejected: MuJoCo's
        # soft edge constraints cannot follow a teleported vertex, its edges stretched up to 7x.
        m, d = self.model, self.data
        x = d.flexvert_xpos
        for i in range(self.num_pickers):
            eq = self._grasp_eq[i]
            if picks[i] > 0:
                if self._grasped[i] >= 0:
                    continue
                dist = np.linalg.norm(x - d.mocap_pos[i], axis=1)
                dist[self._pinned] = np.inf
                dist[self._grasped[self._grasped >= 0]] = np.inf
                v = int(np.argmin(dist))
                if dist[v] <= self.grasp_radius:
                    m.eq_obj2id[eq] = self._vert_body[v]
                    m.eq_data[eq, :6] = 0.0  # anchor at the picker centre and at the vertex
                    d.eq_active[eq] = 1
                    self._grasped[i] = v
            elif self._grasped[i] >= 0:
                d.eq_active[eq] = 0
                self._grasped[i] = -1

    def _unstable(self, warn_before: list[int]) -> bool:
        d = self.data
        if any(d.warning[w].number > n for w, n in zip(_BAD_WARNINGS, warn_before)):
            return True
        if not (np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
            return True
        return bool(np.abs(d.qvel).max(initial=0.0) > MAX_SPEED)

    def step(self, action):
        if self._done:
            raise RuntimeError(f"{self.task}: step() called on a finished episode; call reset() first")
        a = self._check_action(action)
        m, d = self.model, self.data
        self._update_grasps(a[:, 3])
        delta = a[:, :3] * self.move_per_substep
        warn_before = [d.warning[w].number for w in _BAD_WARNINGS]
        for _ in range(self.action_repeat):
            d.mocap_pos[:] = np.clip(d.mocap_pos + delta, WORKSPACE_LOW, WORKSPACE_HIGH)
            for _ in range(self.physics.substeps):
                mujoco.mj_step(m, d)
        # Checked once per env step: MuJoCo's warning counters and non-finite values persist, so
        # nothing that happened in an earlier sub-step is missed.
        unstable = self._unstable(warn_before)
        self._t += 1
        if unstable:
            # No NaN leaves the env: repeat the last finite observation and performance.
            self._done = True
            return self._last_obs, float(self._last_perf), False, True, self._info(self._last_perf, True)
        self._refresh_positions()
        perf = self.performance()
        obs = self._observation()
        self._last_obs, self._last_perf = obs, perf
        truncated = self._t >= self.horizon
        self._done = truncated
        return obs, float(perf), False, truncated, self._info(perf, False)

    # ------------------------------------------------------------------ extras
    def render(self):
        if self._renderer is None:
            raise RuntimeError("create the env with render_mode='rgb_array' or from_pixels=True to render")
        return self._renderer.render(self.data)

    def camera_matrix(self) -> np.ndarray:
        """3 x 4 world-to-pixel projection of the ``pixels`` image (needs a renderer)."""
        if self._renderer is None:
            raise RuntimeError("camera_matrix() needs from_pixels=True or render_mode='rgb_array'")
        return self._renderer.camera_matrix(self.data)

    def inject_velocity(self, speed: float) -> None:
        """Test hook: set every cloth degree of freedom's velocity to ``speed`` (m/s)."""
        if self.data is None:
            raise RuntimeError("call reset() first")
        self.data.qvel[:] = speed

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
        super().close()


class ClothFoldEnv(ClothEnv):
    """Two pickers fold the far half of a rectangular cloth onto the near half (SoftGym ClothFold)."""

    def __init__(self, **kwargs):
        super().__init__(task="ClothFold", **kwargs)


class ClothFoldDiagonalPinnedEnv(ClothEnv):
    """One picker folds corner c00 onto cNN; the corner region cN0 is pinned to the table (DMfD)."""

    def __init__(self, **kwargs):
        super().__init__(task="ClothFoldDiagonalPinned", **kwargs)


class ClothFoldDiagonalUnpinnedEnv(ClothEnv):
    """One picker folds corner c00 onto cNN of a free square cloth (DMfD)."""

    def __init__(self, **kwargs):
        super().__init__(task="ClothFoldDiagonalUnpinned", **kwargs)


ENV_CLASSES = {
    "ClothFold": ClothFoldEnv,
    "ClothFoldDiagonalPinned": ClothFoldDiagonalPinnedEnv,
    "ClothFoldDiagonalUnpinned": ClothFoldDiagonalUnpinnedEnv,
}
