"""TorchRL transforms for TraKDis: image resizing, frozen-encoder state estimation, return-to-go, noise;
out-of-view picker masking and the proprioception override; picker odometry (the encoder's picker
estimates fused with the policy's own commands); state standardisation (TorchRL's ``ObservationNorm``,
built and saved by the ``*normalizer*`` functions); image augmentation with consistent label
transforms (``random_shift``, ``random_flip``, ``horizontal_flip``, ``mirror_state``)."""

from .augment import horizontal_flip, mirror_state, random_flip, random_shift
from .encoder import EncoderTransform
from .image import ImageResize, resize_images
from .noise import StateNoise
from .odometry import PickerOdometry
from .normalization import (ProprioceptionOverride, fit_state_normalizer, normalizer_from_state_dict, normalizer_parts,
                            normalizer_state_dict, normalizer_with_keys, state_normalizer)
from .return_to_go import ReturnToGo, hindsight_return_to_go
from .visibility import OutOfViewFill, fixed_camera_matrix

__all__ = [
    "EncoderTransform",
    "ImageResize",
    "OutOfViewFill",
    "PickerOdometry",
    "ProprioceptionOverride",
    "ReturnToGo",
    "StateNoise",
    "fit_state_normalizer",
    "fixed_camera_matrix",
    "hindsight_return_to_go",
    "horizontal_flip",
    "mirror_state",
    "normalizer_from_state_dict",
    "normalizer_parts",
    "normalizer_state_dict",
    "normalizer_with_keys",
    "random_flip",
    "random_shift",
    "resize_images",
    "state_normalizer",
]
