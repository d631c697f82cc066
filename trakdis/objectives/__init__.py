"""Losses (TorchRL ``LossModule``s) and encoder image augmentation."""
from trakdis.objectives.augment import horizontal_flip, mirror_state, random_flip, random_shift
from trakdis.objectives.bc_loss import BehaviourCloningLoss
from trakdis.objectives.distillation import DistillationLoss
from trakdis.objectives.dt_loss import MaskedOnlineDTLoss, masked_mean
from trakdis.objectives.encoder_loss import EncoderLoss

__all__ = [
    "BehaviourCloningLoss",
    "DistillationLoss",
    "EncoderLoss",
    "MaskedOnlineDTLoss",
    "horizontal_flip",
    "masked_mean",
    "mirror_state",
    "random_flip",
    "random_shift",
]
