"""Optimisation: the training step of every recipe, its options, the optimizers and LR schedules.

* :class:`Updater`: one optimisation step of a TorchRL loss module (sum of the ``loss_*``
  entries, gradient clipping, LR warm-up and decay) returning plain floats for the CSV log;
  its state (optimiser, schedule, loss module) checkpoints and resumes.
* :class:`OptimConfig`: the optimiser options (``--optimizer``, ``--lr``, ...) as a base of a
  recipe's config dataclass, and the :class:`Updater` they make; :func:`mean_metrics` averages
  per-update metrics into one log row.
* :func:`make_optimizer`: Adam(W) from torch, or :class:`Lamb` (not in torch) for the paper preset;
  :func:`make_warmup_scheduler` (linear warm-up, optional cosine decay) and
  :func:`make_constant_scheduler`.

The TraKDis paper and Online DT train the Decision Transformer with LAMB (You et al., "Large
Batch Optimization for Deep Learning", ICLR 2020), lr 1e-4, weight decay 1e-4. torch ships no
LAMB and the ``torch_optimizer``/``timm`` versions would be extra dependencies, so a compact
implementation follows (Adam moments with bias correction, decoupled weight decay, layer-wise
trust ratio ``||w|| / ||update||`` clamped to ``[0, max_trust]``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable, Literal, Mapping, Sequence

import torch
from tensordict import TensorDictBase

from trakdis.utils.limits import check_option

__all__ = ["Lamb", "OptimConfig", "Updater", "make_constant_scheduler", "make_optimizer", "make_warmup_scheduler",
           "mean_metrics"]


class Lamb(torch.optim.Optimizer):
    def __init__(self, params: Iterable, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-6, weight_decay: float = 0.0, max_trust: float = 10.0):
        if lr <= 0:
            raise ValueError(f"Lamb: lr must be > 0, got {lr}")
        if not (0.0 <= betas[0] < 1.0 and 0.0 <= betas[1] < 1.0):
            raise ValueError(f"Lamb: betas must be in [0, 1), got {betas}")
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps, weight_decay=weight_decay, max_trust=max_trust))

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            b1, b2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                grad = p.grad
                if grad.is_sparse:
                    raise RuntimeError("Lamb does not support sparse gradients")
                state = self.state[p]
                if not state:
                    state["step"] = 0
                    state["exp_avg"] = torch.zeros_like(p)
                    state["exp_avg_sq"] = torch.zeros_like(p)
                state["step"] += 1
                m, v = state["exp_avg"], state["exp_avg_sq"]
                m.mul_(b1).add_(grad, alpha=1 - b1)
                v.mul_(b2).addcmul_(grad, grad, value=1 - b2)
                m_hat = m / (1 - b1 ** state["step"])
                v_hat = v / (1 - b2 ** state["step"])
                update = m_hat / (v_hat.sqrt() + group["eps"])
                if group["weight_decay"]:
                    update = update.add(p, alpha=group["weight_decay"])
                w_norm, u_norm = p.norm(), update.norm()
                trust = torch.where(
                    (w_norm > 0) & (u_norm > 0), (w_norm / u_norm).clamp(max=group["max_trust"]), torch.ones_like(w_norm)
                )
                p.add_(update * trust, alpha=-group["lr"])
        return loss


def make_optimizer(name: str, params, *, lr: float, weight_decay: float = 0.0) -> torch.optim.Optimizer:
    """``"adamw"``, ``"adam"`` or ``"lamb"``."""
    params = list(params)
    if name == "adamw":
        return torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay)
    if name == "adam":
        return torch.optim.Adam(params, lr=lr, weight_decay=weight_decay)
    if name == "lamb":
        return Lamb(params, lr=lr, weight_decay=weight_decay)
    raise ValueError(f"unknown optimizer {name!r}; use 'adamw', 'adam' or 'lamb'")


def make_warmup_scheduler(optimizer: torch.optim.Optimizer, warmup_steps: int, decay_steps: int = 0,
                          min_fraction: float = 1.0) -> torch.optim.lr_scheduler.LambdaLR:
    """Linear warm-up from ~0 to the optimizer's lr over ``warmup_steps`` updates, then constant (as
    in ODT); with ``decay_steps > warmup_steps``, a cosine decay from the lr to ``min_fraction`` of it
    at update ``decay_steps``, constant afterwards."""
    warmup = max(1, int(warmup_steps))
    decay = int(decay_steps)
    if not 0.0 < min_fraction <= 1.0:
        raise ValueError(f"min_fraction must be in (0, 1], got {min_fraction}")

    def factor(step: int) -> float:
        if step + 1 < warmup:
            return (step + 1) / warmup
        if decay <= warmup or min_fraction == 1.0:
            return 1.0
        progress = min(1.0, (step + 1 - warmup) / (decay - warmup))
        return min_fraction + (1.0 - min_fraction) * 0.5 * (1.0 + math.cos(math.pi * progress))

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


def make_constant_scheduler(optimizer: torch.optim.Optimizer) -> torch.optim.lr_scheduler.LambdaLR:
    """The optimizer's lr, unchanged (e.g. the online phase after a decayed offline phase)."""
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 1.0)


