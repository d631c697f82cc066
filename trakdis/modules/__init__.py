"""Models: causal transformer, Decision Transformer actor, acting wrapper, CNN state encoder, image
baselines, and the wrappers that act on standardised values (``NormalizedPolicy``, ``NormalizedEncoder``)."""
from trakdis.modules.acting import DTActingPolicy
from trakdis.modules.baselines import BCConfig, BCHead, ImageTrunk, ImageTrunkConfig, make_bc_actor, with_image_trunk
from trakdis.modules.decision_transformer import (DTBackbone, DTModelConfig, StochasticDTActor, find_dt_actor,
                                                 make_dt_actor, recipe_hidden_action_dims)
from trakdis.modules.grasp_distribution import GraspConditionedTanhNormal, picker_of_dims
from trakdis.modules.normalized import NormalizedEncoder, NormalizedPolicy
from trakdis.modules.encoder import EncoderEnsemble, SpatialSoftArgmax, StateEncoder, coordinate_channels, to_float_chw
from trakdis.modules.transformer import CausalTransformer, KVCache, TransformerConfig
from trakdis.modules.weights import copy_teacher_weights

__all__ = [
    "BCConfig",
    "BCHead",
    "ImageTrunk",
    "ImageTrunkConfig",
    "make_bc_actor",
    "with_image_trunk",
    "CausalTransformer",
    "DTActingPolicy",
    "DTBackbone",
    "DTModelConfig",
    "recipe_hidden_action_dims",
    "KVCache",
    "NormalizedEncoder",
    "NormalizedPolicy",
    "EncoderEnsemble",
    "SpatialSoftArgmax",
    "StateEncoder",
    "StochasticDTActor",
    "TransformerConfig",
    "coordinate_channels",
    "copy_teacher_weights",
    "find_dt_actor",
    "GraspConditionedTanhNormal",
    "picker_of_dims",
    "make_dt_actor",
    "to_float_chw",
]
