"""Optimizers for the recipes: Adam(W) from torch, and LAMB (not in torch) for the paper preset.

The TraKDis paper and Online DT train the Decision Transformer with LAMB (You et al., "Large
Batch Optimization for Deep Learning", ICLR 2020), lr 1e-4, weight decay 1e-4. torch ships no
LAMB and the ``torch_optimizer``/``timm`` versions would be extra dependencies, so a compact
implementation follows (Adam moments with bias correction, decoupled weight decay, layer-wise
trust ratio ``||w|| / ||update||`` clamped to ``[0, max_trust]``).
"""
from __future__ import annotations

import math
from typing import Iterable

import torch

__all__ = ["Lamb", "make_constant_scheduler", "make_optimizer", "make_warmup_scheduler"]


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
