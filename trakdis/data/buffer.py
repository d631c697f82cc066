"""The offline-to-online trajectory replay buffer of Online Decision Transformer, on TorchRL parts.

Semantics (ODT, Zheng et al. 2022, and its reference code):

* The buffer holds whole trajectories (capacity counted in trajectories). It starts full of offline
  trajectories; when there are more than ``capacity`` of them, the highest-return ones are kept.
* Each online trajectory replaces the *oldest* stored one; offline trajectories count as older than
  any online one and, among themselves, lower return = older. So the lowest-return offline data
  goes first and the buffer turns from offline to online (``online_fraction``).
  With ``replacement="lowest_return"`` a full buffer instead keeps the ``capacity`` highest-return
  trajectories seen so far: a new one replaces the lowest-return stored one, offline or online, and
  is dropped if it is not better (return-filtered, like self-imitation learning; not ODT).
* ``sample(B)`` returns windows ``[B, K]``: a start step is drawn uniformly among all stored steps
  (i.e. a trajectory with probability proportional to its length, then a uniform start in it), the
  window covers up to ``K`` steps from there and is left-padded to ``K`` with ``mask`` False and
  zero values; ``return_to_go`` is relabelled from the stored rewards at sampling time
  (hindsight, times ``rtg_scale``; ``relabel_return_to_go=False`` stores and returns the acting
  one instead); ``timestep`` is the step index in the episode. With
  ``early_windows=True`` (used by the recipes) windows may also begin up to ``K - 1`` steps before
  the first step, so that the first steps of an episode are trained as often as the others.

TorchRL parts and why:

* Storage: TorchRL ``LazyTensorStorage`` of trajectories (each item a padded ``[max_len]`` TensorDict),
  so the buffer lives in one preallocated TensorDict ``[capacity, max_len]`` and windows are gathered
  with one advanced index (no Python loop over trajectories).
* Writer: TorchRL ``RoundRobinWriter``. Its ring order *is* ODT's replacement order provided that the
  offline trajectories are written in ascending order of return (done in :meth:`load_offline`):
  the ring cursor then points at the lowest-return offline trajectory first, then the next, and
  after one full turn at the oldest online trajectory. No custom writer is needed.
  ``replacement="lowest_return"``: TorchRL ``TensorDictMaxValueWriter`` ranking trajectories by their
  summed reward (padding is zero), subclassed for the two gaps it has with trajectory items
  (:class:`TopReturnWriter`).
* Sampler: :class:`WindowSampler` (ours). TorchRL's ``SliceSampler`` samples trajectory slices of
  *fixed* length that must fit inside a trajectory (or are truncated at the end, not left-padded),
  picks trajectories uniformly rather than by length unless weighted by hand, and finds trajectory
  boundaries from done/trajectory-id markers at every call; ODT needs windows that may start in the
  last ``K - 1`` steps and are left-padded with a mask. Our sampler keeps a cumulative sum of the
  stored lengths (updated on writes only) and draws ``B`` starts with one ``searchsorted``, so a
  sample costs O(B log capacity + B K), independent of the buffer size in practice.
* TorchRL's ``OfflineToOnlineReplayBuffer`` mixes an immutable offline dataset and an online buffer
  of transitions at a fixed fraction per batch; it does not replace offline trajectories by online
  ones, which is the mechanism of ODT, hence this class.
"""

from __future__ import annotations

from typing import Any, Iterable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import LazyTensorStorage, ReplayBuffer, RoundRobinWriter, TensorDictMaxValueWriter
from torchrl.data.replay_buffers.samplers import Sampler

from trakdis.transforms.return_to_go import hindsight_return_to_go

from .layout import episode_to_trajectory, valid_mask

__all__ = ["TopReturnWriter", "TrajectoryReplayBuffer", "WindowSampler"]


class WindowSampler(Sampler):
    """Samples left-padded windows of ``K`` steps from a storage of padded trajectories.

    Returns a tuple index ``(trajectory [B, K], step [B, K])`` for a storage whose items are
    ``[max_len]`` trajectories, and ``info`` with ``"mask"`` ``[B, K]`` (False on left padding),
    ``"start"`` and ``"trajectory"`` ``[B]``. Padded positions index the window's first real step
    (a valid address); callers must zero them using the mask.

    Trajectory lengths are told to the sampler with :meth:`set_lengths` when written.

    Args:
        capacity: number of trajectory slots.
        context_len: window length ``K``.
        seed: seeds the sampler's own ``torch.Generator`` (``None``: global RNG).
        early_windows: also draw windows that begin up to ``K - 1`` steps *before* a trajectory's
            first step (left-padded), so that every step lies in ``K`` possible windows. With
            ``False`` (the DT/ODT reference: starts inside the trajectory) step ``t < K - 1`` lies
            in only ``t + 1`` of them: the first step of an episode is trained ~K times less
            often than the others, although every acting context of the first ``K - 1`` steps
            is such a window. Trajectories are then drawn with probability proportional to
            ``length + K - 1``.
    """

    def __init__(self, capacity: int, context_len: int, seed: int | None = None, early_windows: bool = False):
        super().__init__()
        if context_len < 1:
            raise ValueError(f"WindowSampler: context_len must be >= 1, got {context_len}")
        self.capacity = int(capacity)
        self.context_len = int(context_len)
        self.early_windows = bool(early_windows)
        self.lengths = torch.zeros(self.capacity, dtype=torch.long)
        self._update_cdf()
        self.seed = seed
        self._generator = None
        if seed is not None:
            self._generator = torch.Generator().manual_seed(int(seed))

    def set_lengths(self, index: torch.Tensor, lengths: torch.Tensor) -> None:
        """Records the lengths of the trajectories just written at ``index`` (O(capacity), writes only)."""
        self.lengths[index] = lengths.to(torch.long)
        self._update_cdf()

    def _update_cdf(self) -> None:
        # number of possible window starts per trajectory
        starts = self.lengths + (self.context_len - 1) * (self.lengths > 0) if self.early_windows else self.lengths
        self._starts = starts
        self._cdf = torch.cumsum(starts, 0)

    @property
    def total_steps(self) -> int:
        """Number of stored steps."""
        return int(self.lengths.sum())

    @property
    def num_windows(self) -> int:
        """Number of distinct windows (window starts) that can be drawn."""
        return int(self._cdf[-1]) if self.capacity else 0

    def sample(self, storage, batch_size: int) -> tuple[tuple[torch.Tensor, torch.Tensor], dict]:
        total = self.num_windows
        if total == 0:
            raise RuntimeError("WindowSampler: the buffer holds no steps; load or add trajectories first")
        K = self.context_len
        u = (torch.rand(batch_size, generator=self._generator, dtype=torch.float64) * total).long().clamp_(max=total - 1)
        traj = torch.searchsorted(self._cdf, u, right=True)
        start = u - (self._cdf[traj] - self._starts[traj])
        if self.early_windows:
            start = start - (K - 1)  # may be negative: the window begins before the first step
        first = start.clamp(min=0)
        n_valid = torch.minimum(self.lengths[traj], start + K) - first
        pad = K - n_valid
        j = torch.arange(K)
        mask = j.unsqueeze(0) >= pad.unsqueeze(1)
        steps = torch.where(mask, first.unsqueeze(1) + j.unsqueeze(0) - pad.unsqueeze(1), first.unsqueeze(1))
        start = first
        traj_k = traj.unsqueeze(1).expand(batch_size, K)
        return (traj_k, steps), {"mask": mask, "start": start, "trajectory": traj}

    def _empty(self):
        self.lengths.zero_()
        self._update_cdf()

    def state_dict(self) -> dict[str, Any]:
        out = {"lengths": self.lengths.clone(), "context_len": self.context_len, "early_windows": self.early_windows}
        if self._generator is not None:
            out["generator"] = self._generator.get_state()
        return out

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        if state_dict["lengths"].shape != self.lengths.shape:
            raise ValueError(
                f"WindowSampler: state_dict has {state_dict['lengths'].shape[0]} slots, this sampler "
                f"{self.capacity}"
            )
        self.lengths.copy_(state_dict["lengths"])
        self.context_len = int(state_dict["context_len"])
        self.early_windows = bool(state_dict.get("early_windows", self.early_windows))
        self._update_cdf()
        if "generator" in state_dict and self._generator is not None:
            self._generator.set_state(state_dict["generator"])

    def dumps(self, path):
        torch.save(self.state_dict(), f"{path}/window_sampler.pt")

    def loads(self, path):
        self.load_state_dict(torch.load(f"{path}/window_sampler.pt", weights_only=True))

    def __repr__(self) -> str:
        return f"{type(self).__name__}(capacity={self.capacity}, context_len={self.context_len})"


