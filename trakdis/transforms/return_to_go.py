"""Return-to-go: an online countdown for acting, and hindsight relabelling for training.

Both use one ``rtg_scale`` (see docs/design.md): the value a Decision Transformer sees is
``rtg_scale * (sum of the rewards still to come)``.

* Acting: :class:`ReturnToGo` starts every episode at ``rtg_scale * target_return`` and subtracts
  ``rtg_scale * reward`` after every step. It subclasses TorchRL's ``TargetReturn(mode="reduce")``,
  which already resets the countdown per env on partial resets of batched envs (checked in
  tests/transforms/test_return_to_go.py with ``SerialEnv``/``ParallelEnv`` and envs that end at
  different times); it only lacks the scale, which is added here.
* Training: :func:`hindsight_return_to_go` computes ``rtg_scale * sum_{t' >= t} r_t'`` from the stored
  rewards of padded trajectories. TorchRL's ``Reward2GoTransform`` is an inverse (write-time)
  transform that needs every stored sequence to contain an episode end and has no scale, so it cannot
  relabel the return-to-go at sampling time from a trajectory store; this function can, and the
  replay buffer (``trakdis.data.TrajectoryReplayBuffer``) uses it.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs.transforms import TargetReturn

__all__ = ["ReturnToGo", "hindsight_return_to_go"]


class ReturnToGo(TargetReturn):
    """Online return-to-go countdown for acting with a Decision Transformer.

    On reset (per env for batched envs with partial resets) the ``out_key`` entry (``[*B, 1]``,
    default ``"return_to_go"``) is set to ``rtg_scale * target_return``; after each step the
    ``rtg_scale * reward`` just received is subtracted, so the policy always sees the (scaled) return
    still to be achieved. The entry lives in the observation spec so it survives ``step_mdp``.

    Args:
        target_return: the (unscaled) return to aim for at the start of an episode
            (e.g. -1.0 for the cloth tasks, whose rewards are negative).
        rtg_scale: multiplies both the target and the rewards (default 1.0).
        out_key: where to write the countdown (default ``"return_to_go"``).
        reward_key: reward entry to subtract (default: the env's only reward key).
        reset_key: reset entry to use for partial resets (default: the env's only reset key).
        mode: ``"reduce"`` (countdown, default) or ``"constant"`` (keep the initial value).
    """

    def __init__(
        self,
        target_return: float,
        rtg_scale: float = 1.0,
        out_key: NestedKey = "return_to_go",
        reward_key: NestedKey | None = None,
        reset_key: NestedKey | None = None,
        mode: str = "reduce",
    ):
        self.unscaled_target_return = float(target_return)
        self.rtg_scale = float(rtg_scale)
        super().__init__(
            target_return=self.unscaled_target_return * self.rtg_scale,
            mode=mode,
            in_keys=None if reward_key is None else [reward_key],
            out_keys=[out_key],
            reset_key=reset_key,
        )

    def _apply_transform(self, reward: torch.Tensor, target_return: torch.Tensor) -> torch.Tensor:
        if target_return is None:
            raise KeyError(
                f"ReturnToGo: {self.out_keys[0]!r} is missing from the step input; was the env reset "
                f"through this TransformedEnv?"
            )
        return super()._apply_transform(reward * self.rtg_scale, target_return)

    def _reset(self, tensordict: TensorDictBase | None, tensordict_reset: TensorDictBase) -> TensorDictBase:
        if tensordict is None:  # plain env.reset(): start every env's countdown afresh
            tensordict = tensordict_reset.empty()
        return super()._reset(tensordict, tensordict_reset)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(target_return={self.unscaled_target_return}, rtg_scale={self.rtg_scale}, "
            f"out_key={self.out_keys[0]!r}, mode={self.mode!r})"
        )


def hindsight_return_to_go(
    reward: torch.Tensor,
    mask: torch.Tensor | None = None,
    rtg_scale: float = 1.0,
    time_dim: int = -2,
) -> torch.Tensor:
    """Hindsight return-to-go of (padded) trajectories: ``rtg[t] = rtg_scale * sum_{t' >= t, mask} r[t']``.

    Args:
        reward: rewards ``[..., T, 1]`` (or ``[..., T]`` with ``time_dim=-1``); ``reward[t]`` is the
            reward received after the action at step ``t``.
        mask: bool, same shape as ``reward`` or without its trailing singleton; True for real steps.
            Masked-out steps contribute nothing and get a return-to-go of 0. ``None``: all real.
        rtg_scale: multiplies the result.
        time_dim: the time dimension of ``reward``.

    The sum is accumulated in float64 and cast back, so 100-step sums are exact to float32 precision.

    Example:
        >>> hindsight_return_to_go(torch.tensor([[-1., -2., -3.]]), time_dim=-1)
        tensor([[-6., -5., -3.]])
    """
    if not reward.is_floating_point():
        raise TypeError(f"hindsight_return_to_go: reward must be floating point, got {reward.dtype}")
    r = reward.double()
    if mask is not None:
        if mask.shape != reward.shape:
            if mask.shape == reward.shape[:-1] and reward.shape[-1] == 1 and time_dim != -1:
                mask = mask.unsqueeze(-1)
            else:
                raise ValueError(
                    f"hindsight_return_to_go: mask shape {tuple(mask.shape)} does not match reward shape "
                    f"{tuple(reward.shape)}"
                )
        r = torch.where(mask.bool(), r, torch.zeros((), dtype=r.dtype, device=r.device))
    rtg = r.flip(time_dim).cumsum(time_dim).flip(time_dim)
    if mask is not None:
        rtg = torch.where(mask.bool(), rtg, torch.zeros((), dtype=rtg.dtype, device=rtg.device))
    return (rtg * rtg_scale).to(reward.dtype)
