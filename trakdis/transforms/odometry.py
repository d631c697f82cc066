"""Picker odometry: the encoder's picker estimates fused with the pickers' own motion commands.

A picker is a mocap body: each env step moves it by exactly ``clip(action[:3], -1, 1) *
move_per_substep`` in each of ``action_repeat`` sub-steps, clipped to the workspace box
(:class:`~trakdis.envs.ClothEnv`). A policy knows the commands it sent (a Decision Transformer
even reads them back as its action tokens), so the only unknown about a picker's position is
where it started. :class:`PickerOdometry` predicts each picker's position from its previous
estimate and the action, then moves the prediction toward the encoder's new estimate with gain
``1 / (n + 1)`` after ``n`` fused views: the Kalman filter of a constant offset observed with equal
noise (no process noise: the motion model is exact, and clipping to the box only shrinks an
offset). The estimate at every step is the running mean of the encoder's views, each carried
forward by the known motion, instead of one view's error; views in which the predicted picker is
outside the camera's image are not fused (the encoder cannot see it there). Nothing but the image
and the policy's own commands is read: no proprioception.

* In an env (``TransformedEnv``, after :class:`~trakdis.transforms.EncoderTransform`): the fused
  estimate replaces the picker dims of ``in_keys`` (``"state_estimate"``); the number of fused views
  per picker rides along as an observation (``count_key``), so batched envs, partial resets and
  collectors need no state kept in the transform.
* On stored episodes (:meth:`PickerOdometry.filter`): the same fusion along the time dim of
  ``[..., T, D]`` estimates with the executed ``[..., T, A]`` actions (the student's distillation
  data, so that it trains on what it will read when acting).

The held corner (``hold_radius`` > 0, with ``corner_starts``): a picker that closes (grasp command > 0)
within ``hold_radius`` of its source corner, as the previous estimate shows them, takes a cloth vertex
there (the env grasps the nearest vertex within its reach and pulls it to the picker's centre), so
while it stays closed the corner's estimate is the picker's. The encoder is the weak witness here: a
corner lifted a few centimetres looks from above almost as it did on the table, and a student that
reads it still down opens again (docs/recipes/distill.md, "Why the pinned fold's student holds the
corner it closed on").
The rule needs no state of its own: a held corner's estimate is its picker's, so the next close is
within reach again until the picker opens.

Why not a TorchRL transform that exists (checked in 0.14): none integrates actions into an
observation; ``TargetReturn`` (the model for keeping the running value in the observation spec)
accumulates rewards only.
"""
from __future__ import annotations

import inspect
import math
from typing import Mapping, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from trakdis.envs import ClothEnv, task_spec
from trakdis.envs.cloth_env import WORKSPACE_HIGH, WORKSPACE_LOW
from trakdis.envs.experts import FOLD_PLAN
from trakdis.transforms.visibility import OutOfViewFill, fixed_camera_matrix

__all__ = ["PickerOdometry"]


