"""Decision Transformer (Chen et al. 2021) with the Online DT actor head (Zheng et al. 2022).

Tokens are interleaved per step as ``(R_t, s_t, a_t)`` (return-to-go, state, action), each
embedded by its own linear layer plus a learned timestep embedding; the action at ``t`` is
predicted from the output at the state token ``s_t``, so it sees ``R_<=t, s_<=t, a_<t``.

Unlike TorchRL's ``DecisionTransformer`` (HuggingFace GPT-2), this one has a timestep embedding,
handles left-padded windows with a padding mask, and supports cached incremental decoding
(:class:`~trakdis.modules.DTActingPolicy`).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import ClassVar, Optional

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import ProbabilisticActor, TanhNormal

from trakdis.envs.specs import task_spec
from trakdis.envs.task_defaults import task_defaults
from trakdis.modules.grasp_distribution import GraspConditionedTanhNormal, picker_of_dims
from trakdis.modules.transformer import CausalTransformer, KVCache, TransformerConfig

__all__ = ["DTModelConfig", "DTBackbone", "StochasticDTActor", "make_dt_actor", "find_dt_actor",
           "recipe_hidden_action_dims"]

TOKENS_PER_STEP = 3  # (return-to-go, state, action)


@dataclass
class DTModelConfig:
    """A Decision Transformer's sizes and action head: the one definition of them, also the
    recipes' ``--model.*`` section (each field's docstring is its ``--help`` text).

    The defaults are the recipes' small model, which trains on a CPU; :meth:`paper` gives the
    paper's sizes. ``state_dim``/``action_dim`` depend on the task: a recipe leaves them unset
    and fills them in with :meth:`for_task` once the environment is known. Unbounded means
    (``loc_bound=0``) and ``log_std_min=-5`` are Online DT's choices; why the defaults differ:
    docs/recipes/online_dt.md.

    Not TorchRL's ``DecisionTransformer.DTConfig`` (the GPT-2 sizes of its ``DTActor`` and
    ``OnlineDTActor``): this one also holds the action head's bounds and the hidden action dims.
    """

    state_dim: Optional[int] = None
    """observation (reduced state) width (the recipes fill it in from the task)"""
    action_dim: Optional[int] = None
    """action width (the recipes fill it in from the task)"""
    embed_dim: int = 64
    """token embedding width"""
    n_layer: int = 2
    """transformer blocks"""
    n_head: int = 2
    """attention heads"""
    context_len: int = 20
    """K: steps per training window and acting context"""
    max_timestep: int = 1024
    """size of the timestep embedding table (timesteps must be < this; the recipes make it at least horizon + 1)"""
    dropout: float = 0.0
    """dropout (embeddings, residuals and, unless --model.attn-dropout, attention); the DT reference
    and --preset paper use 0.1, which cost the small offline teacher most of its score (docs/recipes/online_dt.md)"""
    attn_dropout: Optional[float] = None
    """dropout on the attention weights (None: the same as --model.dropout)"""
    mlp_ratio: int = 4
    """hidden width of each block's MLP, as a multiple of embed_dim"""
    activation: str = "gelu"
    """MLP activation: gelu, gelu_tanh or relu"""
    log_std_min: float = -2.5
    """lower bound of the policy's log-std (Online DT: -5; a binary grasp command's std falls to the
    bound, and a tiny std makes the NLL of the policy's own earlier actions explode online)"""
    log_std_max: float = 2.0
    """upper bound of the policy's log-std"""
    init_log_std: float = 0.0
    """the policy's log-std at initialisation, for every input"""
    loc_bound: float = 5.0
    """soft bound of the policy's pre-tanh mean, loc_bound * tanh(x / loc_bound) (TorchRL's TanhNormal
    upscale; 0: unbounded, as Online DT). The losses clamp target actions at +-tanh(loc_bound) to match
    (action_eps), so the policy's own mean actions, written back as online targets, map back to the same
    pre-tanh value (docs/recipes/online_dt.md)"""

    hidden_action_dims: Optional[tuple[int, ...]] = None
    """action dims left out of the action tokens (zeroed before embedding): the DT does not read them in
    its own past actions (None: the recipes' default, the grasp commands on ClothFold, where a DT that reads
    them learns to repeat them and seldom starts a grasp itself, and none on the diagonal folds, where
    hiding them lowered the student; a DT built directly hides none; empty: none; docs/recipes/online_dt.md)"""

    grasp_head: bool = False
    """model each grasp command as a Bernoulli and each picker's movement as a tanh-Gaussian conditioned on its
    grasp decision (GraspConditionedTanhNormal), instead of one tanh-Gaussian per action dim, which averages
    the closing lift into an unsure open gripper's movement (docs/recipes/online_dt.md)"""
    grasp_dims: Optional[tuple[int, ...]] = None
    """the action dims of the grasp head's commands (None: the task's pick commands, filled in by the recipes;
    read only with --model.grasp-head)"""

    PAPER_SIZES: ClassVar[dict] = {"embed_dim": 256, "n_layer": 10, "n_head": 16, "context_len": 30, "dropout": 0.1}
    """The TraKDis paper's sizes (:meth:`paper`, the recipes' ``--preset paper``)."""

    def __post_init__(self) -> None:
        for name in ("state_dim", "action_dim", "context_len", "max_timestep"):
            value = getattr(self, name)
            if value is not None and int(value) < 1:
                raise ValueError(f"DTModelConfig.{name}={value} must be >= 1")
        if not self.log_std_min < self.log_std_max:
            raise ValueError(f"log_std_min={self.log_std_min} must be < log_std_max={self.log_std_max}")
        if not self.log_std_min < self.init_log_std < self.log_std_max:
            raise ValueError(f"init_log_std={self.init_log_std} must lie strictly inside ({self.log_std_min}, {self.log_std_max})")
        if self.loc_bound < 0:
            raise ValueError(f"loc_bound={self.loc_bound} must be >= 0 (0: unbounded)")
        if self.hidden_action_dims is not None:
            self.hidden_action_dims = tuple(int(d) for d in self.hidden_action_dims)
            bad = [d for d in self.hidden_action_dims if d < 0 or (self.action_dim is not None and d >= self.action_dim)]
            if bad or len(set(self.hidden_action_dims)) != len(self.hidden_action_dims):
                raise ValueError(f"DTModelConfig.hidden_action_dims={self.hidden_action_dims} must be distinct action "
                                 f"dims in [0, action_dim={self.action_dim})")
        if self.grasp_dims is not None:
            self.grasp_dims = tuple(int(d) for d in self.grasp_dims)
            if self.action_dim is not None:
                picker_of_dims(self.action_dim, self.grasp_dims)  # raises on bad dims
        if self.grasp_head and self.grasp_dims is None and self.action_dim is not None and self.state_dim is not None:
            raise ValueError("DTModelConfig.grasp_head needs grasp_dims (the recipes fill them in from the task)")
        if self.grasp_head and self.grasp_dims and set(self.grasp_dims) & set(self.hidden_action_dims or ()):
            raise ValueError(f"DTModelConfig.grasp_head with grasp_dims {self.grasp_dims} hidden from the action tokens "
                             f"(hidden_action_dims {self.hidden_action_dims}): the grasp head decides a switch from its "
                             f"own past grasps, so it must read them (--model.hidden-action-dims with no value shows them)")
        self.transformer_config()  # validates embed_dim/n_head/activation/dropouts

    @property
    def action_eps(self) -> float:
        """The clamp of target actions that matches :attr:`loc_bound` (``1 - tanh(loc_bound)``;
        ``1e-6`` when unbounded): pass it as ``MaskedOnlineDTLoss(action_eps=...)``."""
        return 1.0 - math.tanh(self.loc_bound) if self.loc_bound > 0 else 1e-6

    @classmethod
    def paper(cls, state_dim: int, action_dim: int, **overrides) -> "DTModelConfig":
        """TraKDis paper sizes (:attr:`PAPER_SIZES`): embedding 256, 10 layers, 16 heads, context 30, dropout 0.1."""
        kwargs = dict(cls.PAPER_SIZES)
        kwargs.update(overrides)
        return cls(state_dim=state_dim, action_dim=action_dim, **kwargs)

    def for_task(self, state_dim: int, action_dim: int, horizon: int,
                 hidden_action_dims: tuple[int, ...] = (), grasp_dims: tuple[int, ...] = ()) -> "DTModelConfig":
        """A copy (``dataclasses.replace``) for a task: its observation and action widths, a
        timestep table of at least ``horizon + 1`` entries, the attention dropout written out,
        ``hidden_action_dims`` unless this config sets its own (the recipes pass
        :func:`recipe_hidden_action_dims`), and with :attr:`grasp_head` the task's ``grasp_dims``
        (``TaskSpec.grasp_dims``) unless this config sets its own."""
        grasp = (tuple(grasp_dims) if self.grasp_dims is None else self.grasp_dims) if self.grasp_head else None
        return dataclasses.replace(
            self, state_dim=state_dim, action_dim=action_dim, max_timestep=max(self.max_timestep, horizon + 1),
            attn_dropout=self.dropout if self.attn_dropout is None else self.attn_dropout,
            hidden_action_dims=tuple(hidden_action_dims) if self.hidden_action_dims is None else self.hidden_action_dims,
            grasp_dims=grasp)

    def transformer_config(self) -> TransformerConfig:
        return TransformerConfig(
            embed_dim=self.embed_dim,
            n_layer=self.n_layer,
            n_head=self.n_head,
            dropout=self.dropout,
            attn_dropout=self.dropout if self.attn_dropout is None else self.attn_dropout,
            mlp_ratio=self.mlp_ratio,
            activation=self.activation,
        )

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def recipe_hidden_action_dims(task: str) -> tuple[int, ...]:
    """The recipes' default ``DTModelConfig.hidden_action_dims`` for ``task``: its grasp commands
    (``TaskSpec.grasp_dims``) where its ``TaskDefaults.hidden_grasp`` says so (trakdis.envs.task_defaults),
    else none."""
    return task_spec(task).grasp_dims if task_defaults(task).hidden_grasp else ()


