"""Gaussian noise on state observations (the paper's robustness experiment)."""

from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded, TensorSpec, Unbounded
from torchrl.envs.transforms import ObservationTransform
from torchrl.envs.transforms.transforms import _apply_to_composite

__all__ = ["StateNoise"]


class StateNoise(ObservationTransform):
    """Adds i.i.d. Gaussian noise ``N(0, sigma^2)`` to state keys (TorchRL ``Transform``).

    Used on the estimated state (``"state_estimate"``) to test or train robustness (the paper uses
    sigma 1e-5 .. 1e-3). Works in a ``TransformedEnv`` (on reset and step outputs) and as a
    replay-buffer transform. ``sigma=0`` is the identity.

    Args:
        sigma: noise standard deviation (>= 0).
        in_keys: keys to perturb (default ``["state_estimate"]``).
        out_keys: keys to write (default: ``in_keys``, in place).
        seed: seeds a private ``torch.Generator`` (CPU) so the noise sequence is reproducible and
            independent of the global RNG; ``None`` uses the global RNG. Note that copies of the
            transform in ``ParallelEnv`` workers start from the same generator state.
        shared_dims: dims of the perturbed tensor along which one draw is shared (drawn with size 1
            there and broadcast). ``(-2,)`` on a replay buffer's windows ``[B, K, D]``: one offset per
            window, the same at its ``K`` steps, a biased state rather than a noisy one (an image
            encoder errs by a bias per configuration, shared by every view of it). Default: none,
            i.i.d. per entry. Not for env steps, where the tensor has no time dim.

    A bounded input spec becomes unbounded (noise can leave the bounds).
    """

    def __init__(
        self,
        sigma: float,
        in_keys: Sequence[NestedKey] | None = None,
        out_keys: Sequence[NestedKey] | None = None,
        seed: int | None = None,
        shared_dims: Sequence[int] = (),
    ):
        if in_keys is None:
            in_keys = ["state_estimate"]
        if out_keys is None:
            out_keys = list(in_keys)
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        sigma = float(sigma)
        if not sigma >= 0.0:
            raise ValueError(f"StateNoise: sigma must be >= 0, got {sigma}")
        self.sigma = sigma
        self.shared_dims = tuple(int(d) for d in shared_dims)
        self.seed = seed
        self._generator = None
        self._generator_state = None

    def _get_generator(self) -> torch.Generator | None:
        if self.seed is None:
            return None
        if self._generator is None:
            self._generator = torch.Generator()
            if self._generator_state is not None:
                self._generator.set_state(self._generator_state)
                self._generator_state = None
            else:
                self._generator.manual_seed(int(self.seed))
        return self._generator

    def set_seed(self, seed: int) -> None:
        """Restarts the private generator from ``seed``."""
        self.seed = int(seed)
        self._generator = None
        self._generator_state = None

    def __getstate__(self):
        # torch.Generator does not pickle: ship its state (for ParallelEnv workers / checkpoints).
        state = super().__getstate__() if hasattr(super(), "__getstate__") else self.__dict__.copy()
        state = dict(state)
        gen = state.pop("_generator", None)
        if gen is not None:
            state["_generator_state"] = gen.get_state()
        state["_generator"] = None
        return state

    def _apply_transform(self, obs: torch.Tensor) -> torch.Tensor:
        if not obs.is_floating_point():
            raise TypeError(f"StateNoise: {self.in_keys} must be floating point, got {obs.dtype}")
        if self.sigma == 0.0:
            return obs
        shape = list(obs.shape)
        for d in self.shared_dims:
            if not -obs.ndim <= d < obs.ndim:
                raise ValueError(f"StateNoise: shared dim {d} of {self.in_keys} of shape {tuple(obs.shape)} "
                                 f"does not exist")
            shape[d] = 1
        gen = self._get_generator()
        if gen is None:
            noise = torch.randn(shape, dtype=obs.dtype, device=obs.device)
        else:
            noise = torch.randn(shape, dtype=obs.dtype, generator=gen).to(obs.device)
        return obs + self.sigma * noise

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    @_apply_to_composite
    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        if isinstance(observation_spec, Bounded) and self.sigma > 0:
            return Unbounded(
                shape=observation_spec.shape, dtype=observation_spec.dtype, device=observation_spec.device
            )
        return observation_spec

    def __repr__(self) -> str:
        shared = f", shared_dims={self.shared_dims}" if self.shared_dims else ""
        return f"{type(self).__name__}(sigma={self.sigma}, in_keys={self.in_keys}, seed={self.seed}{shared})"
