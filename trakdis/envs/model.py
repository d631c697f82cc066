"""MJCF construction for the cloth tasks (MuJoCo flex cloth, mocap pickers, fixed camera)."""

from __future__ import annotations

import dataclasses
import math

from trakdis.envs.specs import ClothConfig, check_task

# Camera: in the plane x = 0, image x axis = world +x, looking down at 45 degrees at the cloth
# centre. A horizontal image flip is then exactly the reflection x -> -x (see specs.TaskSpec).
CAMERA_POS = (0.0, -0.48, 0.48)
CAMERA_XYAXES = (1.0, 0.0, 0.0, 0.0, 1.0, 1.0)  # MJCF xyaxes: the camera's x and y axes in the world frame
# Vertical field of view (degrees) per task. The unpinned diagonal fold's source corner can start
# 2-3 pixels from the 32x32 frame's left edge, where an image-only student lost its picker: its
# camera sees wider. The pinned fold's students do not fail there, and ClothFold's distilled
# student lost with the wider view (measured: docs/recipes/distill.md).
CAMERA_FOVY = {"ClothFold": 45.0, "ClothFoldDiagonalPinned": 45.0, "ClothFoldDiagonalUnpinned": 55.0}

TABLE_RGBA = "0.55 0.47 0.38 1"
CLOTH_RGBA = "0.25 0.45 0.85 1"
PICKER_RGBA = "0.95 0.95 0.95 1"
# Radius of the sphere that draws a picker (rendering only: the geom has no contacts and the picker
# is a mocap body, so physics and state are unchanged). SoftGym draws its pickers at 0.05 m beside
# a cloth of similar size; at 12 mm a picker covered about one pixel of a 32x32 frame and an
# image-only encoder could not tell where it was (docs/recipes/distill.md). 35 mm is about
# 4 pixels across at the cloth's distance.
PICKER_MARKER_RADIUS = 0.035
# Each task's rendering version, bumped whenever what its camera shows changes (2: the 35 mm picker
# markers; 3: the unpinned fold's wider view). Datasets with pixels and encoder files record it:
# images of an older rendering do not match what a policy sees today.
RENDER_VERSIONS = {"ClothFold": 2, "ClothFoldDiagonalPinned": 2, "ClothFoldDiagonalUnpinned": 3}
BLOCK_RGBA = "0.35 0.35 0.35 1"


def camera_fovy(task: str) -> float:
    """The vertical field of view (degrees) of ``task``'s fixed camera."""
    check_task(task)
    return CAMERA_FOVY[task]


def render_version(task: str) -> int:
    """The version of what ``task``'s camera shows (recorded in image datasets and encoder files)."""
    check_task(task)
    return RENDER_VERSIONS[task]


@dataclasses.dataclass(frozen=True)
class PhysicsOptions:
    """Simulation settings shared by all tasks (see docs/tasks.md for the speed/quality trade-off).

    Attributes:
        resolution: vertices per cloth side (N x N grid).
        timestep: MuJoCo timestep (s). Explicit Euler is required by flex shell elasticity in
            MuJoCo >= 3.3 (the implicit integrators reject it).
        substeps: physics steps per picker sub-step (SoftGym's action repeat is over sub-steps).
        iterations: constraint solver iterations (upper bound; ``tolerance`` may stop earlier).
        solver: MuJoCo constraint solver (``CG``, ``Newton`` or ``PGS``).
        tolerance: solver tolerance.
        vertex_radius: collision radius of a cloth vertex (m); self-collision uses it too.
        selfcollide: flex self-collision mode (kept on: without it a fold sinks through itself).
        thickness: shell thickness used by the bending model (m).
    """

    resolution: int = 12
    timestep: float = 0.01
    substeps: int = 1
    iterations: int = 20
    solver: str = "CG"
    tolerance: float = 1e-6
    vertex_radius: float = 0.004
    selfcollide: str = "auto"
    thickness: float = 1e-3

    def __post_init__(self):
        if not (isinstance(self.resolution, int) and not isinstance(self.resolution, bool) and 4 <= self.resolution <= 30):
            raise ValueError(f"resolution must be an int in [4, 30] (finer grids fail in MuJoCo, docs/tasks.md), got {self.resolution!r}")
        if not 0 < self.timestep <= 0.02:
            raise ValueError(f"timestep must be in (0, 0.02] s, got {self.timestep!r}")
        if not (isinstance(self.substeps, int) and not isinstance(self.substeps, bool) and self.substeps >= 1):
            raise ValueError(f"substeps must be a positive int, got {self.substeps!r}")
        if self.solver not in ("CG", "Newton", "PGS"):
            raise ValueError(f"solver must be CG, Newton or PGS, got {self.solver!r}")
        if self.selfcollide not in ("none", "narrow", "bvh", "sap", "auto"):
            raise ValueError(f"selfcollide must be a MuJoCo flex selfcollide mode, got {self.selfcollide!r}")


