"""Expert datasets for the recipes: find or collect them, load them, fill a replay buffer.

Thin glue over the dataset format and the replay buffer so that every recipe names datasets the
same way (``datasets/<task>_<episodes>ep_h<horizon>_noise<sigma>[_px<size>]``) and collects a missing one
automatically (an interrupted collection resumes when the same command runs again).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, ClassVar, Literal, NamedTuple, Optional, Sequence

import torch
from tensordict import TensorDict
from torchrl.envs.transforms import Compose, ObservationNorm

from trakdis.envs import expert_version, render_version
from trakdis.transforms import (OutOfViewFill, ProprioceptionOverride, StateNoise, fit_state_normalizer,
                                normalizer_from_state_dict, normalizer_state_dict)
from trakdis.utils.limits import cap_workers, check_options, read_json
from trakdis.utils.phases import PhaseTimer, available_workers
from trakdis.utils.run import RunState

from .buffer import TrajectoryReplayBuffer
from .dataset import (DatasetError, collect_expert_dataset, collected_close_radius, collected_expert_version,
                      load_expert_dataset, partial_path, read_meta)
from .labels import ACTION_LABELS, ActionLabels, expert_labels
from .layout import encode_trajectories, real_steps, split_episodes_train_val, valid_mask

__all__ = ["DataConfig", "EncoderDataConfig", "TrainValSteps", "default_dataset_path", "ensure_dataset", "ensure_dataset_timed",
           "load_encoded_dataset", "load_offline_data", "load_train_val_steps", "load_trajectories", "make_buffer",
           "offline_state_buffer", "StateBufferConfig", "student_buffer"]


@dataclass
class DataConfig:
    """Expert dataset (collected with the scripted expert if missing)."""

    path: Optional[str] = None
    """dataset directory (default: <root>/<task>_<episodes>ep_h<horizon>_noise<sigma>_px<size>)"""
    root: str = "datasets"
    """where default dataset directories live"""
    episodes: int = 40
    """episodes to collect when the dataset does not exist (the paper: 8000)"""
    expert_noise: float = 0.15
    """std of the Gaussian noise on the collecting expert's picker movements: diverse, sub-optimal data
    that online fine-tuning can improve on (see docs/recipes/collect.md)"""
    aim_error: float = 0.0
    """std (metres) of a horizontal misplacement of each source corner in the state the collecting expert
    reads, drawn per episode and held (ExpertPolicy's aim_error: grasps that miss, as a student's biased
    estimate makes them; 0: none). Part of the default path when > 0 (_aim<sigma>). Its recorded actions are
    the misled expert's; --data.action-labels expert recomputes those of the expert that sees the true state"""
    close_radius: Optional[float] = None
    """metres: the collecting expert closes a picker on a corner still on the table within this distance of it
    (default: the task's, trakdis.envs.experts.DEFAULT_CLOSE_RADIUS). When set, part of the default path
    (_close<r>) and recorded in the dataset; its expert labels (--data.action-labels expert, DAgger) use it too"""
    num_envs: int = field(default_factory=available_workers)
    """environments stepped together while collecting, one worker process each when > 1 (default: the
    available cores, at most 2; also the chunk size, so a dataset's episodes depend on it)"""
    seed: Optional[int] = None
    """seed of the collection when the dataset is missing. When set, part of the default path (_seed<k>), so that
    the same expert's datasets of other seeds live beside it: more episodes, never the same. Unset, a default path
    is always collected with seed 0 (the encoder's extra datasets: 1 and 2), whichever run's --seed collects it
    first, so that a run's data never depends on which run went before; a --data.path of one's own: the run's seed"""
    action_labels: ActionLabels = "executed"
    """the actions a policy learns: the recorded, noisy ones (executed), or the scripted expert's
    noise-free action at each recorded step (expert: DART's clean labels; trakdis.data.labels)"""

    def __post_init__(self):  # while parsing (tyro), before the run directory exists
        check_options(self, sizes=("episodes", "num_envs"), counts=("seed",), nonnegative=("expert_noise", "aim_error"),
                      positive=("close_radius",), prefix="data.")


