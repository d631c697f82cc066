"""Losses (TorchRL ``LossModule``s); the encoder's image augmentation is in :mod:`trakdis.transforms.augment`."""
import warnings

from trakdis.objectives.bc_loss import BehaviourCloningLoss
from trakdis.objectives.distillation import DTDistillationLoss
from trakdis.objectives.dt_loss import MaskedOnlineDTLoss, masked_mean
from trakdis.objectives.encoder_loss import EncoderLoss

__all__ = [
    "BehaviourCloningLoss",
    "DTDistillationLoss",
    "EncoderLoss",
    "MaskedOnlineDTLoss",
    "masked_mean",
]


def __getattr__(name: str):
    # The former name, kept for one release: torchrl.objectives.llm.DistillationLoss is TorchRL's LLM distillation
    # loss, a different thing, so this library's loss is DTDistillationLoss.
    if name == "DistillationLoss":
        warnings.warn("trakdis.objectives.DistillationLoss was renamed DTDistillationLoss (torchrl.objectives.llm."
                      "DistillationLoss is TorchRL's LLM distillation loss); the old name will be removed",
                      FutureWarning, stacklevel=2)
        return DTDistillationLoss
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