def pinned_gridrange(resolution: int) -> tuple[int, int, int, int]:
    """Grid range ``(ix0, iy0, ix1, iy1)`` (inclusive) held down in the pinned diagonal task.

    The 2 x 2 vertices at corner cN0 (ix = N-1, iy = 0) lie on the fold line of the c00 -> cNN
    diagonal fold, so the pin holds the cloth in place without blocking the fold.
    """
    n = resolution
    return (n - 2, 0, n - 1, 1)


def build_mjcf(
    task: str,
    config: ClothConfig,
    physics: PhysicsOptions,
    picker_pos: list[tuple[float, float, float]],
    render_size: int = 64,
) -> str:
    """MJCF string of one episode's scene (cloth geometry and material from ``config``)."""
    check_task(task)
    n = physics.resolution
    sx = config.size_x / (n - 1)
    sy = config.size_y / (n - 1)
    r = physics.vertex_radius
    deg = math.degrees(config.rotation)
    f = config.friction
    tc = max(config.stretch_timeconst, 2 * physics.timestep)
    pin = ""
    block = ""
    if task != "ClothFold":
        # A heavy-looking block: on the pinned corner (ClothFoldDiagonalPinned), or off the cloth
        # (ClothFoldDiagonalUnpinned), so the two tasks look alike apart from the pin.
        half = 0.5 * config.size_x
        c, s = math.cos(config.rotation), math.sin(config.rotation)
        if task == "ClothFoldDiagonalPinned":
            ix0, iy0, ix1, iy1 = pinned_gridrange(n)
            pin = f'<pin gridrange="{ix0} {iy0} {ix1} {iy1}"/>'
            lx, ly, bz = half - 0.5 * sx, -half + 0.5 * sy, 2 * r + 0.012
        else:
            lx, ly, bz = half + 0.07, -half - 0.07, 0.012
        bx = config.offset_x + c * lx - s * ly
        by = config.offset_y + s * lx + c * ly
        block = (
            f'<geom name="block" type="box" size="0.025 0.025 0.012" pos="{bx:.6f} {by:.6f} {bz:.6f}" '
            f'euler="0 0 {deg:.6f}" rgba="{BLOCK_RGBA}" contype="0" conaffinity="0"/>'
        )
    pickers = "\n".join(
        f'<body name="picker{i}" mocap="true" pos="{p[0]:.6f} {p[1]:.6f} {p[2]:.6f}">'
        f'<geom type="sphere" size="{PICKER_MARKER_RADIUS}" rgba="{PICKER_RGBA}" contype="0" conaffinity="0"/></body>'
        for i, p in enumerate(picker_pos)
    )
    grasps = "\n".join(
        f'<connect name="grasp{i}" body1="picker{i}" body2="cloth_0" anchor="0 0 0" active="false" '
        f'solref="{2 * physics.timestep:.6f} 1"/>'
        for i in range(len(picker_pos))
    )
    off = max(render_size, 64)
    cam = CAMERA_POS
    xyaxes = " ".join(f"{a:g}" for a in CAMERA_XYAXES)
    return f"""
<mujoco model="trakdis_{task}">
  <option timestep="{physics.timestep}" integrator="Euler" solver="{physics.solver}" iterations="{physics.iterations}"
          tolerance="{physics.tolerance}"/>
  <size memory="32M"/>
  <visual>
    <quality shadowsize="0" offsamples="0"/>
    <global offwidth="{off}" offheight="{off}"/>
    <headlight ambient="0.35 0.35 0.35" diffuse="0.55 0.55 0.55" specular="0 0 0"/>
  </visual>
  <worldbody>
    <light pos="0 -0.2 1.2" dir="0 0.15 -1" castshadow="false" diffuse="0.35 0.35 0.35"/>
    <geom name="table" type="plane" size="0.8 0.8 0.01" rgba="{TABLE_RGBA}" friction="{f:.6f} 0.005 0.0001"/>
    <camera name="main" pos="{cam[0]} {cam[1]} {cam[2]}" xyaxes="{xyaxes}" fovy="{camera_fovy(task)}"/>
    <flexcomp name="cloth" type="grid" count="{n} {n} 1" spacing="{sx:.6f} {sy:.6f} {sx:.6f}"
              pos="{config.offset_x:.6f} {config.offset_y:.6f} {r}" euler="0 0 {deg:.6f}" radius="{r}"
              dim="2" mass="{config.mass:.6f}" rgba="{CLOTH_RGBA}">
      <contact condim="3" solref="0.01 1" solimp="0.95 0.99 0.0001" selfcollide="{physics.selfcollide}"
               friction="{f:.6f} 0.005 0.0001"/>
      <edge equality="true" solref="{tc:.6f} 1" damping="{config.damping:.6g}"/>
      <elasticity young="{config.young:.6g}" poisson="0" thickness="{physics.thickness}" elastic2d="bend"/>
      {pin}
    </flexcomp>
    {block}
    {pickers}
  </worldbody>
  <equality>
    {grasps}
  </equality>
</mujoco>
"""