def default_dataset_path(cfg: DataConfig, *, task: str, horizon: int, pixels: bool, image_size: int = 32) -> Path:
    if cfg.path:
        return Path(cfg.path)
    name = (f"{task}_{cfg.episodes}ep_h{horizon}_noise{cfg.expert_noise:g}" + (f"_aim{cfg.aim_error:g}" if cfg.aim_error else "")
            + (f"_close{cfg.close_radius:g}" if cfg.close_radius is not None else "")
            + (f"_seed{cfg.seed}" if cfg.seed is not None else "") + (f"_px{image_size}" if pixels else ""))
    return Path(cfg.root) / name


def collection_seed(cfg: DataConfig, *, seed: int, seed_offset: int = 0) -> int:
    """The seed a missing dataset of ``cfg`` is collected with: ``--data.seed`` when set; else ``seed_offset`` at a
    default path (which names no seed: the same episodes whichever run collects it first), the run's ``seed`` at a
    ``--data.path`` of one's own."""
    if cfg.seed is not None:
        return cfg.seed
    return seed if cfg.path else seed_offset


def ensure_dataset(cfg: DataConfig, *, task: str, horizon: int, seed: int, pixels: bool, image_size: int = 32,
                   log: Callable[..., None] = print, progress: bool = True, seed_offset: int = 0) -> Path:
    """The dataset directory; collected first (resuming an interrupted collection) if missing, with
    :func:`collection_seed` (``seed``: the run's; ``seed_offset``: which of a run's default datasets).

    An existing dataset must hold episodes of ``task`` with ``horizon`` steps (its ``meta.json``):
    anything else is a :class:`~trakdis.data.DatasetError` naming the path and both values. A default
    dataset collected with another seed (by an earlier trakdis) is used, and said so."""
    if horizon < 1:
        raise ValueError(f"--horizon {horizon}: the episode length must be >= 1")
    seed = collection_seed(cfg, seed=seed, seed_offset=seed_offset)
    path = default_dataset_path(cfg, task=task, horizon=horizon, pixels=pixels, image_size=image_size)
    if (path / "meta.json").exists():
        meta = read_meta(path)
        where = "--data.path" if cfg.path else "the default dataset path"
        found = meta.get("config", {}).get("seed")
        if not cfg.path and found is not None and found != seed:
            log(f"note: {path} was collected with seed {found}, not the default path's {seed} (an earlier trakdis "
                f"collected default datasets with the seed of the run that made them); using it")
        if meta["task"] != task or meta["horizon"] != horizon:
            raise DatasetError(
                f"dataset {path} ({where}) holds task {meta['task']} with horizon {meta['horizon']}, but this run "
                f"asks for --task {task} --horizon {horizon}; pass a dataset of that task and horizon (or none, "
                f"to collect one)")
        found = collected_close_radius(meta)
        if found != cfg.close_radius:  # the run's radius is the data's, which its expert labels (DAgger's) use too
            radius = lambda r: "the task's default" if r is None else f"{r:g} m"  # noqa: E731
            raise DatasetError(
                f"dataset {path} ({where}) was collected by an expert closing its grasps within {radius(found)} of "
                f"the corners, but this run asks for {radius(cfg.close_radius)} (--data.close-radius); pass the "
                f"dataset's radius")
        if not cfg.path:  # a default dataset must come from the current scripted expert
            found, version = collected_expert_version(meta), expert_version(task)
            if found != version:
                raise DatasetError(
                    f"{path} was collected with version {found} of the {task} scripted expert; this trakdis has "
                    f"version {version} (docs/tasks.md). Delete the directory to collect it again, or "
                    f"pass --data.path {path} to use it anyway")
            found = meta.get("config", {}).get("render_version", 1)
            if pixels and found != render_version(task):
                raise DatasetError(
                    f"{path} holds images of rendering version {found}; this trakdis renders {task} at version "
                    f"{render_version(task)} (docs/tasks.md), so a policy would see other "
                    f"images than it was trained on. Delete the directory to collect it again, or pass "
                    f"--data.path {path} to use it anyway")
        return path
    if path.exists():
        raise FileExistsError(f"{path} exists but holds no dataset (no meta.json); remove it or pass another path")
    verb = "resuming the collection of" if partial_path(path).exists() else "collecting"
    aim = (f", source corners misplaced by {cfg.aim_error:g} m" if cfg.aim_error else "") + \
        (f", grasps closed within {cfg.close_radius:g} m" if cfg.close_radius is not None else "")
    log(f"{verb} {cfg.episodes} expert episodes of {task} into {path} (movement noise {cfg.expert_noise:g}{aim}, "
        f"{'with' if pixels else 'without'} pixels)")
    workers = cap_workers(cfg.num_envs, cfg.episodes, what="--data.num-envs", warn=log)  # no idle worker processes
    collect_expert_dataset(path, task=task, num_episodes=cfg.episodes, num_workers=workers,
                           image_size=image_size, from_pixels=pixels, noise=cfg.expert_noise, aim_error=cfg.aim_error, seed=seed,
                           horizon=horizon, progress=progress, close_radius=cfg.close_radius)
    return path