class Updater:
    """Optimise ``loss_module``: ``step(batch)`` -> ``{"loss_nll": ..., "entropy": ..., "lr": ...}``.

    Every ``loss_*`` entry of the loss output is summed and back-propagated; other scalar
    entries are reported as metrics. ``params`` defaults to the loss module's parameters (for a
    :class:`~trakdis.objectives.DTDistillationLoss` these are the student's only).
    """

    def __init__(self, loss_module: torch.nn.Module, *, optimizer: str = "adamw", lr: float = 1e-3,
                 weight_decay: float = 1e-4, warmup_steps: int = 100, grad_clip: float | None = 0.25,
                 params: Iterable[torch.nn.Parameter] | None = None, decay_steps: int = 0, min_lr_fraction: float = 1.0):
        self.loss_module = loss_module
        self.params = [p for p in (params if params is not None else loss_module.parameters()) if p.requires_grad]
        if not self.params:
            raise ValueError(f"Updater: {type(loss_module).__name__} has no trainable parameters")
        if grad_clip is not None and not (math.isfinite(grad_clip) and grad_clip > 0):
            # clip_grad_norm_ scales by max_norm / norm: a negative bound reverses the gradient
            raise ValueError(f"Updater: grad_clip must be > 0 (None: no clipping), got {grad_clip!r}")
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

    def __post_init__(self):  # while parsing (tyro), before the run directory exists
        check_option("lr", self.lr, gt=0)
        check_option("weight_decay", self.weight_decay, ge=0)
        check_option("warmup_steps", self.warmup_steps, ge=0, integer=True)
        check_option("grad_clip", self.grad_clip, ge=0)  # a negative bound would reverse the gradient
        parent = getattr(super(), "__post_init__", None)
        if parent is not None:
            parent()

    def make_updater(self, loss_module: torch.nn.Module, **kwargs: Any) -> "Updater":
        """An :class:`Updater` of ``loss_module`` with these options (``kwargs``: the other arguments)."""
        return Updater(loss_module, optimizer=self.optimizer, lr=self.lr, weight_decay=self.weight_decay,
                       warmup_steps=self.warmup_steps, grad_clip=self.grad_clip or None, **kwargs)


def mean_metrics(history: Sequence[Mapping[str, float]], prefix: str = "train/") -> dict[str, float]:
    """Average a list of per-update metric dicts into ``{prefix + key: mean}``."""
    keys = {k for h in history for k in h}
    return {prefix + k: sum(h[k] for h in history if k in h) / sum(1 for h in history if k in h) for k in sorted(keys)}
