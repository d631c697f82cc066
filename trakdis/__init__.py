"""trakdis: TorchRL/TensorDict components for transformer-based knowledge distillation in visual RL.

Subpackages: ``envs`` (MuJoCo cloth tasks), ``modules`` (Decision Transformer, encoder),
``objectives`` (losses), ``transforms``, ``data`` (datasets, replay buffer), ``utils``.
"""

__version__ = "0.1.0"