def _episodes_done(partial: Path) -> int:
    """Episodes an interrupted collection already wrote (0 if its progress file is unreadable)."""
    try:
        return int(read_json(partial / "progress.json", within=partial)["episodes_done"])
    except (OSError, ValueError, KeyError, TypeError):
        return 0


def ensure_dataset_timed(cfg: DataConfig, *, phases: PhaseTimer, task: str, horizon: int, seed: int, pixels: bool,
                         log: Callable[..., None] = print, progress: bool = True) -> Path:
    """:func:`ensure_dataset` as the phase ``"dataset collection"`` of ``phases`` (the episodes it
    collects counted there), and a line with the collection's rate when it collected."""
    path = default_dataset_path(cfg, task=task, horizon=horizon, pixels=pixels)
    before = 0 if not partial_path(path).exists() else _episodes_done(partial_path(path))
    with phases.phase("dataset collection", workers=cfg.num_envs) as rec:
        collecting = not (path / "meta.json").exists()
        dataset = ensure_dataset(cfg, task=task, horizon=horizon, seed=seed, pixels=pixels, log=log, progress=progress)
        if collecting:
            rec["episodes"] += cfg.episodes - before
    if collecting:
        n, secs = cfg.episodes - before, rec["wall"]
        log(f"collected {n} episodes in {secs:.1f} s, {cfg.num_envs} workers: {n / max(secs, 1e-9):.2f} episodes/s, "
            f"{n * horizon / max(secs, 1e-9) / cfg.num_envs:.1f} steps/s per worker")
    return dataset


def load_trajectories(path: str | Path, keys: Sequence[str] | None = None, *,
                      action_labels: ActionLabels = "executed") -> tuple[TensorDict, torch.Tensor]:
    """``(steps [episodes, horizon], lengths [episodes])`` of a dataset (memory-mapped), optionally
    restricted to ``keys``; raises a clear error naming missing keys. ``action_labels="expert"``: the
    ``"action"`` entry holds the scripted expert's noise-free actions (:func:`~trakdis.data.expert_labels`;
    then in memory, the dataset on disk unchanged)."""
    if action_labels not in ACTION_LABELS:
        raise ValueError(f"action_labels must be one of {ACTION_LABELS}, got {action_labels!r}")
    steps, meta = load_expert_dataset(path)
    labels = None
    if action_labels == "expert" and (keys is None or "action" in keys):
        labels = expert_labels(steps, meta, path=path)
    if keys is not None:
        missing = [k for k in keys if k not in steps.keys()]
        if missing:
            hint = " (collect it with pixels: recipes/collect.py --pixels)" if "pixels" in missing else ""
            raise KeyError(f"dataset {path} has no {missing}; it has {sorted(steps.keys())}{hint}")
        steps = steps.select(*keys)
    if labels is not None:
        steps = steps.to_tensordict()
        steps.set("action", labels)
    return steps, meta["lengths"]


