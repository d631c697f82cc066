"""A policy distribution for pick-and-place actions: each grasp command a Bernoulli, each picker's
movement a tanh-Gaussian conditioned on that picker's grasp decision.

A factorised ``TanhNormal`` over all action dims treats a binary grasp command as one more
continuous dimension. Where the policy is unsure whether to close, its mean action averages the
two behaviours: on the diagonal folds the expert's closing step is also a saturated lift, so an
unsure teacher lifts with the gripper still open and closes centimetres above the corner
(docs/recipes/online_dt.md, "Why a diagonal-fold teacher collapses"). Here the grasp is decided
first and the movement comes from the branch of that decision, so an open gripper gets the
open-gripper movement whatever the probability of closing.
"""
from __future__ import annotations

import bisect
import math

import torch
import torch.nn.functional as F
from torch import distributions as D

__all__ = ["GraspConditionedTanhNormal", "picker_of_dims", "normal_log_prob", "tanh_log_det"]

_LOG_2 = math.log(2.0)
_LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))


def normal_log_prob(x, loc, scale, log_scale):
    """Elementwise log-density of a Normal: ``torch.distributions.Normal.log_prob``, op for op (same rounding)."""
    return -((x - loc) ** 2) / (2 * scale**2) - log_scale - _LOG_SQRT_2PI


def tanh_log_det(x):
    """Elementwise ``log |d tanh(x) / dx|`` = ``2 (log 2 - x - softplus(-2x))``, stable for large ``|x|``
    (``torch.distributions.TanhTransform.log_abs_det_jacobian``)."""
    return 2.0 * (_LOG_2 - x - F.softplus(-2.0 * x))


def _tanh_normal_log_prob_per_dim(x, loc, scale):
    """Elementwise log-density of ``tanh(Normal(loc, scale))`` at ``tanh(x)``, from the pre-tanh ``x``."""
    return normal_log_prob(x, loc, scale, scale.log()) - tanh_log_det(x)


def picker_of_dims(action_dim: int, grasp_dims: tuple[int, ...]) -> tuple[int, ...]:
    """For each action dim, the index of the grasp command (picker) that conditions it: the dims up to
    and including ``grasp_dims[0]`` belong to picker 0, those after it up to ``grasp_dims[1]`` to
    picker 1, and so on (dims after the last grasp dim to the last picker). ``grasp_dims`` must be
    increasing and inside ``[0, action_dim)``."""
    dims = tuple(int(d) for d in grasp_dims)
    if not dims or any(b <= a for a, b in zip(dims, dims[1:])) or dims[0] < 0 or dims[-1] >= action_dim:
        raise ValueError(f"grasp_dims={grasp_dims} must be increasing, distinct action dims in [0, {action_dim})")
    return tuple(min(bisect.bisect_left(dims, d), len(dims) - 1) for d in range(action_dim))