class DTBackbone(nn.Module):
    """Decision Transformer trunk: returns the hidden state at each state token.

    Named apart from TorchRL's ``DecisionTransformer`` (a HuggingFace GPT-2 trunk without timestep
    embedding, padding mask or cache), which it does not replace one-for-one.

    ``forward(observation [B, K, S], action [B, K, A], return_to_go [B, K, 1], timestep [B, K]
    int64, mask [B, K] bool or None) -> [B, K, embed_dim]``. Extra leading batch dims are
    flattened and restored. Padded steps (``mask == False``) are zeroed before embedding and
    masked out of attention, so their content never changes the outputs at real steps.
    Floating-point inputs of another dtype (e.g. float64 states) are cast to the model's dtype;
    an empty batch or window, or a non-floating observation/action/return, is a clear error.
    """

    def __init__(self, config: DTModelConfig):
        super().__init__()
        if config.state_dim is None or config.action_dim is None:
            raise ValueError(f"DTModelConfig.state_dim={config.state_dim} and action_dim={config.action_dim} must be set "
                             "to build a model (DTModelConfig.for_task)")
        self.config = config
        d = config.embed_dim
        self.embed_return = nn.Linear(1, d)
        self.embed_state = nn.Linear(config.state_dim, d)
        self.embed_action = nn.Linear(config.action_dim, d)
        self.embed_timestep = nn.Embedding(config.max_timestep, d)
        self.embed_ln = nn.LayerNorm(d)
        self.embed_drop = nn.Dropout(config.dropout)
        self.transformer = CausalTransformer(config.transformer_config())
        for lin in (self.embed_return, self.embed_state, self.embed_action):
            nn.init.normal_(lin.weight, std=0.02)
            nn.init.zeros_(lin.bias)
        nn.init.normal_(self.embed_timestep.weight, std=0.02)
        hidden = list(config.hidden_action_dims or ())
        keep = torch.ones(config.action_dim)
        keep[hidden] = 0.0
        # derived from the config, so not saved with the weights
        self.register_buffer("action_token_keep", keep if hidden else None, persistent=False)

    def embed_past_action(self, action: torch.Tensor) -> torch.Tensor:
        """The action token's embedding, without ``DTModelConfig.hidden_action_dims`` (zeroed)."""
        if self.action_token_keep is not None:
            action = action * self.action_token_keep
        return self.embed_action(action)

    # -- input checks ---------------------------------------------------------------------
    def _check(self, observation, action, return_to_go, timestep, mask) -> None:
        c = self.config
        lead = observation.shape[:-1]
        expected = {
            "observation": (observation, (*lead, c.state_dim)),
            "action": (action, (*lead, c.action_dim)),
            "return_to_go": (return_to_go, (*lead, 1)),
            "timestep": (timestep, tuple(lead)),
        }
        if mask is not None:
            expected["mask"] = (mask, tuple(lead))
        for name, (tensor, shape) in expected.items():
            if tuple(tensor.shape) != tuple(shape):
                raise ValueError(
                    f"DTBackbone: {name!r} has shape {tuple(tensor.shape)}, expected {tuple(shape)} "
                    f"(state_dim={c.state_dim}, action_dim={c.action_dim})"
                )
        if 0 in tuple(lead):
            raise ValueError(
                f"DTBackbone: empty input: 'observation' has shape {tuple(observation.shape)}; at least one "
                f"window of at least one step is needed")
        for name in ("observation", "action", "return_to_go"):
            if not expected[name][0].dtype.is_floating_point:
                raise TypeError(f"DTBackbone: {name!r} must be a floating-point tensor, got {expected[name][0].dtype}")
        if timestep.dtype.is_floating_point:
            raise TypeError(f"DTBackbone: 'timestep' must be an integer tensor, got {timestep.dtype}")
        if mask is not None and mask.dtype != torch.bool:
            raise TypeError(f"DTBackbone: 'mask' must be bool, got {mask.dtype}")

    def _check_timestep(self, timestep: torch.Tensor) -> None:
        # One host sync; worth it, since an out-of-range index would otherwise fail deep in
        # the embedding (or silently on some devices).
        if timestep.numel() == 0:
            return
        lo, hi = (int(v) for v in torch.aminmax(timestep))
        if hi >= self.config.max_timestep or lo < 0:
            raise ValueError(
                f"DTBackbone: 'timestep' values must lie in [0, {self.config.max_timestep - 1}] "
                f"(DTModelConfig.max_timestep), got [{int(timestep.min())}, {int(timestep.max())}]"
            )

    def embed_step(self, observation, action, return_to_go, timestep) -> torch.Tensor:
        """Embed steps ``[..., *]`` to tokens ``[..., 3, D]`` ordered (R, s, a), before the LayerNorm."""
        t = self.embed_timestep(timestep)
        tokens = torch.stack((self.embed_return(return_to_go), self.embed_state(observation), self.embed_past_action(action)),
                             dim=-2)
        return tokens + t.unsqueeze(-2)  # one broadcast add (and one reduction backward) for the 3 tokens

    def forward(
        self,
        observation: torch.Tensor,
        action: torch.Tensor,
        return_to_go: torch.Tensor,
        timestep: torch.Tensor,
        mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        self._check(observation, action, return_to_go, timestep, mask)
        dtype = self.embed_state.weight.dtype  # e.g. float64 data into a float32 model
        observation, action, return_to_go = observation.to(dtype), action.to(dtype), return_to_go.to(dtype)
        lead = observation.shape[:-2]
        k = observation.shape[-2]
        observation = observation.reshape(-1, k, observation.shape[-1])
        action = action.reshape(-1, k, action.shape[-1])
        return_to_go = return_to_go.reshape(-1, k, 1)
        timestep = timestep.reshape(-1, k)
        b = observation.shape[0]
        if mask is not None:
            mask = mask.reshape(b, k)
            if bool(mask.all()):  # fast path: plain causal attention (fused SDPA kernels)
                mask = None
            else:
                valid = mask.unsqueeze(-1)
                # zero padded inputs: NaN/inf padding cannot leak through 0-weight attention
                observation = torch.where(valid, observation, 0.0)
                action = torch.where(valid, action, 0.0)
                return_to_go = torch.where(valid, return_to_go, 0.0)
                timestep = torch.where(mask, timestep, 0)
        self._check_timestep(timestep)
        tokens = self.embed_step(observation, action, return_to_go, timestep.long())  # [B, K, 3, D]
        # the last action token is dropped: no state token comes after it, so (causal attention)
        # no output the actor returns depends on it; 1/(3K) less work in every layer
        n_tok = TOKENS_PER_STEP * k - 1
        tokens = self.embed_drop(self.embed_ln(tokens.reshape(b, TOKENS_PER_STEP * k, -1)[:, :n_tok]))
        token_mask = None if mask is None else mask.repeat_interleave(TOKENS_PER_STEP, dim=-1)[:, :n_tok]
        h = self.transformer(tokens, token_mask, output_positions=slice(1, None, TOKENS_PER_STEP))  # state tokens
        return h.reshape(*lead, k, h.shape[-1])

    def forward_cached(
        self, tokens_in: torch.Tensor, cache: KVCache, slots: torch.Tensor, attn_mask: torch.Tensor
    ) -> torch.Tensor:
        """Run pre-embedded (not yet normalised) new tokens ``[B, T_new, D]`` against a cache."""
        return self.transformer.forward_cached(self.embed_drop(self.embed_ln(tokens_in)), cache, slots, attn_mask)


class StochasticDTActor(nn.Module):
    """Decision Transformer with the Online DT Gaussian head: returns ``(loc, scale)``.

    The counterpart of TorchRL's ``OnlineDTActor`` on :class:`DTBackbone` (it also reads
    ``timestep`` and ``mask``); named apart from TorchRL's ``DTActor``, which returns deterministic
    actions.

    ``scale = exp(log_std)`` with ``log_std = min + (max - min) * (tanh(x) + 1) / 2`` in
    ``[log_std_min, log_std_max]`` (Online DT). Unlike Online DT/TorchRL (orthogonal init of the
    log-std layer, so the initial std is anywhere in ``[e^-5, e^2]`` depending on the input), the
    log-std layer starts with zero weights and a bias giving ``log_std = init_log_std``: with the
    orthogonal init, steps whose initial std is ~e^-5 produce NLLs of ~1e4 whose gradients slam
    other dims into the saturated top of the tanh, where training stalls. The tanh squashing of actions to [-1, 1] is done
    by the ``TanhNormal`` distribution of the :class:`ProbabilisticActor` that wraps this module (with
    ``grasp_head``: :class:`~trakdis.modules.GraspConditionedTanhNormal`, fed two branches and the grasp logits).
    """

    def __init__(self, config: DTModelConfig):
        super().__init__()
        if config.grasp_head and not config.grasp_dims:
            raise ValueError("DTModelConfig.grasp_head needs grasp_dims")
        self.config = config
        self.transformer = DTBackbone(config)
        branches = 2 if config.grasp_head else 1  # open and closed grasp (GraspConditionedTanhNormal)
        self.head_loc = nn.Linear(config.embed_dim, branches * config.action_dim)
        self.head_log_std = nn.Linear(config.embed_dim, branches * config.action_dim)
        nn.init.orthogonal_(self.head_loc.weight)
        nn.init.zeros_(self.head_loc.bias)
        nn.init.zeros_(self.head_log_std.weight)
        frac = (config.init_log_std - config.log_std_min) / (config.log_std_max - config.log_std_min)
        nn.init.constant_(self.head_log_std.bias, math.atanh(2.0 * frac - 1.0))
        if config.grasp_head:
            self.head_grasp = nn.Linear(config.embed_dim, len(config.grasp_dims))
            nn.init.zeros_(self.head_grasp.weight)
            nn.init.zeros_(self.head_grasp.bias)

    @property
    def dist_keys(self) -> tuple[str, ...]:
        """The names of :meth:`head`'s outputs, the parameters of the actor's distribution."""
        return ("loc", "scale", "grasp_logits") if self.config.grasp_head else ("loc", "scale")

    def head(self, h: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``(loc, scale)`` ``[*, action_dim]``; with ``grasp_head``, ``(loc, scale, grasp_logits)`` with
        ``loc``/``scale`` ``[*, 2, action_dim]`` (open, closed branch) and ``grasp_logits`` ``[*, grasp dims]``."""
        c = self.config
        log_std = torch.tanh(self.head_log_std(h))
        log_std = c.log_std_min + 0.5 * (c.log_std_max - c.log_std_min) * (log_std + 1.0)
        loc = self.head_loc(h)
        if c.loc_bound > 0:
            loc = c.loc_bound * torch.tanh(loc / c.loc_bound)
        if not c.grasp_head:
            return loc, log_std.exp()
        branches = (*h.shape[:-1], 2, c.action_dim)
        return loc.reshape(branches), log_std.exp().reshape(branches), self.head_grasp(h)

    def forward(self, observation, action, return_to_go, timestep, mask=None):
        return self.head(self.transformer(observation, action, return_to_go, timestep, mask))


def make_dt_actor(
    config: DTModelConfig, observation_key="observation", *, device: torch.device | str | None = None
) -> ProbabilisticActor:
    """Build a TorchRL ``ProbabilisticActor`` around a :class:`StochasticDTActor`.

    The actor reads ``[observation_key, "action", "return_to_go", "timestep", "mask"]`` over
    ``[B, K]`` windows, writes ``"loc"``/``"scale"`` and an ``"action"`` drawn from
    ``TanhNormal(loc, scale, low=-1, high=1)`` (with ``config.grasp_head``: also ``"grasp_logits"``, and
    :class:`~trakdis.modules.GraspConditionedTanhNormal`) according to the current ``ExplorationType``
    (deterministic: ``tanh(loc)``; random: a sample). ``actor.get_dist(td)`` gives the per-step
    distribution (log-prob shape ``[B, K]``) for the losses; it is also accepted by
    ``torchrl.objectives.OnlineDTLoss``.

    Note that calling the actor overwrites ``"action"``: use ``get_dist`` on training windows.
    """
    net = StochasticDTActor(config)
    if device is not None:
        net = net.to(device)
    keys = list(net.dist_keys)
    module = TensorDictModule(net, in_keys=[observation_key, "action", "return_to_go", "timestep", "mask"], out_keys=keys)
    spec = Bounded(low=-1.0, high=1.0, shape=(config.action_dim,), device=device)
    dist_class, dist_kwargs = TanhNormal, {"low": -1.0, "high": 1.0}
    if config.grasp_head:
        dist_class, dist_kwargs = GraspConditionedTanhNormal, {"grasp_dims": tuple(config.grasp_dims)}
    return ProbabilisticActor(module, in_keys=keys, out_keys=["action"], spec=spec, distribution_class=dist_class,
                              distribution_kwargs=dist_kwargs, return_log_prob=False)


def find_dt_actor(actor: nn.Module) -> StochasticDTActor:
    """Return the (unique) :class:`StochasticDTActor` inside ``actor`` (an actor from :func:`make_dt_actor`)."""
    if isinstance(actor, StochasticDTActor):
        return actor
    found = [m for m in actor.modules() if isinstance(m, StochasticDTActor)]
    if len(found) != 1:
        raise ValueError(f"expected exactly one StochasticDTActor inside {type(actor).__name__}, found {len(found)}")
    return found[0]