class TopReturnWriter(TensorDictMaxValueWriter):
    """TorchRL's ``TensorDictMaxValueWriter`` ranking stored trajectories by return, with a state dict.

    Two departures from TorchRL 0.14's writer, each a gap for trajectory items:

    * ``state_dict`` raises ``NotImplementedError`` there (it only has ``dumps``/``loads`` to a
      directory), and the replay buffer's ``state_dict`` calls it; checkpoints need the heap of
      (return, slot) pairs and the cursor, which is all its state.
    * ``extend`` there builds its output index with ``data.shape``, which fails for items that are
      trajectories (``[N, max_len]`` written into a storage of ``N`` slots, the use its docstring
      allows); here the index has one entry per trajectory.
    """

    def __init__(self, rank_key: NestedKey = "reward"):
        super().__init__(rank_key=rank_key, reduction="sum")

    def extend(self, data: TensorDictBase) -> torch.Tensor:
        """Writes the items of ``data`` (along its first dim) that rank among the top; returns their
        slots, -1 for items not kept."""
        slot_of_item = {}
        for i in range(data.shape[0]):
            slot = self.get_insert_index(data[i])
            if slot is not None:
                self._write_count += 1
                slot_of_item[slot] = i  # a later item of the batch may evict an earlier one: last wins
        out = torch.full((data.shape[0],), -1, dtype=torch.long)
        if slot_of_item:
            slots = torch.tensor(list(slot_of_item.keys()), dtype=torch.long)
            items = torch.tensor(list(slot_of_item.values()), dtype=torch.long)
            out[items] = slots
            self._storage.set(slots, data[items])
            self._mark_update_entities(slots)
        return out

    def state_dict(self) -> dict[str, Any]:
        return {"cursor": int(self._cursor), "top_values": [(float(r), int(i)) for r, i in self._current_top_values]}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._cursor = int(state_dict["cursor"])
        self._current_top_values = [(float(r), int(i)) for r, i in state_dict["top_values"]]


def _get(td: TensorDictBase, key: NestedKey) -> torch.Tensor | TensorDictBase | None:
    """``td[key]``, else ``td["next", key]`` (collector layout: rewards live under ``"next"``)."""
    val = td.get(key, None)
    if val is None:
        nk = ("next", *key) if isinstance(key, tuple) else ("next", key)
        val = td.get(nk, None)
    return val