def load_offline_data(cfg: DataConfig, *, phases: PhaseTimer, task: str, horizon: int, seed: int,
                      keys: Sequence[str] = ("state", "action"), collect_pixels: bool = False,
                      log: Callable[..., None] = print, progress: bool = True) -> tuple[TensorDict, torch.Tensor]:
    """The expert dataset of ``cfg`` in memory: ``(steps [episodes, horizon], lengths [episodes])``
    with ``keys`` and ``"reward"``, ``"normalized_performance"``, after :func:`ensure_dataset_timed`
    (collected with images if ``collect_pixels`` or if the dataset with images exists already), and
    a line ``"offline data: <n> episodes from <path>; return <mean> (best <max>); final normalized
    performance <mean>"``."""
    pixels = collect_pixels or (default_dataset_path(cfg, task=task, horizon=horizon, pixels=True) / "meta.json").exists()
    dataset = ensure_dataset_timed(cfg, phases=phases, task=task, horizon=horizon, seed=seed, pixels=pixels, log=log,
                                   progress=progress)
    keys = list(dict.fromkeys([*keys, "reward", "normalized_performance"]))
    trajectories, lengths = load_trajectories(dataset, keys=keys, action_labels=cfg.action_labels)
    trajectories = trajectories.to_tensordict()
    rets = trajectories["reward"].sum(dim=(-2, -1))
    final = trajectories["normalized_performance"][torch.arange(len(lengths)), lengths - 1]
    log(f"offline data: {trajectories.shape[0]} episodes from {dataset}; return {rets.mean():.3f} "
        f"(best {rets.max():.3f}); final normalized performance {final.mean():.3f}")
    return trajectories, lengths


def load_encoded_dataset(cfg: DataConfig, encoder: Callable[[torch.Tensor], torch.Tensor], *, task: str, horizon: int,
                         seed: int, keys: Sequence[str], log: Callable[..., None] = print,
                         progress: bool = True) -> tuple[TensorDict, torch.Tensor, Path]:
    """``(episodes [N, horizon], lengths [N], path)``: the dataset with images of ``cfg``
    (:func:`ensure_dataset`: collected first if missing) as an image policy sees it, its images
    through ``encoder`` as ``"state_estimate"`` beside the entries ``keys``
    (:func:`~trakdis.data.encode_trajectories`)."""
    path = ensure_dataset(cfg, task=task, horizon=horizon, seed=seed, pixels=True, log=log, progress=progress)
    data, lengths = load_trajectories(path, keys=("pixels", *keys), action_labels=cfg.action_labels)
    return encode_trajectories(data, encoder, keys=keys), lengths, path


class TrainValSteps(NamedTuple):
    """The steps of :func:`load_train_val_steps`."""

    path: Path
    """the dataset directory"""
    train: TensorDict
    """training steps ``[N]``"""
    val: TensorDict | None
    """validation steps ``[M]`` (None without validation episodes)"""
    train_episodes: torch.Tensor
    """the dataset's training episodes"""
    val_episodes: torch.Tensor
    """its validation episodes"""


