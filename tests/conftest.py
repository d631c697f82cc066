import os

# MuJoCo picks its GL backend at import time: offscreen EGL works on a CPU-only machine (Mesa llvmpipe).
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
