"""trakdis: TorchRL/TensorDict components for transformer-based knowledge distillation in visual RL.

Subpackages, lowest floor first: ``utils`` (generic helpers), ``envs`` (MuJoCo cloth tasks),
``modules`` (Decision Transformer, encoder), ``transforms``, ``objectives`` (losses), ``data``
(episode layout, datasets, replay buffer), ``evaluation``, ``policies`` (saved policies), ``optim``,
``training`` (the recipes' update loop), ``method`` (the method's stages and their default options).
"""

import os as _os

# MuJoCo fixes its GL backend when it is first imported, and ``import torchrl.envs`` imports it.
# Choose offscreen EGL (works on CPU-only machines through Mesa) before anything else can, unless
# the user already chose a backend.
_os.environ.setdefault("MUJOCO_GL", "egl")
if _os.environ["MUJOCO_GL"] in ("egl", "osmesa"):
    _os.environ.setdefault("PYOPENGL_PLATFORM", _os.environ["MUJOCO_GL"])

__version__ = "0.1.0"