def load_train_val_steps(cfg: DataConfig, *, task: str, horizon: int, seed: int, keys: Sequence[str],
                         val_fraction: float, image_size: int = 32, extra_noise: Sequence[float] = (),
                         extra_aim_error: Sequence[float] = (), extra_seeds: Sequence[int] = (),
                         extra_data: Sequence[str | Path] = (),
                         log: Callable[..., None] = print, progress: bool = True) -> TrainValSteps:
    """The real steps (entries ``keys``) of the dataset with images of ``cfg`` (:func:`ensure_dataset`:
    collected first if missing), split by episode into training and validation steps
    (:func:`~trakdis.data.split_episodes_train_val` with ``val_fraction`` and ``seed``).

    ``extra_noise``: the training steps also hold all the steps of the datasets of ``cfg``'s size
    collected with these expert movement noises (default paths, collection seed 1; each found or
    collected before the split), each announced as ``"training images +<n> from <path>"``; the
    validation steps stay the main dataset's. ``extra_aim_error``: the same with datasets whose expert
    aims at source corners misplaced by these stds (:attr:`DataConfig.aim_error`; ``cfg``'s movement
    noise, collection seed 2). ``extra_seeds``: datasets like ``cfg``'s (its size and movement noise) collected
    with these seeds (:attr:`DataConfig.seed`: their own default paths), more episodes of the same expert.
    ``extra_data``: the steps of these existing datasets too (each of ``task`` and ``horizon``, with images).
    An extra dataset that is the main one, or was collected exactly as it was, is a
    :class:`~trakdis.data.DatasetError` naming it (the same episodes would count twice)."""
    path = ensure_dataset(cfg, task=task, horizon=horizon, seed=seed, pixels=True, image_size=image_size, log=log,
                          progress=progress)
    data, lengths = load_trajectories(path, keys=keys, action_labels=cfg.action_labels)
    main_config = read_meta(path).get("config", {})
    extra = []
    # the noisier and the misled experts' datasets: default paths, seeds 1 and 2 (collection_seed)
    extra_cfgs = [(dataclasses.replace(cfg, path=None, seed=None, expert_noise=float(noise)), 1)
                  for noise in extra_noise]
    extra_cfgs += [(dataclasses.replace(cfg, path=None, seed=None, aim_error=float(aim)), 2) for aim in extra_aim_error]
    extra_cfgs += [(dataclasses.replace(cfg, path=None, seed=int(k)), 0) for k in extra_seeds]
    for extra_path in map(Path, extra_data):  # never collected: a path given by hand must hold a dataset
        if not (extra_path / "meta.json").exists():
            raise DatasetError(f"extra dataset {extra_path}: no dataset there (no meta.json)")
        extra_cfgs.append((dataclasses.replace(cfg, path=str(extra_path)), 0))
    for extra_cfg, offset in extra_cfgs:
        extra_path = ensure_dataset(extra_cfg, task=task, horizon=horizon, seed=seed, seed_offset=offset, pixels=True,
                                    image_size=image_size, log=log, progress=progress)
        _check_not_the_same_episodes(path, main_config, extra_path)
        extra.append((extra_path, *load_trajectories(extra_path, keys=keys, action_labels=cfg.action_labels)))
    train_episodes, val_episodes = split_episodes_train_val(data.shape[0], val_fraction, seed=seed)
    train = real_steps(data, lengths, train_episodes)
    val = real_steps(data, lengths, val_episodes) if len(val_episodes) else None
    for extra_path, extra_data, extra_lengths in extra:
        extra_steps = real_steps(extra_data, extra_lengths)
        train = torch.cat([train, extra_steps])
        log(f"training images +{extra_steps.shape[0]} from {extra_path}")
    return TrainValSteps(path, train, val, train_episodes, val_episodes)


