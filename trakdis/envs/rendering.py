"""Offscreen rendering: GL backend selection and a small renderer with clear failure messages.

MuJoCo picks its OpenGL backend when ``mujoco`` is first imported, from ``MUJOCO_GL``. On a
machine without a display, EGL (Mesa llvmpipe on a CPU) is the backend that works, so
:func:`configure_gl` sets ``MUJOCO_GL=egl`` (and ``PYOPENGL_PLATFORM`` to match) when nothing is
set. It must run before ``import mujoco``; ``trakdis.envs`` calls it on import.
"""

from __future__ import annotations

import os
import sys

import numpy as np

GL_HELP = (
    "MuJoCo could not create an offscreen OpenGL context (MUJOCO_GL={gl!r}). To fix it: on a "
    "headless Linux machine install Mesa EGL (e.g. `apt-get install libegl1 libgl1-mesa-dri`) and "
    "set MUJOCO_GL=egl before Python imports mujoco; with a display use MUJOCO_GL=glfw; "
    "MUJOCO_GL=osmesa needs libosmesa6. State-only environments (from_pixels=False) do not need "
    "OpenGL. Original error: {err}"
)


def configure_gl() -> str:
    """Default ``MUJOCO_GL`` to ``egl`` (and ``PYOPENGL_PLATFORM`` to the same); return it."""
    gl = os.environ.setdefault("MUJOCO_GL", "egl")
    if gl in ("egl", "osmesa"):
        os.environ.setdefault("PYOPENGL_PLATFORM", gl)
    return gl


def adopt_configured_backend() -> None:
    """Make an already imported ``mujoco`` render with the backend ``MUJOCO_GL`` names now.

    ``mujoco`` reads ``MUJOCO_GL`` once, at import; ``import torchrl.envs`` (or any library that
    imports mujoco) before ``import trakdis`` therefore leaves it on its default, GLFW, which needs a
    display. ``mujoco.Renderer`` looks its context class up in
    ``mujoco.rendering.classic.gl_context`` each time it is built, so when mujoco saw *no*
    ``MUJOCO_GL`` at import and ``MUJOCO_GL`` is now ``egl`` or ``osmesa``, that class is swapped for
    the offscreen one. A backend the user chose explicitly before importing mujoco is never touched.
    """
    if "mujoco" not in sys.modules:
        return  # mujoco will read MUJOCO_GL itself when imported
    try:
        from mujoco.rendering.classic import gl_context
    except ImportError:  # another mujoco layout: keep its own choice (bind() explains failures)
        return
    wanted = os.environ.get("MUJOCO_GL", "").lower().strip()
    if getattr(gl_context, "_MUJOCO_GL", None) != "" or wanted not in ("egl", "osmesa"):
        return
    if wanted == "egl":  # each backend's module needs its own system library: only the chosen one is imported
        from mujoco.egl import GLContext
    else:
        from mujoco.osmesa import GLContext
    gl_context.GLContext = GLContext
    gl_context._MUJOCO_GL = wanted
    sys.modules["mujoco"].GLContext = GLContext


def mujoco_gl_backend() -> str | None:
    """The GL backend the imported ``mujoco`` actually uses (``egl``, ``glfw``, ``osmesa``), or None."""
    mujoco = sys.modules.get("mujoco")
    ctx = getattr(mujoco, "GLContext", None)
    return ctx.__module__.rsplit(".", 1)[-1] if ctx is not None else None


def camera_projection(pos, rot, fovy_deg: float, image_size: int) -> np.ndarray:
    """3 x 4 projection from world coordinates to pixel coordinates (u right, v down, pixel centres
    at integer + 0.5) of a MuJoCo camera at ``pos`` whose axes (x, y, z) are the columns of ``rot``,
    with vertical field of view ``fovy_deg`` degrees, in an ``image_size`` square image."""
    f = 0.5 * image_size / np.tan(0.5 * np.deg2rad(fovy_deg))
    k = np.array([[f, 0, 0.5 * image_size], [0, f, 0.5 * image_size], [0, 0, 1.0]])
    # camera frame: x right, y up, looking along -z; image v grows downwards
    r_wc = np.diag([1.0, -1.0, -1.0]) @ np.asarray(rot, dtype=np.float64).T
    t = -r_wc @ np.asarray(pos, dtype=np.float64)
    return k @ np.hstack([r_wc, t[:, None]])


class FrameRenderer:
    """Renders the ``main`` camera to ``uint8 [size, size, 3]``.

    Renders at ``size * supersample`` pixels and downsamples with area averaging (anti-aliasing
    for small images, like SoftGym's render-large-then-resize). A new MuJoCo model (every reset
    re-compiles the scene with new cloth geometry) needs a new GL context, see :meth:`bind`.
    """

    def __init__(self, size: int, supersample: int = 2):
        if not (isinstance(size, int) and 8 <= size <= 512):
            raise ValueError(f"image_size must be an int in [8, 512], got {size!r}")
        if not (isinstance(supersample, int) and 1 <= supersample <= 4):
            raise ValueError(f"render_supersample must be an int in [1, 4], got {supersample!r}")
        self.size = size
        self.supersample = supersample
        self._renderer = None
        self._model = None

    @property
    def render_size(self) -> int:
        return self.size * self.supersample

    def bind(self, model) -> None:
        """Create (or re-create) the GL context for ``model``."""
        import mujoco  # here, not at the top: mujoco fixes its GL backend at import, after configure_gl()

        self.close()
        try:
            adopt_configured_backend()
            self._renderer = mujoco.Renderer(model, self.render_size, self.render_size)
        except Exception as err:  # noqa: BLE001 - re-raised with instructions
            msg = GL_HELP.format(gl=os.environ.get("MUJOCO_GL"), err=err)
            loaded = mujoco_gl_backend()
            wanted = os.environ.get("MUJOCO_GL", "")
            if loaded and wanted and loaded != wanted:
                # mujoco fixes its backend at import: it was imported before MUJOCO_GL was set
                msg = (f"`mujoco` was imported before MUJOCO_GL={wanted} was set and uses the {loaded!r} "
                       f"backend: export MUJOCO_GL={wanted} in the shell, or import trakdis before "
                       "mujoco. " + msg)
            raise RuntimeError(msg) from err
        self._model = model

    def render(self, data) -> np.ndarray:
        if self._renderer is None:
            raise RuntimeError("FrameRenderer.render() called before bind(model)")
        self._renderer.update_scene(data, camera="main")
        img = self._renderer.render()
        if self.supersample > 1:
            s = self.supersample
            img = img.reshape(self.size, s, self.size, s, 3).mean(axis=(1, 3))
            img = np.rint(img).astype(np.uint8)
        return np.ascontiguousarray(img)

    def camera_matrix(self, data) -> np.ndarray:
        """3 x 4 projection from world coordinates to pixel coordinates of the output image.

        Pixel coordinates: u to the right, v downwards, pixel centres at integer + 0.5.
        """
        import mujoco  # here, not at the top: mujoco fixes its GL backend at import, after configure_gl()

        model = self._model
        cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "main")
        rot = data.cam_xmat[cam_id].reshape(3, 3)  # columns: camera x, y, z axes in world frame
        return camera_projection(data.cam_xpos[cam_id], rot, model.cam_fovy[cam_id], self.size)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
        self._renderer = None
        self._model = None

    def __del__(self):
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass
