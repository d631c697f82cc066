"""TorchRL transforms for TraKDis: image resizing, frozen-encoder state estimation, return-to-go, noise."""

from .encoder import EncoderTransform
from .image import ImageResize, resize_images
from .noise import StateNoise
from .return_to_go import ReturnToGo, hindsight_return_to_go

__all__ = [
    "EncoderTransform",
    "ImageResize",
    "ReturnToGo",
    "StateNoise",
    "hindsight_return_to_go",
    "resize_images",
]