@dataclass
class EncoderDataConfig:
    """The steps an encoder trains and validates on, beside the main dataset's options (``--data.*``; a base of
    ``train_encoder.py``'s config dataclass, so the flags stay ``--val-fraction``, ``--extra-noise``, ...): the
    episodes held out for validation and the extra datasets whose steps join the training ones
    (:func:`load_train_val_steps`)."""

    extra_noise: tuple[float, ...] = ()
    """also train on datasets of the same size collected with these expert movement noises"""
    extra_aim_error: tuple[float, ...] = ()
    """also train on datasets of the same size whose expert aims at source corners misplaced by these stds (m):
    images of missed grasps, labelled with the true state (the main dataset's movement noise)"""
    extra_seeds: tuple[int, ...] = ()
    """also train on datasets like the main one (its size and movement noise) collected with these seeds (default
    paths ..._seed<k>...; collected if missing): more episodes of the same expert"""
    extra_data: tuple[str, ...] = ()
    """also train on these existing datasets of the task (directories with images), e.g. more expert episodes"""
    val_fraction: float = 0.1  # fraction of the episodes held out for validation

    def train_val_steps(self, data: DataConfig, *, task: str, horizon: int, seed: int, keys: Sequence[str],
                        image_size: int = 32, log: Callable[..., None] = print, progress: bool = True) -> TrainValSteps:
        """:func:`load_train_val_steps` of the dataset ``data`` with these options; the other arguments are its own."""
        return load_train_val_steps(data, task=task, horizon=horizon, seed=seed, keys=keys, val_fraction=self.val_fraction,
                                    image_size=image_size, extra_noise=self.extra_noise,
                                    extra_aim_error=self.extra_aim_error, extra_seeds=self.extra_seeds,
                                    extra_data=self.extra_data, log=log, progress=progress)


def _check_not_the_same_episodes(main: Path, main_config: dict, extra: Path) -> None:
    """A :class:`~trakdis.data.DatasetError` if the extra dataset ``extra`` is the main one, or was collected by the
    scripted expert exactly as it was (``main_config``, the main dataset's collection config: same seed, noise,
    misled aim and chunks, so the same episodes, counted twice)."""
    if Path(extra).resolve() == Path(main).resolve():
        raise DatasetError(f"extra dataset {extra} is the main dataset: its images would count twice")
    keys = ("task", "seed", "noise", "aim_error", "close_radius", "chunk_size", "split", "horizon", "custom_env",
            "custom_policy")
    a, b = main_config, read_meta(extra).get("config", {})
    if not a.get("custom_policy", True) and all(a.get(k) == b.get(k) for k in keys):
        raise DatasetError(f"extra dataset {extra} was collected as the main dataset {main} was (seed {b.get('seed')}, "
                           f"noise {b.get('noise')}): the same episodes would count twice; use another seed")


def make_buffer(capacity: int, context_len: int, max_len: int, rtg_scale: float, keys: Sequence[str],
                seed: int | None = None, transform=None, early_windows: bool = False, replacement: str = "oldest",
                relabel_return_to_go: bool = True):
    """A :class:`~trakdis.data.TrajectoryReplayBuffer` storing ``keys`` (+ ``"action"``, reward);
    ``transform`` is applied to sampled windows (e.g. a state normaliser, TorchRL's ``ObservationNorm``)."""
    keys = list(dict.fromkeys([*keys, "action"]))
    return TrajectoryReplayBuffer(capacity, context_len, max_len, keys=keys, rtg_scale=rtg_scale, seed=seed,
                                  transform=transform, early_windows=early_windows, replacement=replacement,
                                  relabel_return_to_go=relabel_return_to_go)


