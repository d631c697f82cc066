"""Training-loop pieces shared by ``online_dt.py`` and ``distill.py``.

* :class:`ModelConfig`: the command-line section ``--model.*`` that becomes a
  :class:`~trakdis.modules.DTConfig` once the task's state/action sizes are known.
* :class:`Updater`: one optimisation step of a TorchRL loss module (sum of the ``loss_*``
  entries, gradient clipping, LR warm-up) returning plain floats for the CSV log.
* :func:`episode_to_trajectory`: a rollout episode (``env.rollout`` layout, ``("next", ...)``
  entries) in the on-disk dataset layout of docs/design.md, ready for the replay buffer.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable, Literal, Mapping, Sequence

import torch
from tensordict import TensorDict, TensorDictBase

from .optim import make_constant_scheduler, make_optimizer, make_warmup_scheduler

__all__ = ["ModelConfig", "OptimConfig", "Updater", "episode_to_trajectory", "mean_metrics"]


@dataclass
class ModelConfig:
    """Decision Transformer sizes (the defaults train on a laptop CPU; --preset paper: 256/10/16/30)."""

    embed_dim: int = 64
    """token embedding width"""
    n_layer: int = 2
    """transformer blocks"""
    n_head: int = 2
    """attention heads"""
    context_len: int = 20
    """K: steps per training window and acting context"""
    dropout: float = 0.0
    """dropout (embeddings, residuals and attention); the DT reference and --preset paper use 0.1.
    Measured on ClothFold (40 demonstrations, the small default model, 40 eval episodes): the
    offline teacher scored 0.01 with 0.1 and 0.37 with 0 (the actions must be precise)"""

    loc_bound: float = 5.0
    """soft bound of the policy's pre-tanh mean (TorchRL's TanhNormal upscale; 0: unbounded, as Online
    DT); the losses clamp target actions to match (DTConfig.loc_bound). Without it, online fine-tuning
    on ClothFold fed the policy's own saturated grasp commands back with NLLs of ~1e4"""

    log_std_min: float = -2.5
    """lower bound of the policy's log-std (Online DT: -5). A grasp command is binary: its std falls to
    the bound, and once the policy's mean moves, the NLL of its own earlier actions (online data)
    grows like (shift / std)^2. Measured on ClothFold with -5: update-mean NLLs of 800-2000 in the
    online phase (the gradients of a few steps dominated every clipped update)"""

    def dt_config(self, state_dim: int, action_dim: int, horizon: int):
        from trakdis.modules import DTConfig

        return DTConfig(state_dim=state_dim, action_dim=action_dim, embed_dim=self.embed_dim, n_layer=self.n_layer,
                        n_head=self.n_head, context_len=self.context_len, dropout=self.dropout,
                        attn_dropout=self.dropout, max_timestep=max(1024, horizon + 1), loc_bound=self.loc_bound,
                        log_std_min=self.log_std_min)


