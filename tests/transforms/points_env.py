"""A tiny TorchRL env whose ``"state"`` holds two xyz points (not a cloth env).

Used by the transform tests as a cheap stand-in for a cloth env's reduced state: point 0 starts in
the ClothFold camera's view, point 1 above it (out of view); each step moves both by the action.
``"state_estimate"`` is the state plus 0.01 (an encoder a centimetre off). The env keeps its own
state: transforms may rewrite the observations it returns.
"""
from __future__ import annotations

import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import EnvBase

START = (0.0, 0.0, 0.0, 0.0, 0.0, 0.3)


class PointsEnv(EnvBase):
    def __init__(self, max_steps: int = 5):
        super().__init__(batch_size=torch.Size([]))
        self.max_steps = int(max_steps)
        self.observation_spec = Composite(
            state=Bounded(-0.5, 0.35, (6,), dtype=torch.float32),
            state_estimate=Unbounded((6,), dtype=torch.float32),
        )
        self.action_spec = Bounded(-0.01, 0.01, (6,), dtype=torch.float32)
        self.reward_spec = Unbounded((1,), dtype=torch.float32)
        self._state = torch.tensor(START)
        self._t = 0

    def _obs(self, **entries) -> TensorDict:
        done = torch.tensor([self._t >= self.max_steps])
        return TensorDict({"state": self._state.clone(), "state_estimate": self._state + 0.01, "done": done,
                           "terminated": done.clone(), **entries}, [])

    def _reset(self, tensordict=None, **kwargs) -> TensorDict:
        self._state, self._t = torch.tensor(START), 0
        return self._obs()

    def _step(self, tensordict) -> TensorDict:
        self._state = self._state + tensordict["action"]
        self._t += 1
        return self._obs(reward=torch.zeros(1))

    def _set_seed(self, seed):
        return seed