def offline_state_buffer(state: RunState, cfg: DataConfig, *, phases: PhaseTimer, task: str,
                         horizon: int, seed: int, context_len: int, rtg_scale: float = 1.0, min_scale: float = 1e-3,
                         state_noise: float = 0.0, state_offset: float = 0.0, fill: OutOfViewFill | None = None,
                         early_windows: bool = False, replacement: str = "oldest", collect_pixels: bool = False,
                         log: Callable[..., None] = print, progress: bool = True, target_key: str | None = None,
                         extra_capacity: int = 0) -> tuple[TrajectoryReplayBuffer, ObservationNorm | Compose]:
    """``(buffer, normalizer)``: a teacher's replay buffer of the expert dataset's states and actions,
    its sampled windows standardised by ``normalizer`` (TorchRL's ``ObservationNorm`` of ``"state"``,
    :func:`~trakdis.transforms.state_normalizer`; the acting policy's too): with ``state_noise`` > 0, Gaussian noise of that std
    (seed ``seed + 7919``) on the raw states first, and with ``state_offset`` > 0 a Gaussian offset of that std per
    window, the same at each of its steps (seed ``seed + 7927``); ``fill`` (``--mask-unseen-pickers``) carried by
    the normaliser, which masks the out-of-view pickers before standardising. The data stay raw.

    ``state`` is the run's :class:`~trakdis.utils.run.RunState`, holding the counters
    ``"normalizer"``, ``"best_return"`` and ``"buffer_capacity"`` (None: the dataset's number of
    episodes). A fresh run loads the dataset (:func:`load_offline_data`), sets the counters (the
    statistics of its real raw states, ``min_scale`` the floor of the std; its best episode return)
    and fills the buffer. A resumed run does not read the dataset: the counters are the
    checkpoint's, and the buffer, registered as the state's object ``"buffer"``, is filled by
    ``state.load()``.

    ``target_key`` (DAgger, ``--online-labels expert``): the buffer also stores that entry, the
    action a loss learns where it differs from the executed one; the demonstrations' is their
    ``"action"``. ``extra_capacity``: room for that many rollouts beside the dataset (when the
    capacity is the dataset's)."""
    if not state.resuming:
        trajectories, lengths = load_offline_data(cfg, phases=phases, task=task, horizon=horizon, seed=seed,
                                                  collect_pixels=collect_pixels, log=log, progress=progress)
        state["normalizer"] = normalizer_state_dict(fit_state_normalizer(
            trajectories["state"][valid_mask(lengths, trajectories.shape[1])], min_scale=min_scale, fill=fill))
        state["best_return"] = float(trajectories["reward"].sum(dim=(-2, -1)).max())
        if state["buffer_capacity"] is None:
            state["buffer_capacity"] = int(trajectories.shape[0]) + int(extra_capacity)
        if target_key is not None:
            trajectories.set(target_key, trajectories.get("action").clone())
    normalizer = normalizer_from_state_dict(state["normalizer"])
    noise = StateNoise(state_noise, in_keys=["state"], seed=seed + 7919) if state_noise > 0 else None
    offset = (StateNoise(state_offset, in_keys=["state"], seed=seed + 7927, shared_dims=(-2,))
              if state_offset > 0 else None)  # windows [B, K, D]: one offset per window
    keys = ("state",) if target_key is None else ("state", target_key)
    buffer = make_buffer(state["buffer_capacity"], context_len, horizon, rtg_scale, keys=keys, seed=seed,
                         transform=Compose(*(t for t in (noise, offset, normalizer) if t is not None)),
                         early_windows=early_windows, replacement=replacement)
    state.objects["buffer"] = buffer
    if not state.resuming:
        buffer.load_offline(trajectories, lengths)
    return buffer, normalizer