class Updater:
    """Optimise ``loss_module``: ``step(batch)`` -> ``{"loss_nll": ..., "entropy": ..., "lr": ...}``.

    Every ``loss_*`` entry of the loss output is summed and back-propagated; other scalar
    entries are reported as metrics. ``params`` defaults to the loss module's parameters (for a
    :class:`~trakdis.objectives.DistillationLoss` these are the student's only).
    """

    def __init__(self, loss_module: torch.nn.Module, *, optimizer: str = "adamw", lr: float = 1e-3,
                 weight_decay: float = 1e-4, warmup_steps: int = 100, grad_clip: float | None = 0.25,
                 params: Iterable[torch.nn.Parameter] | None = None, decay_steps: int = 0, min_lr_fraction: float = 1.0):
        self.loss_module = loss_module
        self.params = [p for p in (params if params is not None else loss_module.parameters()) if p.requires_grad]
        if not self.params:
            raise ValueError(f"Updater: {type(loss_module).__name__} has no trainable parameters")
        self.optimizer = make_optimizer(optimizer, self.params, lr=lr, weight_decay=weight_decay)
        self.scheduler = make_warmup_scheduler(self.optimizer, warmup_steps, decay_steps, min_lr_fraction)
        self.grad_clip = grad_clip
        self.updates = 0

    def step(self, batch: TensorDictBase) -> dict[str, float]:
        self.loss_module.train()
        out = self.loss_module(batch)
        losses = [v for k, v in out.items() if isinstance(k, str) and k.startswith("loss_")]
        if not losses:
            raise KeyError(f"{type(self.loss_module).__name__} returned no loss_* entry; got {list(out.keys())}")
        total = sum(losses)
        if not torch.isfinite(total):
            raise FloatingPointError(f"non-finite loss at update {self.updates}: "
                                     + ", ".join(f"{k}={float(v.detach()):.4g}" for k, v in out.items()))
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        metrics = {k: float(v.detach()) for k, v in out.items() if isinstance(k, str) and v.numel() == 1}
        if self.grad_clip:
            metrics["grad_norm"] = float(torch.nn.utils.clip_grad_norm_(self.params, self.grad_clip))
        self.optimizer.step()
        self.scheduler.step()
        self.updates += 1
        metrics["lr"] = self.optimizer.param_groups[0]["lr"]
        return metrics

    def set_constant_lr(self, lr: float) -> None:
        """From now on train with the constant learning rate ``lr`` (e.g. for the online phase)."""
        for group in self.optimizer.param_groups:
            group["lr"] = lr
            group["initial_lr"] = lr
        self.scheduler = make_constant_scheduler(self.optimizer)

    def state_dict(self) -> dict[str, Any]:
        return {"optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(),
                "loss_module": self.loss_module.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.loss_module.load_state_dict(state["loss_module"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.updates = int(state["updates"])


@dataclass
class OptimConfig:
    """Optimiser options of a recipe that trains with an :class:`Updater` (a base of its config
    dataclass, so the flags stay ``--lr``, ``--warmup-steps``, ...; a recipe redeclares a field to
    change its default)."""

    optimizer: Literal["adamw", "adam", "lamb"] = "adamw"
    """optimiser (the paper: lamb)"""
    lr: float = 1e-3
    """learning rate"""
    weight_decay: float = 1e-4
    """weight decay"""
    warmup_steps: int = 100
    """linear learning-rate warm-up (updates)"""
    grad_clip: float = 0.25
    """gradient-norm clip (0: off)"""

    def make_updater(self, loss_module: torch.nn.Module, **kwargs: Any) -> "Updater":
        """An :class:`Updater` of ``loss_module`` with these options (``kwargs``: the other arguments)."""
        return Updater(loss_module, optimizer=self.optimizer, lr=self.lr, weight_decay=self.weight_decay,
                       warmup_steps=self.warmup_steps, grad_clip=self.grad_clip or None, **kwargs)


def mean_metrics(history: Sequence[Mapping[str, float]], prefix: str = "train/") -> dict[str, float]:
    """Average a list of per-update metric dicts into ``{prefix + key: mean}``."""
    keys = {k for h in history for k in h}
    return {prefix + k: sum(h[k] for h in history if k in h) / sum(1 for h in history if k in h) for k in sorted(keys)}


_STEP_KEYS = ("state", "pixels", "state_estimate", "action", "step_count", "return_to_go")
_NEXT_KEYS = ("reward", "normalized_performance", "done", "terminated", "truncated", "sim_unstable")


def episode_to_trajectory(episode: TensorDictBase, keys: Sequence[str] = _STEP_KEYS) -> TensorDict:
    """Flatten one rollout episode ``[T]`` into the dataset layout (``reward`` = reward after ``action``).

    Step entries (``state``, ``action``, ``step_count`` and, when present, ``pixels`` /
    ``state_estimate``) are taken as they are; ``reward``, ``normalized_performance`` and the
    done flags come from ``("next", ...)``.
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
    nxt = episode.get("next")
    for k in _NEXT_KEYS:
        if k in nxt.keys():
            out.set(k, nxt.get(k))
    if "reward" not in out.keys():
        raise KeyError("episode_to_trajectory: the episode has no ('next', 'reward')")
    return out