class GraspConditionedTanhNormal(D.Distribution):
    r"""Grasp commands as Bernoullis; each picker's movement a tanh-Gaussian of its grasp decision's branch.

    Parameters (``*B`` any batch shape, ``A`` action dims, ``P`` grasp dims):

    * ``loc``, ``scale``: ``[*B, 2, A]``, the pre-tanh Gaussian of every dim under an open (branch 0)
      and a closed (branch 1) grasp of its picker; the entries of the grasp dims themselves are unused.
    * ``grasp_logits``: ``[*B, P]``, the log-odds that each picker closes (``pick > 0``).

    An action's grasp dims are ``+1`` (close) or ``-1`` (open); a value is read as closed where it is
    ``> 0``, so the expert's labels and clamped targets score as their sign. ``log_prob(a)`` is
    ``sum_p log Bern(g_p) + sum_{d not grasp} log TanhNormal(a_d; loc[g_{p(d)}, d], scale[g_{p(d)}, d])``.
    ``deterministic_sample`` closes where the logit is > 0 and takes ``tanh(loc)`` of the decided branch;
    ``sample`` draws the grasps, then the movement of their branches. No reparameterised sample
    exists (the grasp is discrete): :meth:`entropy_estimate` gives the entropy, exact for the
    Bernoullis and with reparameterised samples for the movement, weighted by the grasp probabilities
    so that it is differentiable in every parameter.

    Args:
        loc, scale, grasp_logits: as above.
        grasp_dims: the action dims of the grasp commands, increasing.
        low, high: accepted for the interface of TorchRL's ``TanhNormal``; must be -1 and 1.
    """

    arg_constraints: dict = {}
    has_rsample = False

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor, grasp_logits: torch.Tensor, *,
                 grasp_dims: tuple[int, ...], low: float = -1.0, high: float = 1.0):
        if float(low) != -1.0 or float(high) != 1.0:
            raise ValueError(f"GraspConditionedTanhNormal acts on [-1, 1]; got low={low}, high={high}")
        if loc.dim() < 2 or loc.shape[-2] != 2 or scale.shape != loc.shape:
            raise ValueError(f"loc and scale must be [*B, 2, A] (open and closed branches); got loc "
                             f"{tuple(loc.shape)}, scale {tuple(scale.shape)}")
        action_dim = loc.shape[-1]
        self.grasp_dims = tuple(int(d) for d in grasp_dims)
        picker = picker_of_dims(action_dim, self.grasp_dims)
        if grasp_logits.shape != (*loc.shape[:-2], len(self.grasp_dims)):
            raise ValueError(f"grasp_logits must be {(*loc.shape[:-2], len(self.grasp_dims))}; got {tuple(grasp_logits.shape)}")
        self.loc, self.scale, self.grasp_logits = loc, scale, grasp_logits
        device = loc.device
        self._picker = torch.tensor(picker, device=device)
        move = torch.ones(action_dim, dtype=torch.bool, device=device)  # the dims that are not grasp commands
        move[list(self.grasp_dims)] = False
        self.movement_mask = move
        self._grasp_index = torch.tensor(self.grasp_dims, device=device)
        super().__init__(batch_shape=loc.shape[:-2], event_shape=loc.shape[-1:], validate_args=False)

    # -- helpers -------------------------------------------------------------------------------
    def closed(self, value: torch.Tensor) -> torch.Tensor:
        """The grasp decisions ``[*B, P]`` (bool) an action ``[*, A]`` carries."""
        return value.index_select(-1, self._grasp_index) > 0

    def branch(self, closed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(loc, scale)`` ``[*S, *B, A]`` of the branches that the grasp decisions ``closed`` ``[*S, *B, P]`` select."""
        lead = torch.broadcast_shapes(closed.shape[:-1], self.loc.shape[:-2])  # sample dims in front
        idx = closed.long().index_select(-1, self._picker)  # each dim's picker's decision
        idx = idx.expand(*lead, idx.shape[-1]).unsqueeze(-2)
        loc, scale = (t.expand(*lead, *t.shape[-2:]) for t in (self.loc, self.scale))
        return loc.gather(-2, idx).squeeze(-2), scale.gather(-2, idx).squeeze(-2)

    def _action(self, closed: torch.Tensor, movement: torch.Tensor) -> torch.Tensor:
        grasp = closed.to(movement.dtype) * 2.0 - 1.0
        lead = torch.broadcast_shapes(grasp.shape[:-1], movement.shape[:-1])
        movement = movement.expand(*lead, movement.shape[-1])
        return movement.index_copy(-1, self._grasp_index, grasp.expand(*lead, grasp.shape[-1]))

    # -- the Distribution interface -----------------------------------------------------------
    @property
    def support(self):
        return D.constraints.independent(D.constraints.interval(-1.0, 1.0), 1)

    def action_for(self, closed: torch.Tensor) -> torch.Tensor:
        """The deterministic action ``[*B, A]`` of the grasp decisions ``closed`` ``[*B, P]``: the commands
        ``+-1`` and ``tanh(loc)`` of their branches."""
        loc, _ = self.branch(closed)
        return self._action(closed, torch.tanh(loc))

    @property
    def deterministic_sample(self) -> torch.Tensor:
        """Each grasp by its more likely value (logit > 0), the movement of its branch. Acting step by
        step, :class:`~trakdis.modules.DTActingPolicy` decides the grasp from the whole episode instead
        (the median of the switch time)."""
        return self.action_for(self.grasp_logits > 0)

    @property
    def mode(self) -> torch.Tensor:
        return self.deterministic_sample

    def sample(self, sample_shape=torch.Size()) -> torch.Tensor:
        shape = torch.Size(sample_shape)
        with torch.no_grad():
            logits = self.grasp_logits.expand(*shape, *self.grasp_logits.shape)
            closed = torch.bernoulli(torch.sigmoid(logits)).bool()
            loc, scale = self.branch(closed)
            movement = torch.tanh(loc + scale * torch.randn_like(loc))
            return self._action(closed, movement)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        closed = self.closed(value)
        log_grasp = -F.binary_cross_entropy_with_logits(
            self.grasp_logits.expand_as(closed), closed.to(self.grasp_logits.dtype), reduction="none").sum(-1)
        loc, scale = self.branch(closed)
        eps = torch.finfo(value.dtype).resolution
        x = value.clamp(-(1.0 - eps), 1.0 - eps).atanh()
        per_dim = _tanh_normal_log_prob_per_dim(x, loc, scale)
        return log_grasp + (per_dim * self.movement_mask.to(per_dim.dtype)).sum(-1)

    def grasp_entropy(self) -> torch.Tensor:
        """Entropy ``[*B]`` of the grasp commands (exact)."""
        p = torch.sigmoid(self.grasp_logits)
        return F.binary_cross_entropy_with_logits(self.grasp_logits, p, reduction="none").sum(-1)

    def entropy_estimate(self, n: int = 1) -> torch.Tensor:
        """Entropy ``[*B]``: the grasps' exactly, plus each picker's movement entropy in both branches
        (``n`` reparameterised samples each, as Online DT estimates a ``TanhNormal``'s), weighted by
        the probability of each branch."""
        eps = torch.randn((n, *self.loc.shape), dtype=self.loc.dtype, device=self.loc.device)
        x = self.loc + eps * self.scale  # [n, *B, 2, A]
        log_p = (-(eps**2) / 2 - self.scale.log() - _LOG_SQRT_2PI) - tanh_log_det(x)  # the Normal's at loc + eps scale
        per_dim = -log_p.mean(0) * self.movement_mask.to(log_p.dtype)  # [*B, 2, A]
        p_closed = self._p_closed_per_dim()
        movement = ((1 - p_closed) * per_dim[..., 0, :] + p_closed * per_dim[..., 1, :]).sum(-1)
        return self.grasp_entropy() + movement

    def _p_closed_per_dim(self) -> torch.Tensor:
        """``[*B, A]``: for each dim, the probability that its picker closes."""
        return torch.sigmoid(self.grasp_logits).index_select(-1, self._picker)

    def branch_probs(self) -> torch.Tensor:
        """``[*B, 2, A]``: for each dim, the probability of its picker's open (0) and closed (1) branch."""
        p_closed = self._p_closed_per_dim()
        return torch.stack((1 - p_closed, p_closed), dim=-2)

    def soft_imitation_loss(self, teacher: "GraspConditionedTanhNormal", *, loss_function: str = "nll",
                            eps: float = 1e-6) -> torch.Tensor:
        """``[*B]``: this policy imitating ``teacher``'s grasp probabilities and both of its movement branches.

        The grasps: the cross-entropy of the teacher's Bernoullis (binary cross-entropy on its probabilities, not
        on its more likely grasp), minimal where this policy's probabilities equal the teacher's. The movement:
        in each branch, ``loss_function="nll"`` this policy's negative log-density of the teacher's deterministic
        movement of that branch (clamped to ``[-1 + eps, 1 - eps]``), ``"mse"`` the squared error of the two
        deterministic movements; each branch weighted by the teacher's probability of it. Where the teacher is
        sure of a grasp (probability 0 or 1) this is the loss of its deterministic action, term for term.
        """
        if teacher.loc.shape != self.loc.shape or teacher.grasp_dims != self.grasp_dims:
            raise ValueError(f"teacher loc {tuple(teacher.loc.shape)}, grasp_dims {teacher.grasp_dims} do not match "
                             f"this policy's {tuple(self.loc.shape)}, {self.grasp_dims}")
        grasp = F.binary_cross_entropy_with_logits(self.grasp_logits, torch.sigmoid(teacher.grasp_logits),
                                                   reduction="none").sum(-1)
        target = torch.tanh(teacher.loc)
        if loss_function == "nll":
            x = target.clamp(-1.0 + eps, 1.0 - eps).atanh()
            per_dim = -_tanh_normal_log_prob_per_dim(x, self.loc, self.scale)
        elif loss_function == "mse":
            per_dim = (torch.tanh(self.loc) - target).pow(2)
        else:
            raise ValueError(f"loss_function={loss_function!r}; expected 'nll' or 'mse'")
        weighted = teacher.branch_probs() * per_dim * self.movement_mask.to(per_dim.dtype)
        return grasp + weighted.sum((-2, -1))

    def movement_given(self, value: torch.Tensor) -> torch.Tensor:
        """The deterministic movement ``tanh(loc)`` ``[*B, A]`` in the branches of ``value``'s grasps
        (grasp dims hold ``value``'s commands): the action this policy takes if it grasps as ``value``
        does, for a squared-error imitation of the movement."""
        return self.action_for(self.closed(value))
