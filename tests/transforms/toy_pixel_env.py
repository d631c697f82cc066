"""A tiny gymnasium env with Dict observations {"state", "pixels"} (not a cloth env).

Used by the transform and data tests as a cheap stand-in for any pixel-based TorchRL pipeline:
the state is a 2-D point, the pixels an ``size x size`` RGB uint8 image of that point, episodes
terminate after a length drawn from the env's RNG at reset (so batched envs reset at different
times), and the reward is ``-|state|_1`` so that return-to-go bookkeeping is non-trivial.
It lives in its own module so that ``SerialEnv``/``ParallelEnv`` workers can import it.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from torch import nn


class ToyPixelEnv(gym.Env):
    metadata = {"render_modes": []}

    def __init__(self, size: int = 16, min_len: int = 3, max_len: int = 8, float_pixels: bool = False):
        self.size = int(size)
        self.min_len, self.max_len = int(min_len), int(max_len)
        self.float_pixels = bool(float_pixels)
        if self.float_pixels:
            pix = spaces.Box(0.0, 1.0, (3, self.size, self.size), np.float32)
        else:
            pix = spaces.Box(0, 255, (self.size, self.size, 3), np.uint8)
        self.observation_space = spaces.Dict(
            {"state": spaces.Box(-np.inf, np.inf, (2,), np.float32), "pixels": pix}
        )
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self._state = np.zeros(2, np.float32)
        self._t = 0
        self._len = self.max_len

    def _obs(self):
        img = np.zeros((self.size, self.size, 3), np.uint8)
        ij = np.clip(((self._state + 1.0) * 0.5 * (self.size - 1)).round().astype(int), 0, self.size - 1)
        img[ij[0], ij[1]] = (255, 128, 64)
        img[..., 2] = np.uint8(self._t * 10 % 256)
        if self.float_pixels:
            pix = img.transpose(2, 0, 1).astype(np.float32) / 255.0
        else:
            pix = img
        return {"state": self._state.copy(), "pixels": pix}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._state = self.np_random.uniform(-0.5, 0.5, 2).astype(np.float32)
        self._t = 0
        self._len = int(self.np_random.integers(self.min_len, self.max_len + 1))
        return self._obs(), {}

    def step(self, action):
        action = np.clip(np.asarray(action, np.float32), -1.0, 1.0)
        self._state = np.clip(self._state + 0.1 * action, -1.0, 1.0).astype(np.float32)
        self._t += 1
        reward = float(-np.abs(self._state).sum())
        terminated = self._t >= self._len
        return self._obs(), reward, terminated, False, {}


def make_toy_env(size: int = 16, min_len: int = 3, max_len: int = 8, float_pixels: bool = False, **kwargs):
    """The toy env as a TorchRL env (``GymWrapper``), keys ``"state"``, ``"pixels"``."""
    from torchrl.envs import GymWrapper, RenameTransform, TransformedEnv

    # GymWrapper maps a Dict observation's "state" entry to TorchRL's "observation" key: rename it back.
    base = GymWrapper(ToyPixelEnv(size=size, min_len=min_len, max_len=max_len, float_pixels=float_pixels), **kwargs)
    return TransformedEnv(base, RenameTransform(in_keys=["observation"], out_keys=["state"]))


class TinyEncoder(nn.Module):
    """A small encoder for uint8 ``[N, H, W, 3]`` images -> ``[N, out_dim]`` (stand-in for a state encoder)."""

    def __init__(self, out_dim: int = 4):
        super().__init__()
        self.conv = nn.Conv2d(3, 4, 3, stride=2)
        self.head = nn.Linear(4, out_dim)
        self.calls = 0

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        x = pixels.float().div(255.0) if pixels.dtype == torch.uint8 else pixels.float()
        if x.shape[-1] == 3:
            x = x.movedim(-1, -3)
        x = torch.relu(self.conv(x)).mean((-1, -2))
        return self.head(x)


class LazyEncoder(nn.Module):
    """An encoder built from lazy modules (``LazyConv2d``, ``LazyLinear``): it takes any channel count
    and image size, and its shapes are only fixed by the first call."""

    def __init__(self, out_dim: int = 3):
        super().__init__()
        self.conv = nn.LazyConv2d(4, 3, stride=2)
        self.pool = nn.AdaptiveAvgPool2d(2)
        self.head = nn.LazyLinear(out_dim)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        x = pixels.float().div(255.0) if pixels.dtype == torch.uint8 else pixels.float()
        x = torch.relu(self.conv(x.movedim(-1, -3)))
        return self.head(self.pool(x).flatten(1))


def make_gym_mujoco_env(encoder_fn=None, size: int = 64):
    """TorchRL's ``GymEnv("InvertedPendulum-v5")`` (gymnasium's MuJoCo env, not ours) rendering
    ``size x size`` pixels, resized to two keys (``"pixels32"``, ``"pixels24"``, two "cameras" of
    different resolutions) and, when ``encoder_fn`` is given, encoded by ``EncoderTransform`` into
    ``"estimate32"`` and ``"estimate24"``."""
    from torchrl.envs import Compose, GymEnv, TransformedEnv

    from trakdis.transforms import EncoderTransform, ImageResize

    base = GymEnv("InvertedPendulum-v5", from_pixels=True, pixels_only=False, width=size, height=size)
    transforms = [
        ImageResize(in_keys=["pixels"], out_keys=["pixels32"], size=32),
        ImageResize(in_keys=["pixels"], out_keys=["pixels24"], size=24),
    ]
    if encoder_fn is not None:
        transforms.append(
            EncoderTransform(encoder_fn(), in_keys=["pixels32", "pixels24"], out_keys=["estimate32", "estimate24"])
        )
    return TransformedEnv(base, Compose(*transforms))


def make_toy_env_with(transforms_fn=None, **env_kwargs):
    """Toy env with transforms built by ``transforms_fn()`` applied inside the (worker) process."""
    from torchrl.envs import TransformedEnv

    env = make_toy_env(**env_kwargs)
    if transforms_fn is not None:
        env = TransformedEnv(env, transforms_fn())
    return env


def make_toy_collect_env(size: int = 8, horizon: int = 6, min_len: int = 3, max_len: int = 8):
    """Toy env shaped like ``trakdis.envs.make_env``: ``"state"``, ``"pixels"``, ``"step_count"`` and
    truncation at ``horizon`` (episodes may also terminate earlier, after ``min_len..max_len`` steps)."""
    from torchrl.envs import StepCounter, TransformedEnv

    return TransformedEnv(make_toy_env(size=size, min_len=min_len, max_len=max_len), StepCounter(max_steps=horizon))


class _SeededRandomActions(nn.Module):
    def __init__(self, seed):
        super().__init__()
        self.generator = torch.Generator().manual_seed(0 if seed is None else int(seed))

    def forward(self, state):
        return torch.rand(state.shape, generator=self.generator) * 2 - 1


def make_toy_policy(seed=None):
    """A seeded random policy (reads ``"state"``, writes ``"action"``) for the toy env."""
    from tensordict.nn import TensorDictModule

    return TensorDictModule(_SeededRandomActions(seed), in_keys=["state"], out_keys=["action"])
