"""The actions a policy learns from an expert dataset: the ones executed, or the scripted expert's own.

The datasets are collected with Gaussian noise on the expert's picker movements (``--data.expert-noise``),
so that they cover states off the expert's own path. The ``"action"`` they record is the *executed*,
noisy action, and a learner fitted to it fits the noise too. The scripted expert is a function of
the recorded ``("state", "step_count")`` alone (``trakdis.envs.expert_action``), so its noise-free
action at every recorded step can be recomputed exactly: noisy execution, clean labels, as in DART
(Laskey et al., "DART: Noise Injection for Robust Imitation Learning", CoRL 2017). What it does to
the teacher is measured in docs/recipes/online_dt.md ("Clean labels").

* ``"executed"``: the recorded actions (what the env received);
* ``"expert"``: the scripted expert's noise-free action at each recorded step, in place of them.

The same recomputation labels a learner's own rollouts (:func:`expert_targets`): DAgger (Ross et al.,
"A Reduction of Imitation Learning and Structured Prediction to No-Regret Online Learning", AISTATS
2011), the expert's action at the states the learner reaches, which no demonstration visits.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Literal, Mapping

import torch
from tensordict import TensorDictBase

from trakdis.envs.experts import expert_action, expert_version
from trakdis.envs.specs import task_spec

from .dataset import DatasetError, collected_close_radius, collected_expert_version
from .layout import valid_mask

__all__ = ["ACTION_LABELS", "ActionLabels", "expert_labels", "expert_targets"]

ActionLabels = Literal["executed", "expert"]
ACTION_LABELS: tuple[str, ...] = ("executed", "expert")


def expert_labels(steps: TensorDictBase, meta: Mapping[str, Any], *, path: str | Path) -> torch.Tensor:
    """``[episodes, horizon, action_dim]``: the scripted expert's noise-free action at every recorded
    ``"state"`` and ``"step_count"`` of ``steps`` (a dataset's ``[episodes, horizon]`` steps, ``meta``
    its ``meta.json`` with ``"lengths"``); zero at the padding after each episode's end, as the
    recorded actions are.

    Raises :class:`~trakdis.data.DatasetError` (naming ``path``) for a dataset that this expert did not
    collect: a custom policy, or another version of the scripted expert (its labels would differ)."""
    if meta.get("config", {}).get("custom_policy", False):
        raise DatasetError(f"{path}: collected by a custom policy, so the scripted expert cannot relabel its actions "
                           "(use --data.action-labels executed)")
    version, current = collected_expert_version(meta), expert_version(meta["task"])
    if version != current:
        raise DatasetError(f"{path}: collected by scripted expert version {version}, this is version {current}; "
                           "its actions cannot be relabelled (recollect it, or use --data.action-labels executed)")
    missing = [k for k in ("state", "step_count", "action") if k not in steps.keys()]
    if missing:
        raise DatasetError(f"{path}: no {missing} to relabel the actions from; it has {sorted(steps.keys())}")
    recorded, state = steps.get("action"), steps.get("state")
    dim = task_spec(meta["task"]).state_dim
    if state.shape[-1] != dim:  # expert_action would index it without naming the file
        raise DatasetError(f"{path}: 'state' has {state.shape[-1]} values per step, a {meta['task']} state has {dim}")
    labels = torch.as_tensor(expert_action(meta["task"], state.numpy(), steps.get("step_count").numpy(),
                                           close_radius=collected_close_radius(meta)))
    if labels.shape != recorded.shape:
        raise DatasetError(f"{path}: the expert's actions have shape {tuple(labels.shape)}, the dataset's "
                           f"'action' {tuple(recorded.shape)}")
    valid = valid_mask(meta["lengths"], recorded.shape[1]).unsqueeze(-1)
    return torch.where(valid, labels.to(recorded.dtype), torch.zeros((), dtype=recorded.dtype))


def expert_targets(episode: TensorDictBase, task: str, *, out_key: str = "expert_action",
                   close_radius: float | None = None) -> TensorDictBase:
    """Writes into ``episode`` (a rollout ``[T]`` or ``[N, T]`` holding the env's raw ``"state"`` and
    ``"step_count"``) the scripted expert's noise-free action at every step, as ``out_key``, beside
    the executed ``"action"``, which it leaves as it is (a Decision Transformer reads its own executed
    actions in its context, and learns ``out_key``); returns ``episode``. ``close_radius``: the expert's
    (``expert_action``'s; None: the task's), as the demonstrations beside these rollouts were collected."""
    missing = [k for k in ("state", "step_count", "action") if k not in episode.keys()]
    if missing:
        raise KeyError(f"expert_targets: the episode has no {missing}; keys: {sorted(map(str, episode.keys()))}")
    action = episode.get("action")
    state, step_count = episode.get("state").cpu().numpy(), episode.get("step_count").cpu().numpy()
    labels = torch.as_tensor(expert_action(task, state, step_count, close_radius=close_radius))
    if labels.shape != action.shape:
        raise ValueError(f"expert_targets: the {task} expert's actions have shape {tuple(labels.shape)}, the episode's "
                         f"'action' {tuple(action.shape)}")
    return episode.set(out_key, labels.to(action))