class TrajectoryReplayBuffer:
    """ODT's offline-to-online replay buffer of whole trajectories (see the module docstring).

    Args:
        capacity: number of trajectories kept.
        context_len: window length ``K`` of :meth:`sample`.
        max_len: the longest trajectory (the episode horizon, e.g. 100); shorter ones are padded.
        keys: per-step keys to store and return besides the bookkeeping (default
            ``("state", "action")``; add ``"pixels"``, ``"state_estimate"``, ... as needed). The
            reward (``"reward"`` or ``("next", "reward")`` in the input) is always stored.
        rtg_scale: multiplies the relabelled return-to-go (docs/design.md).
        reward_key: the reward entry of the input trajectories (looked up at the root, then under
            ``"next"``).
        seed: seeds the window sampler's generator.
        device: device of the sampled windows (storage stays on CPU).
        transform: optional callable applied to each sampled window TensorDict after relabelling
            (e.g. ``trakdis.transforms.EncoderTransform`` or ``StateNoise``).
        early_windows: also sample windows that begin before a trajectory's first step, so the
            first ``K - 1`` steps are trained as often as the others (see :class:`WindowSampler`;
            ``False`` is the DT/ODT reference sampling).
        relabel_return_to_go: recompute ``"return_to_go"`` from the stored rewards at sampling time
            (hindsight, DT/ODT training). ``False``: store ``"return_to_go"`` with the trajectory
            (the countdown the acting policy was conditioned on) and return it unchanged; for
            distillation, where the teacher must label what the student did under the return it
            was asked for, not under the (poor) return its rollout reached.
        replacement: which stored trajectory a new one replaces once the buffer is full:
            ``"oldest"`` (Online DT: the lowest-return offline ones first, then first-in first-out)
            or ``"lowest_return"`` (the lowest-return one, offline or online, and only if the new
            one has a higher return; otherwise the new one is dropped).

    Example:
        >>> rb = TrajectoryReplayBuffer(capacity=1000, context_len=20, max_len=100, keys=("state", "action"))
        >>> rb.load_offline(data, lengths)            # data [N, 100], N may exceed the capacity
        >>> rb.add_trajectory(rollout)                # one online episode [T]
        >>> rb.add_episodes(res.episodes, keys=("state", "action"))   # run_episodes' episodes
        >>> batch = rb.sample(256)                    # [256, 20]: state, action, return_to_go, timestep, mask
    """

    def __init__(
        self,
        capacity: int,
        context_len: int,
        max_len: int,
        keys: Sequence[NestedKey] = ("state", "action"),
        rtg_scale: float = 1.0,
        reward_key: NestedKey = "reward",
        seed: int | None = None,
        device: torch.device | str | None = None,
        transform=None,
        early_windows: bool = False,
        replacement: str = "oldest",
        relabel_return_to_go: bool = True,
    ):
        if capacity < 1 or max_len < 1:
            raise ValueError(f"TrajectoryReplayBuffer: capacity ({capacity}) and max_len ({max_len}) must be >= 1")
        self.capacity = int(capacity)
        self.context_len = int(context_len)
        self.max_len = int(max_len)
        self.keys = [k for k in keys]
        if "reward" in self.keys:
            self.keys.remove("reward")
        self.relabel_return_to_go = bool(relabel_return_to_go)
        if not self.relabel_return_to_go and "return_to_go" not in self.keys:
            self.keys.append("return_to_go")
        self.reward_key = reward_key
        self.rtg_scale = float(rtg_scale)
        self.device = None if device is None else torch.device(device)
        self.transform = transform
        self.sampler = WindowSampler(self.capacity, self.context_len, seed=seed, early_windows=early_windows)
        if replacement not in ("oldest", "lowest_return"):
            raise ValueError(f"TrajectoryReplayBuffer: replacement must be 'oldest' or 'lowest_return', got {replacement!r}")
        self.replacement = replacement
        self.writer = RoundRobinWriter() if replacement == "oldest" else TopReturnWriter("reward")
        self.storage = LazyTensorStorage(self.capacity)
        self._rb = ReplayBuffer(storage=self.storage, sampler=self.sampler, writer=self.writer)
        self.returns = torch.zeros(self.capacity)
        self.online = torch.zeros(self.capacity, dtype=torch.bool)
        self.num_online_added = 0

    # ------------------------------------------------------------------ writing
    def _pack(self, data: TensorDictBase, lengths: torch.Tensor | None) -> tuple[TensorDict, torch.Tensor]:
        """[N, T] input -> padded [N, max_len] TensorDict of the stored keys, and lengths [N]."""
        if data.batch_dims != 2:
            raise ValueError(f"TrajectoryReplayBuffer: expected trajectories [N, T], got batch size {tuple(data.batch_size)}")
        N, T = data.batch_size
        if T > self.max_len:
            raise ValueError(f"TrajectoryReplayBuffer: trajectories of {T} steps exceed max_len={self.max_len}")
        if lengths is None:
            mask = data.get("mask", None)
            lengths = mask.sum(-1) if mask is not None else torch.full((N,), T)
        lengths = torch.as_tensor(lengths, dtype=torch.long).reshape(N)
        if (lengths < 1).any() or (lengths > T).any():
            raise ValueError(f"TrajectoryReplayBuffer: lengths must be in [1, {T}], got {lengths.tolist()[:10]}")
        out = {}
        for key in [*self.keys, self.reward_key]:
            val = _get(data, key)
            if val is None:
                raise KeyError(
                    f"TrajectoryReplayBuffer: key {key!r} not found in the trajectory (nor under 'next'); "
                    f"keys present: {list(data.keys(True, True))}"
                )
            out["reward" if key == self.reward_key else key] = val
        packed = TensorDict(out, batch_size=[N, T])
        reward = packed["reward"]
        if reward.shape == (N, T):
            packed["reward"] = reward = reward.unsqueeze(-1)
        if reward.shape != (N, T, 1):
            raise ValueError(f"TrajectoryReplayBuffer: reward must be [N, T, 1], got {tuple(reward.shape)}")
        valid = valid_mask(lengths, T)
        packed = packed.apply(lambda x: torch.where(valid.view(N, T, *([1] * (x.ndim - 2))), x, torch.zeros((), dtype=x.dtype)))
        if T < self.max_len:
            pad = packed[:, :1].apply(lambda x: x.new_zeros(x.shape)).expand(N, self.max_len - T).clone()
            packed = torch.cat([packed, pad], 1)
        return packed, lengths

    def _write(self, packed: TensorDict, lengths: torch.Tensor, online: bool) -> torch.Tensor:
        """Writes ``packed`` ``[N, max_len]``; returns the slot of each (-1: not kept, ``"lowest_return"``)."""
        index = self._rb.extend(packed)
        index = torch.as_tensor(index).reshape(-1)
        kept = index >= 0
        slots = index[kept]
        self.sampler.set_lengths(slots, lengths[kept])
        valid = valid_mask(lengths, self.max_len)
        returns = (packed["reward"].squeeze(-1).double() * valid).sum(-1).float()
        self.returns[slots] = returns[kept]
        self.online[slots] = online
        return index

    def load_offline(self, data: TensorDictBase, lengths: torch.Tensor | None = None) -> torch.Tensor:
        """Fills the (empty) buffer with offline trajectories ``[N, T]``.

        Keeps the ``capacity`` highest-return ones, written in ascending order of return so that the
        lowest-return ones are replaced first. ``lengths`` ``[N]`` defaults to ``data["mask"].sum(-1)``
        or ``T``. Returns the slots written.
        """
        if len(self) > 0:
            raise RuntimeError("TrajectoryReplayBuffer.load_offline: the buffer is not empty; load offline data first")
        if data.batch_dims != 2:
            raise ValueError(f"TrajectoryReplayBuffer: expected trajectories [N, T], got batch size {tuple(data.batch_size)}")
        N, T = data.batch_size
        if lengths is None:
            mask = data.get("mask", None)
            lengths = mask.sum(-1) if mask is not None else torch.full((N,), T)
        lengths = torch.as_tensor(lengths, dtype=torch.long).reshape(N)
        reward = _get(data, self.reward_key)
        if reward is None:
            raise KeyError(f"TrajectoryReplayBuffer: reward key {self.reward_key!r} not found in the offline data")
        reward = torch.as_tensor(reward).reshape(N, T).double()
        valid = valid_mask(lengths, T)
        returns = (reward * valid).sum(-1)
        # select before packing: only the kept trajectories are read (the data may be memory-mapped
        # and much larger than the buffer, e.g. 8000 episodes with pixels)
        order = torch.argsort(returns, descending=True, stable=True)[: self.capacity]
        order = order.flip(0)  # ascending return: the ring cursor meets the worst trajectories first
        packed, lengths = self._pack(data[order], lengths[order])
        return self._write(packed, lengths, online=False)

    def add_trajectory(self, trajectory: TensorDictBase, length: int | None = None) -> int:
        """Adds one online trajectory ``[T]`` (e.g. a rollout/collector batch of one episode); returns
        its slot, or -1 if a ``"lowest_return"`` buffer did not keep it."""
        if trajectory.batch_dims != 1:
            raise ValueError(
                f"TrajectoryReplayBuffer.add_trajectory: expected one trajectory [T], got batch size "
                f"{tuple(trajectory.batch_size)}; use extend() for [N, T]"
            )
        lengths = None if length is None else torch.tensor([int(length)])
        return int(self.extend(trajectory.unsqueeze(0), lengths)[0])

    def add_episodes(self, episodes: Iterable[TensorDictBase], keys: Sequence[str]) -> int:
        """Adds rollout episodes ``[T]`` (e.g. :func:`~trakdis.evaluation.run_episodes` with
        ``keep_episodes=True``) in order, each as the trajectory of its entries ``keys``
        (:func:`~trakdis.data.episode_to_trajectory`); returns how many were kept."""
        return sum(self.add_trajectory(episode_to_trajectory(ep, keys=keys)) >= 0 for ep in episodes)

    def extend(self, trajectories: TensorDictBase, lengths: torch.Tensor | None = None) -> torch.Tensor:
        """Adds online trajectories ``[N, T]`` in order; each replaces the oldest stored one (or the
        lowest-return one, see ``replacement``). Returns their slots (-1: not kept)."""
        packed, lengths = self._pack(trajectories, lengths)
        self.num_online_added += packed.shape[0]
        return self._write(packed, lengths, online=True)

    # ------------------------------------------------------------------ reading
    def __len__(self) -> int:
        return len(self.storage)

    @property
    def num_online(self) -> int:
        return int(self.online[: len(self)].sum())

    @property
    def num_offline(self) -> int:
        return len(self) - self.num_online

    @property
    def online_fraction(self) -> float:
        """Fraction of the stored trajectories that are online rollouts (0 right after loading)."""
        n = len(self)
        return self.num_online / n if n else 0.0

    @property
    def total_steps(self) -> int:
        return self.sampler.total_steps

    def sample(self, batch_size: int) -> TensorDict:
        """Windows ``[B, K]``: the stored keys, ``"return_to_go"`` ``[B, K, 1]`` (hindsight, scaled;
        the stored one with ``relabel_return_to_go=False``), ``"timestep"`` ``[B, K]`` int64,
        ``"mask"`` ``[B, K]`` bool; padded positions are zero."""
        data, info = self._rb.sample(batch_size, return_info=True)
        mask = info["mask"]
        traj = info["trajectory"]
        steps = info["index"][1]
        B, K = mask.shape
        # hindsight return-to-go from the stored rewards of the sampled trajectories: O(B * max_len)
        # (TorchRL storages have no public accessor for one field of the stored TensorDict, and
        # storage.get(traj) would also gather every other key, pixels included, for whole trajectories)
        data = data.apply(lambda x: torch.where(mask.view(B, K, *([1] * (x.ndim - 2))), x, torch.zeros((), dtype=x.dtype)))
        if self.relabel_return_to_go:
            rewards = self.storage._storage.get("reward")[traj]  # [B, max_len, 1]
            valid = valid_mask(self.sampler.lengths[traj], self.max_len)
            rtg = hindsight_return_to_go(rewards, valid, rtg_scale=self.rtg_scale)
            rtg = rtg.gather(1, steps.unsqueeze(-1))
            data.set("return_to_go", torch.where(mask.unsqueeze(-1), rtg, torch.zeros(())))
        data.set("timestep", torch.where(mask, steps, torch.zeros((), dtype=steps.dtype)))
        data.set("mask", mask)
        if self.device is not None:
            data = data.to(self.device)
        if self.transform is not None:
            data = self.transform(data)
        return data

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        return {
            "config": {
                "capacity": self.capacity,
                "context_len": self.context_len,
                "max_len": self.max_len,
                "keys": list(self.keys),
                "rtg_scale": self.rtg_scale,
                "replacement": self.replacement,
            },
            "replay_buffer": self._rb.state_dict(),
            "returns": self.returns.clone(),
            "online": self.online.clone(),
            "num_online_added": self.num_online_added,
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        cfg = state_dict["config"]
        cfg = {"replacement": "oldest", **cfg}  # checkpoints from before the option was added
        mine = {"capacity": self.capacity, "max_len": self.max_len, "keys": list(self.keys),
                "replacement": self.replacement}
        bad = {k: (cfg[k], v) for k, v in mine.items() if cfg[k] != v}
        if bad:
            raise ValueError(f"TrajectoryReplayBuffer.load_state_dict: config mismatch (saved, current): {bad}")
        self._rb.load_state_dict(state_dict["replay_buffer"])
        self.returns.copy_(state_dict["returns"])
        self.online.copy_(state_dict["online"])
        self.num_online_added = int(state_dict["num_online_added"])

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(capacity={self.capacity}, len={len(self)}, context_len={self.context_len}, "
            f"max_len={self.max_len}, keys={self.keys}, replacement={self.replacement!r}, online_fraction={self.online_fraction:.3f})"
        )
