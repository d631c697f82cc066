"""Initialising the student from the teacher (TraKDis: the student starts as a copy of the teacher)."""
from __future__ import annotations

import torch
from torch import nn

__all__ = ["copy_teacher_weights"]


def copy_teacher_weights(student: nn.Module, teacher: nn.Module) -> nn.Module:
    """Copy every parameter and buffer of ``teacher`` into ``student`` (in place) and return ``student``.

    Both must have the same architecture (same ``state_dict`` names and shapes); modules that only
    differ in their tensordict keys (e.g. the observation key ``"state"`` vs ``"state_estimate"``)
    are compatible. On any mismatch nothing is copied and a ``ValueError`` lists the missing,
    unexpected and mis-shaped entries.
    """
    s_sd, t_sd = student.state_dict(), teacher.state_dict()
    missing = sorted(set(t_sd) - set(s_sd))
    unexpected = sorted(set(s_sd) - set(t_sd))
    shapes = sorted(
        f"{k}: student {tuple(s_sd[k].shape)} vs teacher {tuple(t_sd[k].shape)}"
        for k in set(s_sd) & set(t_sd)
        if s_sd[k].shape != t_sd[k].shape
    )
    if missing or unexpected or shapes:
        lines = ["copy_teacher_weights: student and teacher architectures differ"]
        if missing:
            lines.append(f"  only in teacher: {missing}")
        if unexpected:
            lines.append(f"  only in student: {unexpected}")
        if shapes:
            lines.append("  shape mismatch: " + "; ".join(shapes))
        raise ValueError("\n".join(lines))
    with torch.no_grad():
        for k, v in s_sd.items():
            v.copy_(t_sd[k])
    return student
