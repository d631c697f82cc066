"""Saved policies: policy and encoder files (:mod:`.files`: what they hold, their checks, writing
and reading them) and a loaded policy with its acting environment (:mod:`.acting`:
:class:`PolicyHandle`, :func:`load_policy`, :func:`make_acting_env`)."""
from .acting import PolicyHandle, load_policy, load_teacher, make_acting_env
from .files import (
    ENCODER_KEYS,
    IMAGE_POLICY_KINDS,
    POLICY_KEYS,
    check_render_version,
    encoder_from_dict,
    load_encoder,
    read_policy_file,
    save_encoder,
    save_image_policy,
    save_policy,
)

__all__ = [
    "make_acting_env",
    "PolicyHandle",
    "load_policy",
    "load_teacher",
    "POLICY_KEYS",
    "ENCODER_KEYS",
    "IMAGE_POLICY_KINDS",
    "save_policy",
    "save_image_policy",
    "read_policy_file",
    "save_encoder",
    "load_encoder",
    "encoder_from_dict",
    "check_render_version",
]