class PickerOdometry(Transform):
    """Fuses an encoder's picker estimates with the pickers' motion commands (TorchRL ``Transform``).

    Args:
        starts: the state dims where each picker's xyz starts (``[12, 15]`` on ClothFold).

    Keyword Args:
        in_keys: the one estimate to filter in place (default ``["state_estimate"]``; one key, since one
            ``count_key`` goes with it).
        action_key: the action entry (``[*B, num_pickers * action_stride]``).
        action_stride: action dims per picker; its first three are the xyz move (default 4).
        move_per_substep, action_repeat: the env's picker motion (:class:`~trakdis.envs.ClothEnv`).
        low, high: the workspace box the env clips the pickers to (xyz, metres).
        camera_matrix, image_size: the camera whose image the encoder reads; a view is fused only
            when the predicted picker projects into it (``None``: every view is fused).
        count_key: the observation entry holding the number of views fused per picker.
        corner_starts: the state dims where each picker's source corner's xyz starts (the held corner;
            ``None``: no corner is held).
        hold_radius: a close within this distance (metres) of the source corner, as estimated, holds it:
            its estimate is then the picker's while the picker stays closed (0: off).
    """

    def __init__(self, starts: Sequence[int], *, in_keys: Sequence[NestedKey] | None = None,
                 action_key: NestedKey = "action", action_stride: int = 4, move_per_substep: float = 0.0075,
                 action_repeat: int = 8, low: Sequence[float] = (-0.4, -0.4, 0.0),
                 high: Sequence[float] = (0.4, 0.4, 0.3), camera_matrix=None, image_size: int = 32,
                 count_key: NestedKey = "picker_odometry_count", corner_starts: Sequence[int] | None = None,
                 hold_radius: float = 0.0):
        in_keys = ["state_estimate"] if in_keys is None else list(in_keys)
        if len(in_keys) != 1:
            raise ValueError(f"PickerOdometry: one estimate key (one count_key goes with it), got in_keys {in_keys}")
        super().__init__(in_keys=in_keys, out_keys=list(in_keys))
        self.starts = [int(s) for s in starts]
        if not self.starts or min(self.starts) < 0:
            raise ValueError(f"PickerOdometry: starts must be >= 0 state dims, one per picker, got {list(starts)}")
        if not (action_stride >= 3 and action_repeat >= 1 and move_per_substep > 0):
            raise ValueError(f"PickerOdometry: need action_stride >= 3, action_repeat >= 1 and move_per_substep > 0, "
                             f"got {action_stride}, {action_repeat}, {move_per_substep}")
        self.action_key, self.count_key = action_key, count_key
        self.action_stride, self.action_repeat = int(action_stride), int(action_repeat)
        self.move_per_substep = float(move_per_substep)
        self.low = torch.as_tensor(low, dtype=torch.float32)
        self.high = torch.as_tensor(high, dtype=torch.float32)
        if self.low.shape != (3,) or self.high.shape != (3,) or not (self.low < self.high).all():
            raise ValueError(f"PickerOdometry: low {list(low)} and high {list(high)} must be xyz with low < high")
        self.view = None if camera_matrix is None else OutOfViewFill(
            camera_matrix, image_size, starts=[3 * i for i in range(len(self.starts))])
        self._index = torch.tensor([[s, s + 1, s + 2] for s in self.starts])
        if not (hold_radius >= 0 and math.isfinite(hold_radius)):
            raise ValueError(f"PickerOdometry: hold_radius must be a finite distance >= 0, got {hold_radius}")
        self.hold_radius = float(hold_radius)
        if self.hold_radius > 0 and (self.action_stride < 4 or corner_starts is None
                                     or len(corner_starts) != len(self.starts) or min(corner_starts) < 0):
            raise ValueError(f"PickerOdometry: hold_radius {hold_radius} needs a grasp command (action_stride >= 4, "
                             f"got {self.action_stride}) and corner_starts, one >= 0 state dim per picker "
                             f"({len(self.starts)}), got {corner_starts}")
        self.corner_starts = None if corner_starts is None else [int(c) for c in corner_starts]
        self._corner_index = None if corner_starts is None else torch.tensor([[c, c + 1, c + 2]
                                                                              for c in self.corner_starts])

    @classmethod
    def for_task(cls, task: str, env_kwargs: Mapping | None = None, *, image_size: int = 32,
                 in_keys: Sequence[NestedKey] | None = None, hold_radius: float = 0.0) -> "PickerOdometry":
        """The filter of ``task``'s pickers, with the motion of an env made with ``env_kwargs``
        (``move_per_substep``, ``action_repeat``; the env's defaults otherwise) and the task's fixed
        camera at ``image_size``; ``hold_radius``: each picker holds its source corner of the task's
        fold plan (``trakdis.envs.experts.FOLD_PLAN``) as the class docstring says."""
        spec, kwargs = task_spec(task), dict(env_kwargs or {})
        defaults = inspect.signature(ClothEnv.__init__).parameters
        motion = {k: kwargs.get(k, defaults[k].default) for k in ("move_per_substep", "action_repeat")}
        pickers = spec.state_groups["pickers"]
        return cls(list(range(pickers.start, pickers.stop, 3)), in_keys=in_keys, action_stride=spec.action_dim // spec.num_pickers,
                   low=WORKSPACE_LOW.tolist(), high=WORKSPACE_HIGH.tolist(),
                   camera_matrix=fixed_camera_matrix(task, image_size), image_size=image_size,
                   corner_starts=[3 * source for source, _ in FOLD_PLAN[task]], hold_radius=hold_radius, **motion)

    # ------------------------------------------------------------------ the filter
    def _pickers(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] < max(self.starts) + 3:
            raise ValueError(f"PickerOdometry: pickers at dims {self.starts} need >= {max(self.starts) + 3} state "
                             f"dims, got shape {tuple(x.shape)}")
        return x[..., self._index.to(x.device)]  # [..., P, 3]

    def _moves(self, action: torch.Tensor) -> torch.Tensor:
        num = len(self.starts) * self.action_stride
        if action.shape[-1] != num:
            raise ValueError(f"PickerOdometry: {self.action_key!r} must have {len(self.starts)} picker(s) x "
                             f"{self.action_stride} dims = {num}, got shape {tuple(action.shape)}")
        return action.reshape(*action.shape[:-1], len(self.starts), self.action_stride)[..., :3]

    def predict(self, pickers: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Picker positions ``[..., P, 3]`` after ``action`` ``[..., A]``, as the env moves them."""
        low, high = self.low.to(pickers), self.high.to(pickers)
        delta = self._moves(action).to(pickers).clamp(-1.0, 1.0) * self.move_per_substep
        for _ in range(self.action_repeat):
            pickers = torch.minimum(torch.maximum(pickers + delta, low), high)
        return pickers

    def fuse(self, previous: torch.Tensor, count: torch.Tensor, action: torch.Tensor,
             observed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One step: ``previous`` fused pickers ``[..., P, 3]`` with ``count`` ``[..., P]`` views, moved
        by ``action``, then fused with the encoder's ``observed`` pickers ``[..., P, 3]``.
        Returns the new pickers and counts."""
        pred = self.predict(previous, action)
        seen = torch.ones_like(count, dtype=torch.bool) if self.view is None else self.view.visible(pred.flatten(-2))
        gain = seen.to(pred.dtype) / (count.to(pred.dtype) + 1.0)
        return pred + gain.unsqueeze(-1) * (observed.to(pred.dtype) - pred), count + seen.to(count.dtype)

    def holds(self, previous: torch.Tensor, action: torch.Tensor) -> torch.Tensor | None:
        """Which pickers ``[..., P]`` hold their source corner after ``action`` ``[..., A]``: those
        it closes within ``hold_radius`` of the corner in the ``previous`` estimate ``[..., D]``
        (``None`` with the hold off)."""
        if self.hold_radius <= 0:
            return None
        grasp = action.reshape(*action.shape[:-1], len(self.starts), self.action_stride)[..., -1]
        corners = previous[..., self._corner_index.to(previous.device)]
        return (grasp > 0) & ((self._pickers(previous) - corners).norm(dim=-1) <= self.hold_radius)

    def _write(self, estimate: torch.Tensor, pickers: torch.Tensor, held: torch.Tensor | None = None) -> torch.Tensor:
        out = estimate.clone()
        out[..., self._index.flatten().to(out.device)] = pickers.flatten(-2).to(out.dtype)
        if held is not None:  # a held corner's estimate is its picker's
            index = self._corner_index.to(out.device)
            out[..., index] = torch.where(held.unsqueeze(-1), pickers.to(out.dtype), out[..., index])
        return out

    def filter(self, estimate: torch.Tensor, action: torch.Tensor, time_dim: int = -2) -> torch.Tensor:
        """The fused estimates of stored episodes: ``estimate`` ``[..., T, D]`` (the encoder's, in state
        units) and the executed ``action`` ``[..., T, A]`` (``action[t]`` taken after ``estimate[t]``),
        as the env transform would have written them step by step; a new tensor."""
        est, act = estimate.movedim(time_dim, -2), action.movedim(time_dim, -2)
        if est.shape[:-1] != act.shape[:-1]:
            raise ValueError(f"PickerOdometry.filter: estimate {tuple(estimate.shape)} and action {tuple(action.shape)} "
                             "differ in their batch or time dims")
        observed = self._pickers(est.float())  # [..., T, P, 3]
        pickers, count = observed[..., 0, :, :], torch.ones(observed.shape[:-3] + observed.shape[-2:-1])
        written = [self._write(est[..., 0, :], pickers)]
        for t in range(1, est.shape[-2]):
            pickers, count = self.fuse(pickers, count, act[..., t - 1, :].float(), observed[..., t, :, :])
            # the hold reads the previous step's written estimate, as in an env
            written.append(self._write(est[..., t, :], pickers, self.holds(written[-1], act[..., t - 1, :])))
        return torch.stack(written, -2).movedim(-2, time_dim)

    # ------------------------------------------------------------------ TorchRL Transform
    def _reset(self, tensordict: TensorDictBase | None, tensordict_reset: TensorDictBase) -> TensorDictBase:
        # A fresh episode starts from the encoder's first view (one view fused). On a partial reset
        # the envs that go on keep their fused estimate and count.
        key = self.in_keys[0]
        est = tensordict_reset.get(key)
        count = torch.ones(est.shape[:-1] + (len(self.starts),), device=est.device)
        reset = None if tensordict is None else tensordict.get("_reset", None)
        if reset is not None and key in tensordict.keys(True) and self.count_key in tensordict.keys(True):
            keep = ~reset.reshape(est.shape[:-1]).bool()
            est = torch.where(keep.unsqueeze(-1), tensordict.get(key).to(est.dtype), est)
            count = torch.where(keep.unsqueeze(-1), tensordict.get(self.count_key).to(count.dtype), count)
        tensordict_reset.set(key, est)
        tensordict_reset.set(self.count_key, count)
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(self.action_key, None)
        if action is None:
            raise KeyError(f"PickerOdometry: {self.action_key!r} is missing from the step input")
        key = self.in_keys[0]
        previous, count = tensordict.get(key, None), tensordict.get(self.count_key, None)
        if previous is None or count is None:
            raise KeyError(f"PickerOdometry: {key!r} or {self.count_key!r} is missing from the step input; "
                           "was the env reset through this TransformedEnv?")
        observed = next_tensordict.get(key)
        pickers, count = self.fuse(self._pickers(previous.float()), count, action.float(), self._pickers(observed))
        next_tensordict.set(key, self._write(observed, pickers, self.holds(previous, action)))
        next_tensordict.set(self.count_key, count)
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError("PickerOdometry filters along an episode: use it in a TransformedEnv, or "
                           "PickerOdometry.filter on stored episodes")

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        key = self.in_keys[0]
        if key not in observation_spec.keys(True, True):
            raise KeyError(f"PickerOdometry: {key!r} is not in the observation spec (put it after the EncoderTransform)")
        spec = observation_spec[key]
        observation_spec[self.count_key] = Unbounded(shape=spec.shape[:-1] + (len(self.starts),),
                                                     dtype=torch.float32, device=spec.device)
        return observation_spec

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(starts={self.starts}, in_keys={self.in_keys}, action_repeat={self.action_repeat}, "
                f"move_per_substep={self.move_per_substep}, view={'image' if self.view is not None else 'none'}, "
                f"hold_radius={self.hold_radius})")
