"""Policy distillation loss: the student DT imitates the frozen privileged teacher DT."""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from trakdis.objectives.dt_loss import clamp_action, get_mask, masked_mean

__all__ = ["DTDistillationLoss"]

_KL_DIRECTIONS = ("teacher_student", "student_teacher")
_LOSS_FUNCTIONS = ("nll", "mse")
_TEACHER_CONTEXTS = ("window", "step")
_GRASP_LABELS = ("probability", "decision")


class DTDistillationLoss(LossModule):
    r"""TraKDis distillation: student NLL of the frozen teacher's actions on the same windows.

    The teacher reads its own observation key (the privileged ``"state"``), the student its own
    (``"state_estimate"`` from the encoder); both read the same ``"action"``,
    ``"return_to_go"``, ``"timestep"`` and ``"mask"`` of the window.

    * ``loss_function="nll"`` (the paper's cross-entropy): ``loss_distill = masked_mean(-log pi_S(a_T))``
      with ``a_T = tanh(loc_T)``, the teacher's deterministic action, computed under ``no_grad``
      (clamped to ``[-1 + eps, 1 - eps]``).
    * ``loss_function="mse"``: ``loss_distill = masked_mean(sum_i (tanh(loc_S) - a_T)_i^2)``, the
      squared error of the deterministic actions (DAgger's behaviour cloning). The NLL measures a
      difference of pre-tanh means in units of the student's standard deviation, so where both
      policies saturate (a grasp command at +-1, the same action) a pre-tanh gap still costs
      ``gap^2 / (2 sigma^2)`` and dominates the loss and its gradient; the squared error in action
      space costs what changes the action (docs/recipes/distill.md has the measurement).
    * ``loss_kl`` (only if ``kl_coef > 0``) = ``kl_coef`` x masked mean per-step KL, either
      ``"teacher_student"``: ``KL(pi_T || pi_S)`` (mode covering) or ``"student_teacher"``:
      ``KL(pi_S || pi_T)`` (mode seeking). Both policies are ``tanh`` of diagonal Gaussians and
      KL is invariant under that shared bijection, so the KL is computed exactly, in closed form,
      on the pre-tanh Gaussians (a sample-based estimate through ``atanh`` is noisy and
      numerically poor where tanh saturates). The teacher side is a constant.
    * ``teacher_context="window"``: the teacher reads the whole window, the acting policy's action
      history included; ``"step"``: the teacher labels every step from that step's tokens alone
      (return-to-go, state, timestep), as at the first step of a window that starts mid-episode,
      which DT training samples. With student-driven rollouts (DAgger) the window's actions are
      the student's, and a teacher conditioned on them labels a history it would not have
      produced; ``"step"`` removes that dependence (docs/recipes/distill.md).
    * ``loss_expert`` (only if ``expert_coef > 0``) = ``expert_coef`` x the student's masked mean NLL of the
      window's own ``"action"`` (clamped like the teacher's): on the expert's episodes, the demonstrated
      action beside the teacher's, as knowledge distillation mixes the hard labels with the teacher's
      (Hinton et al., 2015). Only meaningful where the window's actions are the expert's.
    * with a grasp head (:class:`~trakdis.modules.GraspConditionedTanhNormal`): ``"nll"`` scores the teacher's
      action under the student (its grasps as Bernoulli labels, the movement in the teacher's grasp branches);
      ``"mse"`` is the movement's squared error in the teacher's branches plus the grasps' cross-entropy;
      ``kl_coef > 0`` is refused. ``grasp_labels="probability"``: the grasp labels are the teacher's
      probabilities and the movement is imitated in both branches, each weighted by the teacher's probability of
      it (:meth:`~trakdis.modules.GraspConditionedTanhNormal.soft_imitation_loss`), so that the student keeps
      the probabilities that :class:`~trakdis.modules.DTActingPolicy`'s switch-time rule acts on;
      ``"decision"``: each step's more likely grasp (``deterministic_sample``) and the movement of its branch.
    * metric ``teacher_student_mse``: masked mean squared difference of the deterministic actions.

    The teacher is evaluated in eval mode (no dropout) whatever its ``training`` flag, so its
    targets are deterministic. No gradient reaches the teacher (its parameters are held as detached buffers, not
    parameters of this module) nor the encoder (the student's inputs are detached).

    Args:
        student_actor, teacher_actor: actors from :func:`~trakdis.modules.make_dt_actor`.

    Keyword Args:
        kl_coef: weight of ``loss_kl`` (0 disables it).
        kl_direction: ``"teacher_student"`` or ``"student_teacher"``.
        loss_function: ``"nll"`` or ``"mse"`` (see above).
        action_eps: clamp of the teacher's actions away from +-1.
        teacher_context: ``"window"`` or ``"step"`` (see above).
        expert_coef: weight of ``loss_expert`` (0 disables it; see above).
        grasp_labels: ``"probability"`` or ``"decision"``, with a grasp head (see above).
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys.

        Attributes:
            mask: bool ``[B, K]`` padding mask (True = real step). Defaults to ``"mask"``.
            action: the window's actions, the targets of ``loss_expert``. Defaults to ``"action"``.
        """

        mask: NestedKey = "mask"
        action: NestedKey = "action"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    student_network: TensorDictModule
    student_network_params: TensorDictParams
    target_student_network_params: TensorDictParams

    def __init__(
        self,
        student_actor: ProbabilisticTensorDictSequential,
        teacher_actor: ProbabilisticTensorDictSequential,
        *,
        kl_coef: float = 0.0,
        kl_direction: str = "teacher_student",
        loss_function: str = "nll",
        action_eps: float = 1e-6,
        teacher_context: str = "window",
        expert_coef: float = 0.0,
        grasp_labels: str = "probability",
    ) -> None:
        super().__init__()
        if teacher_context not in _TEACHER_CONTEXTS:
            raise ValueError(f"teacher_context={teacher_context!r}; expected one of {_TEACHER_CONTEXTS}")
        if loss_function not in _LOSS_FUNCTIONS:
            raise ValueError(f"loss_function={loss_function!r}; expected one of {_LOSS_FUNCTIONS}")
        if grasp_labels not in _GRASP_LABELS:
            raise ValueError(f"grasp_labels={grasp_labels!r}; expected one of {_GRASP_LABELS}")
        if kl_direction not in _KL_DIRECTIONS:
            raise ValueError(f"kl_direction={kl_direction!r}; expected one of {_KL_DIRECTIONS}")
        if kl_coef < 0:
            raise ValueError(f"kl_coef={kl_coef} must be >= 0")
        if not expert_coef >= 0:  # also NaN
            raise ValueError(f"expert_coef={expert_coef} must be >= 0")
        if student_actor is teacher_actor:
            raise ValueError("student_actor and teacher_actor must be distinct modules (copy the weights instead)")
        self.convert_to_functional(student_actor, "student_network", create_target_params=False)
        # The teacher is frozen: keep its weights as detached buffers (so they are not in
        # self.parameters() and no optimizer built from this loss can touch them), and keep the
        # module itself out of the registered submodules, like convert_to_functional does.
        self.teacher_network_params = TensorDictParams(TensorDict.from_module(teacher_actor, as_module=True).data, no_convert=True)
        self.__dict__["teacher_network"] = teacher_actor
        self.kl_coef = float(kl_coef)
        self.kl_direction = kl_direction
        self.loss_function = loss_function
        self.action_eps = float(action_eps)
        self.teacher_context = teacher_context
        self.expert_coef = float(expert_coef)
        self.grasp_labels = grasp_labels

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self):
        keys = set(self.student_network.in_keys) | set(self.teacher_network.in_keys) | {self.tensor_keys.mask}
        if self.expert_coef > 0:
            keys.add(self.tensor_keys.action)
        return sorted(keys, key=str)

    @property
    def out_keys(self):
        return (["loss_distill"] + (["loss_kl"] if self.kl_coef > 0 else [])
                + (["loss_expert"] if self.expert_coef > 0 else []) + ["teacher_student_mse"])

    def teacher_dist(self, tensordict: TensorDictBase):
        """The teacher's per-step distribution, always computed in eval mode (no dropout).

        Returns ``(action, loc, scale, grasp_logits)``: the deterministic action and the pre-tanh
        Gaussian's parameters, each ``[*B, K, action_dim]``, and ``None``; with a grasp head
        ``loc``/``scale`` are ``[*B, K, 2, action_dim]`` (the open and closed branches) and
        ``grasp_logits`` ``[*B, K, P]``.
        """
        teacher = self.teacher_network
        td = tensordict.copy()
        if self.teacher_context == "step":
            # [*B, K] -> [*B, K, 1]: every step is a window of length one. Padded steps become
            # real one-step windows (finite zeros); their labels are masked out of the loss.
            td = td.unsqueeze(-1)
            td.set(self.tensor_keys.mask, torch.ones(td.shape, dtype=torch.bool, device=td.device))
        was_training = teacher.training
        teacher.eval()
        try:
            with self.teacher_network_params.to_module(teacher):
                dist = teacher.get_dist(td)
        finally:
            teacher.train(was_training)
        if hasattr(dist, "root_dist"):
            out = (dist.deterministic_sample, dist.root_dist.loc, dist.root_dist.scale, None)
        else:  # the grasp head (GraspConditionedTanhNormal): its branches' parameters
            out = (dist.deterministic_sample, dist.loc, dist.scale, dist.grasp_logits)
        if self.teacher_context == "step":
            out = tuple(None if x is None else x.squeeze(len(td.batch_size) - 1) for x in out)
        return out

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        student_td = tensordict.select(*self.student_network.in_keys, strict=True).detach()
        with self.student_network_params.to_module(self.student_network):
            s_dist = self.student_network.get_dist(student_td)
        with torch.no_grad():
            t_action, t_loc, t_scale, t_logits = self.teacher_dist(tensordict)
        s_action = s_dist.deterministic_sample
        grasp_head = hasattr(s_dist, "movement_given")
        if grasp_head and self.grasp_labels == "probability":
            teacher = type(s_dist)(t_loc, t_scale, t_logits, grasp_dims=s_dist.grasp_dims)
            per_step = s_dist.soft_imitation_loss(teacher, loss_function=self.loss_function, eps=self.action_eps)
        elif self.loss_function == "nll":
            per_step = -s_dist.log_prob(clamp_action(t_action, self.action_eps))
        elif grasp_head:  # movement in the teacher's grasp branches, plus the grasps' cross-entropy
            per_step = ((s_dist.movement_given(t_action) - t_action).pow(2) * s_dist.movement_mask).sum(-1) + \
                F.binary_cross_entropy_with_logits(s_dist.grasp_logits, s_dist.closed(t_action).to(t_action.dtype),
                                                   reduction="none").sum(-1)
        else:
            per_step = (s_action - t_action).pow(2).sum(-1)
        mask = get_mask(tensordict, self.tensor_keys.mask, per_step, "DTDistillationLoss")
        out = {"loss_distill": masked_mean(per_step, mask)}
        if self.kl_coef > 0 and grasp_head:
            raise ValueError("DTDistillationLoss: kl_coef > 0 needs TanhNormal actors; the grasp head's KL is not implemented")
        if self.kl_coef > 0:
            # KL is invariant under a bijection applied to both distributions, and both are the
            # same tanh of a diagonal Gaussian: the KL of the TanhNormals is exactly the
            # closed-form KL of the pre-tanh Gaussians (no sampling noise, no atanh round trip).
            t_base = torch.distributions.Normal(t_loc, t_scale)
            s_base = torch.distributions.Normal(s_dist.root_dist.loc, s_dist.root_dist.scale)
            if self.kl_direction == "teacher_student":
                kl = torch.distributions.kl_divergence(t_base, s_base).sum(-1)
            else:
                kl = torch.distributions.kl_divergence(s_base, t_base).sum(-1)
            out["loss_kl"] = self.kl_coef * masked_mean(kl, mask)
        if self.expert_coef > 0:
            target = clamp_action(tensordict.get(self.tensor_keys.action), self.action_eps)
            out["loss_expert"] = self.expert_coef * masked_mean(-s_dist.log_prob(target), mask)
        with torch.no_grad():
            out["teacher_student_mse"] = masked_mean((s_action.detach() - t_action).pow(2).mean(-1), mask)
        return TensorDict(out, batch_size=[])
