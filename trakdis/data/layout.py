"""The layout of an episode's steps, defined once for datasets, rollouts and the replay buffer.

* :data:`STEP_KEYS`: the per-step entries of an expert dataset and where each comes from in a
  TorchRL rollout or collector batch (``("next", ...)``: what the step produced);
  :data:`REQUIRED_KEYS` the ones every dataset has; :data:`ACTING_KEYS` the entries a policy's
  acting env adds to a rollout (an encoder's estimate, the return-to-go countdown).
* :func:`valid_mask`: which steps of padded ``[N, T]`` episodes are real, from their lengths.
* :func:`real_steps`: the real steps of padded episodes as one flat TensorDict.
* :func:`episode_to_trajectory`: one rollout episode in the dataset layout, ready for the buffer.
* :func:`split_episodes_train_val`: a seeded split of episode indices into training and validation.
* :func:`encode_trajectories`: padded episodes with an encoder's output in place of their images.
"""
from __future__ import annotations

from typing import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase

__all__ = ["ACTING_KEYS", "REQUIRED_KEYS", "STEP_KEYS", "encode_trajectories", "episode_to_trajectory", "real_steps",
           "split_episodes_train_val", "valid_mask"]

#: per-step keys: (dataset key, key in the collector batch). Next-step values are what the step produced.
STEP_KEYS = (
    ("state", "state"),
    ("pixels", "pixels"),
    ("action", "action"),
    ("reward", ("next", "reward")),
    ("normalized_performance", ("next", "normalized_performance")),
    ("sim_unstable", ("next", "sim_unstable")),
    ("done", ("next", "done")),
    ("terminated", ("next", "terminated")),
    ("truncated", ("next", "truncated")),
    ("step_count", "step_count"),
)
REQUIRED_KEYS = ("state", "action", "reward", "done", "terminated", "truncated", "step_count")
#: per-step entries of a policy's rollout that an expert dataset does not have
ACTING_KEYS = ("state_estimate", "return_to_go")

_STEP_ENTRIES = tuple(name for name, src in STEP_KEYS if not isinstance(src, tuple))
_NEXT_ENTRIES = tuple((name, src) for name, src in STEP_KEYS if isinstance(src, tuple))


def valid_mask(lengths: torch.Tensor, horizon: int) -> torch.Tensor:
    """``[N, horizon]`` bool: True at the real steps of episodes of ``lengths`` ``[N]``, False at the
    padding after each episode's end."""
    return torch.arange(horizon).unsqueeze(0) < lengths.unsqueeze(1)


def real_steps(steps: TensorDict, lengths: torch.Tensor, episodes: torch.Tensor | None = None) -> TensorDict:
    """The real steps of ``episodes`` (all by default) of ``steps [episodes, horizon]``, in episode
    order, as one flat TensorDict (steps past an episode's length are padding)."""
    episodes = torch.arange(steps.shape[0]) if episodes is None else episodes.sort().values
    valid = valid_mask(lengths[episodes], steps.shape[1])
    return steps[episodes].to_tensordict()[valid]


def split_episodes_train_val(num_episodes: int, val_fraction: float, *, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(train, val)``: indices of ``num_episodes`` episodes split at random (``seed``) into a
    training and a validation set, by episode (the steps of one episode are strongly correlated).

    The validation set holds ``round(val_fraction * num_episodes)`` episodes, at least one when
    ``val_fraction > 0``, and none when ``val_fraction == 0`` or there is a single episode."""
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    n_val = max(1, int(round(val_fraction * num_episodes))) if num_episodes > 1 and val_fraction > 0 else 0
    perm = torch.randperm(num_episodes, generator=torch.Generator().manual_seed(seed))
    return perm[n_val:], perm[:n_val]


@torch.no_grad()
def encode_trajectories(trajectories: TensorDictBase, encoder: Callable[[torch.Tensor], torch.Tensor], *,
                        keys: Sequence[str] = (), in_key: str = "pixels", out_key: str = "state_estimate",
                        batch_size: int = 16) -> TensorDict:
    """Padded episodes ``[N, T]`` with ``out_key`` = ``encoder(trajectories[in_key])`` and the entries
    ``keys`` (the images themselves are left out): an expert dataset as an image policy sees it.

    The images go through ``encoder`` ``batch_size`` episodes at a time, without gradients; ``encoder``
    maps ``[B, T, C, H, W]`` images to ``[B, T, D]`` (e.g. a frozen
    :class:`~trakdis.modules.NormalizedEncoder`)."""
    images = trajectories.get(in_key)
    out = torch.cat([encoder(torch.as_tensor(images[i : i + batch_size]))
                     for i in range(0, trajectories.shape[0], batch_size)])
    encoded = trajectories.select(*keys).to_tensordict()
    encoded.set(out_key, out)
    return encoded


def episode_to_trajectory(episode: TensorDictBase, keys: Sequence[str] = _STEP_ENTRIES + ACTING_KEYS) -> TensorDict:
    """Flatten one rollout episode ``[T]`` into the dataset layout (``reward`` = reward after ``action``).

    Step entries ``keys`` (by default every step entry of :data:`STEP_KEYS` and :data:`ACTING_KEYS`)
    are taken as they are when present; ``reward``, ``normalized_performance``, ``sim_unstable``
    and the done flags come from ``("next", ...)``.
    """
    if episode.batch_dims != 1:
        raise ValueError(f"episode_to_trajectory: expected one episode of shape [T], got batch {tuple(episode.batch_size)}")
    out = TensorDict({}, batch_size=episode.batch_size)
    for k in keys:
        if k in episode.keys():
            out.set(k, episode.get(k))
    for k in ("state", "action"):
        if k not in out.keys():
            raise KeyError(f"episode_to_trajectory: the episode has no {k!r}; keys: {sorted(map(str, episode.keys()))}")
    for name, src in _NEXT_ENTRIES:
        if src in episode.keys(True):
            out.set(name, episode.get(src))
    if "reward" not in out.keys():
        raise KeyError("episode_to_trajectory: the episode has no ('next', 'reward')")
    return out