@dataclass
class StateBufferConfig:
    """The options of a teacher's replay buffer of standardised states (:func:`offline_state_buffer`; a base of
    ``online_dt.py``'s config dataclass, so the flags stay ``--state-scale-floor``, ``--train-state-noise``,
    ...): what the Decision Transformer reads and which trajectories the buffer keeps."""

    state_scale_floor: float = 1e-3  # lower bound (metres) of the state normaliser's per-dimension scale
    train_state_noise: float = 0.0
    """std (m) of Gaussian noise on the training windows' true states (acting: exact)"""
    train_state_offset: float = 0.0
    """std (m) of a Gaussian offset of each training window's true states, the same at all its steps: a biased
    state, as an encoder's estimate of one configuration is (acting: exact)"""
    mask_unseen_pickers: bool = False  # train and act with a picker out of the 32x32 camera view as a fixed sentinel
    rtg_scale: float = 1.0  # return-to-go scale (rewards and targets are multiplied by it)
    buffer_capacity: Optional[int] = None  # trajectories in the replay buffer (default: the dataset's; DAgger: +rollouts)
    buffer_replacement: Literal["oldest", "lowest_return"] = "lowest_return"
    """which trajectory a rollout replaces in a full buffer: the lowest-return one if it beats it, or the oldest"""
    early_windows: bool = True  # also sample windows that begin before an episode's first step (DT/ODT reference: no)
    SAVED_AS: ClassVar[dict] = {"state_noise": "train_state_noise"}  # the option's earlier name (--state-noise)

    def __post_init__(self):  # while parsing (tyro), before the run directory exists
        check_options(self, sizes=("buffer_capacity",), positive=("rtg_scale", "state_scale_floor"),
                      nonnegative=("train_state_noise", "train_state_offset"))
        parent = getattr(super(), "__post_init__", None)
        if parent is not None:
            parent()

    def state_buffer(self, state: RunState, data: DataConfig, *, phases: PhaseTimer, task: str, horizon: int,
                     seed: int, context_len: int, target_key: str | None = None, extra_capacity: int = 0,
                     collect_pixels: bool = False, log: Callable[..., None] = print,
                     progress: bool = True) -> tuple[TrajectoryReplayBuffer, ObservationNorm | Compose]:
        """:func:`offline_state_buffer` of the dataset ``data`` with these options (``--mask-unseen-pickers``:
        the task's :class:`~trakdis.transforms.OutOfViewFill`); the other arguments are its own."""
        return offline_state_buffer(
            state, data, phases=phases, task=task, horizon=horizon, seed=seed, context_len=context_len,
            rtg_scale=self.rtg_scale, min_scale=self.state_scale_floor, state_noise=self.train_state_noise,
            state_offset=self.train_state_offset, fill=OutOfViewFill.for_task(task) if self.mask_unseen_pickers else None,
            early_windows=self.early_windows, replacement=self.buffer_replacement, collect_pixels=collect_pixels, log=log,
            progress=progress, target_key=target_key, extra_capacity=extra_capacity)


def student_buffer(capacity: int, context_len: int, horizon: int, rtg_scale: float, *,
                   normalizer: ObservationNorm | Compose,
                   distill: bool = True, proprio_dims: Sequence[int] = (), state_noise: float = 0.0,
                   seed: int | None = None, early_windows: bool = False,
                   relabel_return_to_go: bool = True) -> TrajectoryReplayBuffer:
    """The student's replay buffer (``distill.py``): windows of the encoder's estimate
    ``"state_estimate"`` in state units, standardised when sampled by ``normalizer`` (the teacher's,
    of ``"state"`` and ``"state_estimate"``). With ``distill`` the windows also hold the true
    ``"state"``, which the frozen teacher reads to label them; ``proprio_dims`` (``--proprio-pickers``):
    the true state's values replace the estimate's there. ``state_noise`` > 0 (distill.py ``--estimate-noise``, the
    paper's robust student): Gaussian noise of that std on every sampled window's estimate, fresh at
    each sample, before the override and the standardisation, whatever the data (the encoded expert
    episodes or rollouts); the teacher's labels read the true state, without noise."""
    keys = ("state", "state_estimate") if distill or proprio_dims else ("state_estimate",)
    # Noise here, not in the rollout envs: distillation on the encoded expert data has no rollouts,
    # and noise added while collecting would be the same on every sample of a window.
    # The global RNG (no private generator): seeded by the run and restored on --resume with it.
    noise = StateNoise(state_noise, in_keys=["state_estimate"]) if state_noise > 0 else None
    override = ProprioceptionOverride(proprio_dims) if proprio_dims else None
    transform = Compose(*(t for t in (noise, override, normalizer) if t is not None))
    return make_buffer(capacity, context_len, horizon, rtg_scale, keys=keys, seed=seed, transform=transform,
                       early_windows=early_windows, relabel_return_to_go=relabel_return_to_go)
