"""Losses (TorchRL ``LossModule``s); the encoder's image augmentation is in :mod:`trakdis.transforms.augment`."""
from trakdis.objectives.bc_loss import BehaviourCloningLoss
from trakdis.objectives.distillation import DistillationLoss
from trakdis.objectives.dt_loss import MaskedOnlineDTLoss, masked_mean
from trakdis.objectives.encoder_loss import EncoderLoss

__all__ = [
    "BehaviourCloningLoss",
    "DistillationLoss",
    "EncoderLoss",
    "MaskedOnlineDTLoss",
    "masked_mean",
]
