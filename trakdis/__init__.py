"""trakdis: TorchRL/TensorDict components for transformer-based knowledge distillation in visual RL.

Parts, lowest floor first (docs/design.md): ``utils`` (generic helpers), ``envs`` (MuJoCo cloth
tasks), ``transforms``, ``modules`` (Decision Transformer, encoder), ``data`` (episode layout, datasets,
replay buffer), ``objectives`` (losses), ``policies`` (policy and encoder files, a loaded policy and its
acting env), ``optim``, ``evaluation``, ``training`` (the recipes' update loop, the snapshot kept),
``teacher`` (the teacher's run: its online phase and evaluations), ``student`` (the student of a teacher
and an encoder: its weight copy, rollouts and races, its distillation), ``encoder_training`` (the
encoder's run: the epoch kept, the student rounds' images, the member kept), ``method`` (the method's
stages and their default options).
"""

import importlib.metadata as _metadata
import os as _os

# MuJoCo fixes its GL backend when it is first imported, and ``import torchrl.envs`` imports it.
# Choose offscreen EGL (works on CPU-only machines through Mesa) before anything else can, unless
# the user already chose a backend.
_os.environ.setdefault("MUJOCO_GL", "egl")
if _os.environ["MUJOCO_GL"] in ("egl", "osmesa"):
    _os.environ.setdefault("PYOPENGL_PLATFORM", _os.environ["MUJOCO_GL"])

try:  # one source of the version: pyproject.toml, through the installed package's metadata
    __version__ = _metadata.version("trakdis")
except _metadata.PackageNotFoundError:  # a source tree that was not installed
    __version__ = "0+unknown"
