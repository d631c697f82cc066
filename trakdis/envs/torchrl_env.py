"""TorchRL factory for the cloth tasks: ``GymWrapper`` + info reader + ``StepCounter``."""

from __future__ import annotations

import torch
from torchrl.data import Binary, Composite, Unbounded
from torchrl.envs import Compose, GymWrapper, RenameTransform, StepCounter, TransformedEnv
from torchrl.envs.gym_like import BaseInfoDictReader

from trakdis.envs.cloth_env import ENV_CLASSES
from trakdis.envs.specs import check_task

INFO_KEYS = ("normalized_performance", "sim_unstable")


class ClothInfoReader(BaseInfoDictReader):
    """Copies ``normalized_performance`` (float32) and ``sim_unstable`` (bool) from the gym info.

    TorchRL's ``default_info_dict_reader`` writes the gym env's scalar infos with shape ``[]``,
    while the design contract (and its spec) wants ``[1]``, like ``"reward"``; this reader
    reshapes them and fails with the missing key's name if the env did not provide it.
    """

    def __init__(self, device=None):
        self._device = device
        self._info_spec = Composite(
            normalized_performance=Unbounded((1,), dtype=torch.float32, device=device),
            sim_unstable=Binary(n=1, shape=(1,), dtype=torch.bool, device=device),
            shape=(),
        )

    def __call__(self, info_dict, tensordict):
        for key in INFO_KEYS:
            if key not in info_dict:
                raise KeyError(f"cloth env info is missing {key!r}; got keys {sorted(info_dict)}")
            spec = self._info_spec[key]
            val = torch.as_tensor(info_dict[key], dtype=spec.dtype).reshape(1)
            tensordict.set(key, val.to(tensordict.device) if tensordict.device is not None else val)
        return tensordict

    def reset(self):
        pass

    @property
    def info_spec(self):
        return self._info_spec


def make_env(
    task: str,
    from_pixels: bool = False,
    image_size: int = 32,
    device: str | torch.device = "cpu",
    seed: int | None = None,
    split: str = "train",
    **env_kwargs,
) -> TransformedEnv:
    """A TorchRL environment for ``task`` with the keys of docs/design.md.

    Keys per step: ``"state"`` ``[state_dim]`` float32, ``"pixels"`` ``[H, W, 3]`` uint8 (with
    ``from_pixels``), ``"action"`` ``[action_dim]``, ``("next", "reward")`` ``[1]`` float32 (task
    performance), ``"normalized_performance"`` ``[1]`` float32, ``"sim_unstable"`` ``[1]`` bool,
    ``"step_count"`` ``[1]`` int64 and ``"done"``/``"terminated"``/``"truncated"``.

    ``env_kwargs`` go to :class:`~trakdis.envs.ClothEnv` (``horizon``, ``resolution``, ...). Use
    ``functools.partial(make_env, task, ...)`` as the ``create_env_fn`` of ``ParallelEnv``.
    """
    check_task(task)
    gym_env = ENV_CLASSES[task](from_pixels=from_pixels, image_size=image_size, split=split, **env_kwargs)
    # GymWrapper's ``from_pixels`` means "render through gym's pixel wrapper": our env puts the
    # image in its Dict observation itself, so it stays False here.
    env = with_contract_keys(GymWrapper(gym_env, device=device))
    if seed is not None:
        env.set_seed(seed)
    return env


def with_contract_keys(env: GymWrapper) -> TransformedEnv:
    """Gives TorchRL's wrapper of a cloth gym env the keys of :func:`make_env` (docs/design.md).

    ``GymEnv("trakdis/<Task>-v0")`` (or ``GymWrapper`` around the gym env) alone differs from
    :func:`make_env` in three ways, all TorchRL's conventions: the ``"state"`` entry of the Dict
    observation is renamed ``"observation"`` (``torchrl/envs/libs/gym.py``, ``convert_dict_spec``;
    no option turns it off), the info entries are not read, and there is no step count. This
    registers :class:`ClothInfoReader` on ``env`` and adds ``RenameTransform("observation" ->
    "state")`` and ``StepCounter()``; :func:`make_env` is exactly this on ``GymWrapper``::

        env = with_contract_keys(GymEnv("trakdis/ClothFold-v0", from_pixels=True, pixels_only=False))

    gives the keys and specs of ``make_env("ClothFold", from_pixels=True)`` (pixels rendered at the
    env's default ``image_size`` through TorchRL's pixel wrapper: the same images).
    """
    if isinstance(env, TransformedEnv):
        raise TypeError(f"with_contract_keys: pass the GymEnv/GymWrapper itself, got a TransformedEnv around {type(env.base_env).__name__}")
    env.set_info_dict_reader(ClothInfoReader(device=env.device))
    # the design contract keeps the name "state" (see the docstring)
    return TransformedEnv(env, Compose(RenameTransform(["observation"], ["state"]), StepCounter()))
