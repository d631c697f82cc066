"""Out-of-view masking of the reduced state: points (the pickers) whose centre projects outside the
camera's image are replaced by a fixed sentinel xyz.

An image-only encoder cannot know where a picker is once it has left the 32x32 frame (the expert
and the teacher lift the pickers out of it in about a third of the picker-steps); with the mask the
teacher is trained and acts on what the image can tell, and the encoder learns to output the
sentinel for a picker it cannot see (``online_dt.py`` / ``train_encoder.py --mask-unseen-pickers``).

* :class:`OutOfViewFill`: the mask, a TorchRL ``Transform`` (in a ``TransformedEnv``, a replay buffer,
  a ``Compose`` or on a stored TensorDict) and a map of tensors (:meth:`OutOfViewFill.mask`).
* :func:`fixed_camera_matrix`: the 3x4 world -> pixel projection of the tasks' fixed camera,
  computed without MuJoCo or OpenGL.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded, TensorSpec
from torchrl.envs.transforms import ObservationTransform
from torchrl.envs.transforms.transforms import _apply_to_composite

from trakdis.envs.model import CAMERA_POS, CAMERA_XYAXES, camera_fovy
from trakdis.envs.rendering import camera_projection
from trakdis.envs.specs import task_spec

__all__ = ["DEFAULT_FILL", "OutOfViewFill", "fixed_camera_matrix"]

DEFAULT_FILL = (0.0, 0.0, 0.4)
"""Sentinel xyz (metres) of an out-of-view picker: a point no picker of the data sits at for long."""


def fixed_camera_matrix(task: str, image_size: int) -> np.ndarray:
    """3 x 4 projection from world coordinates to pixel coordinates (u right, v down, pixel centres at
    integer + 0.5) of ``task``'s ``"main"`` camera in an ``image_size`` image: the same matrix as
    ``ClothEnv(from_pixels=True).camera_matrix()`` (every task has this camera, with its own field of
    view), from the constants of :mod:`trakdis.envs.model` alone (no simulator, no OpenGL context)."""
    x_axis = np.asarray(CAMERA_XYAXES[:3], dtype=np.float64)
    y_axis = np.asarray(CAMERA_XYAXES[3:], dtype=np.float64)
    # MuJoCo's xyaxes: x normalised, y made orthogonal to x and normalised, z = x cross y
    x_axis = x_axis / np.linalg.norm(x_axis)
    y_axis = y_axis - x_axis * (x_axis @ y_axis)
    y_axis = y_axis / np.linalg.norm(y_axis)
    rot = np.stack([x_axis, y_axis, np.cross(x_axis, y_axis)], axis=1)  # columns: camera axes in the world
    return camera_projection(CAMERA_POS, rot, camera_fovy(task), image_size)


class OutOfViewFill(ObservationTransform):
    """Replace the xyz points starting at ``starts`` (state dims ``s, s+1, s+2``) whose centre is out
    of the camera's view by ``fill`` (TorchRL ``Transform``). In view: in front of the camera, with its
    projection ``(u, v) = camera_matrix @ (x, y, z, 1)`` (divided by depth) in ``[0, image_size)``.

    :meth:`mask` works on any leading batch shape ``[..., D]`` and returns a new tensor (the input is
    unchanged); applying it twice gives the same result as once when ``fill`` itself is out of view
    (the default is: it projects above the frame). As a transform it masks ``in_keys`` (default
    ``["state"]``) into ``out_keys`` (default: the same keys; values replaced, not modified in place),
    on env steps and resets, replay-buffer samples and stored TensorDicts. A bounded spec of a
    masked entry is widened to hold ``fill``. Two masks compare by identity, as modules do (module
    sets rely on it): compare their :meth:`to_dict` entries instead."""

    def __init__(self, camera_matrix, image_size: int, starts: Sequence[int], fill=DEFAULT_FILL,
                 in_keys: Sequence[NestedKey] | None = None, out_keys: Sequence[NestedKey] | None = None):
        in_keys = ["state"] if in_keys is None else list(in_keys)
        super().__init__(in_keys=in_keys, out_keys=list(in_keys) if out_keys is None else list(out_keys))
        self.camera_matrix = torch.as_tensor(np.asarray(camera_matrix), dtype=torch.float32).clone()
        if self.camera_matrix.shape != (3, 4):
            raise ValueError(f"OutOfViewFill: camera_matrix must be 3 x 4, got {tuple(self.camera_matrix.shape)}")
        self.image_size = int(image_size)
        if self.image_size < 1:
            raise ValueError(f"OutOfViewFill: image_size must be >= 1, got {image_size!r}")
        self.starts = tuple(int(s) for s in starts)
        if any(s < 0 for s in self.starts):
            raise ValueError(f"OutOfViewFill: starts must be >= 0, got {list(self.starts)}")
        self.fill = torch.as_tensor(fill, dtype=torch.float32).clone()
        if self.fill.shape != (3,):
            raise ValueError(f"OutOfViewFill: fill must be one xyz point, got shape {tuple(self.fill.shape)}")
        self._index = torch.tensor([[s, s + 1, s + 2] for s in self.starts], dtype=torch.long).reshape(-1, 3)

    @classmethod
    def for_task(cls, task: str, image_size: int = 32, fill=DEFAULT_FILL,
                 in_keys: Sequence[NestedKey] | None = None) -> "OutOfViewFill":
        """The mask of ``task``'s pickers (its state group ``pickers``: one for the diagonal folds, two
        for ClothFold) in its fixed camera's ``image_size`` image (:func:`fixed_camera_matrix`)."""
        pickers = task_spec(task).state_groups["pickers"]
        return cls(fixed_camera_matrix(task, image_size), image_size, range(pickers.start, pickers.stop, 3), fill, in_keys)

    def _points(self, x: torch.Tensor) -> torch.Tensor:
        if self.starts and x.shape[-1] < max(self.starts) + 3:
            raise ValueError(f"OutOfViewFill: points at dims {list(self.starts)} (xyz each) need >= "
                             f"{max(self.starts) + 3} dims, got shape {tuple(x.shape)}")
        return x[..., self._index.to(x.device)]  # [..., n_points, 3]

    def visible(self, x: torch.Tensor) -> torch.Tensor:
        """``[..., n_points]`` bool: whether each point of ``x`` ``[..., D]`` is in view."""
        p = self._points(x).to(torch.float32)
        h = torch.cat([p, torch.ones_like(p[..., :1])], -1) @ self.camera_matrix.to(x.device).T
        depth = h[..., 2]
        u, v = h[..., 0] / depth, h[..., 1] / depth
        n = self.image_size
        return (depth > 0) & (u >= 0) & (u < n) & (v >= 0) & (v < n)

    def mask(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` ``[..., D]`` with the out-of-view points' xyz replaced by ``fill`` (a new tensor)."""
        if not self.starts:
            return x.clone()
        out = x.clone()
        index = self._index.to(x.device)
        points = torch.where(self.visible(x)[..., None], x[..., index], self.fill.to(device=x.device, dtype=x.dtype))
        out[..., index.flatten()] = points.flatten(-2)
        return out

    # ------------------------------------------------------------------ the transform
    def _apply_transform(self, x: torch.Tensor) -> torch.Tensor:
        return self.mask(x)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    @_apply_to_composite
    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        if not isinstance(observation_spec, Bounded) or not self.starts:
            return observation_spec
        low, high = observation_spec.space.low.clone(), observation_spec.space.high.clone()
        index = self._index.flatten().to(low.device)
        fill = self.fill.repeat(len(self.starts)).to(device=low.device, dtype=low.dtype)
        low[..., index] = torch.minimum(low[..., index], fill)
        high[..., index] = torch.maximum(high[..., index], fill)
        return Bounded(low=low, high=high, shape=observation_spec.shape, dtype=observation_spec.dtype,
                       device=observation_spec.device)

    # ------------------------------------------------------------------ files
    def to_dict(self) -> dict:
        """Plain tensors, numbers and lists (the ``"fill"`` entry of policy files, the
        ``"out_of_view_fill"`` of encoder files); ``"out_keys"`` only where they differ from the keys."""
        state = {"camera_matrix": self.camera_matrix.clone(), "image_size": self.image_size,
                 "starts": list(self.starts), "fill": self.fill.clone(), "keys": list(self.in_keys)}
        if list(self.out_keys) != list(self.in_keys):
            state["out_keys"] = list(self.out_keys)
        return state

    @classmethod
    def from_dict(cls, state: Mapping[str, Any]) -> "OutOfViewFill":
        return cls(state["camera_matrix"], state["image_size"], state["starts"], state["fill"],
                   state.get("keys", ("state",)), state.get("out_keys"))

    def __repr__(self) -> str:
        return (f"OutOfViewFill(image_size={self.image_size}, starts={list(self.starts)}, "
                f"fill={self.fill.tolist()}, in_keys={list(self.in_keys)}, out_keys={list(self.out_keys)})")
