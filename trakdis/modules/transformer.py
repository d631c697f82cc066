"""A compact causal (GPT-style) transformer on ``torch.nn.functional.scaled_dot_product_attention``.

Written here instead of reusing TorchRL's ``DecisionTransformer`` because that one wraps
HuggingFace ``GPT2Model`` (an extra dependency, learned absolute position embeddings that break
rolling key/value caches, no padding mask) and has no incremental (cached) decoding API.

Two entry points share the same weights:

* :meth:`CausalTransformer.forward` runs a whole (possibly left-padded) sequence ``[B, T, D]``
  with a causal mask combined with a key padding mask.
* :meth:`CausalTransformer.forward_cached` runs a few new tokens ``[B, T_new, D]`` against
  preallocated per-layer key/value buffers (see :class:`KVCache`), so that autoregressive acting
  costs ``O(cache size)`` per step instead of re-encoding the whole context.

No positional embedding is added inside the transformer: callers (the Decision Transformer) add
their own timestep embedding to the tokens, so a token's key/value only depends on the tokens
before it and stays valid while it sits in a cache.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "TransformerConfig",
    "CausalSelfAttention",
    "TransformerBlock",
    "CausalTransformer",
    "CausalMask",
    "KVCache",
    "attention",
]

_ACTIVATIONS = {"gelu": nn.GELU, "relu": nn.ReLU, "gelu_tanh": lambda: nn.GELU(approximate="tanh")}


@dataclass
class TransformerConfig:
    """Size of a :class:`CausalTransformer`, as :meth:`~trakdis.modules.DTModelConfig.transformer_config`
    builds it (the sizes have no defaults here: :class:`~trakdis.modules.DTModelConfig` is where they are chosen).

    Args:
        embed_dim: token width; must be divisible by ``n_head``.
        n_layer: number of pre-LayerNorm blocks.
        n_head: attention heads.
        dropout: dropout on embeddings' residual branches (attention output and MLP output).
        attn_dropout: dropout on attention weights (only while training).
        mlp_ratio: hidden width of the MLP as a multiple of ``embed_dim``.
        activation: ``"gelu"``, ``"gelu_tanh"`` or ``"relu"``.
        bias: whether linear layers and LayerNorms have biases.
    """

    embed_dim: int
    n_layer: int
    n_head: int
    dropout: float = 0.0
    attn_dropout: float = 0.0
    mlp_ratio: int = 4
    activation: str = "gelu"
    bias: bool = True

    def __post_init__(self) -> None:
        if self.embed_dim % self.n_head != 0:
            raise ValueError(f"embed_dim={self.embed_dim} must be divisible by n_head={self.n_head}")
        if self.activation not in _ACTIVATIONS:
            raise ValueError(f"activation={self.activation!r}; expected one of {sorted(_ACTIVATIONS)}")
        for name in ("dropout", "attn_dropout"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"{name}={getattr(self, name)} must be in [0, 1)")


def attention(q, k, v, attn_mask: torch.Tensor | None, dropout_p: float = 0.0) -> torch.Tensor:
    """``scaled_dot_product_attention`` of ``q`` ``[B, H, T_q, hd]`` over ``k``, ``v`` ``[B, H, T_k, hd]``.

    Causal (``is_causal``) when ``attn_mask`` is None, else the bool ``attn_mask`` (True = may
    attend); ``dropout_p`` on the attention weights (pass 0 outside training).
    """
    if attn_mask is None:
        return F.scaled_dot_product_attention(q, k, v, dropout_p=dropout_p, is_causal=True)
    return F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask, dropout_p=dropout_p)


class CausalMask:
    """The attention mask of one :meth:`CausalTransformer.forward` pass, shared by all its layers.

    Causal over ``t`` tokens, combined with an optional key padding mask (bool ``[B, t]``, True =
    real); builds and caches the dense bool masks the layers ask for, so each is built once per
    batch instead of once per layer.
    """

    def __init__(self, t: int, key_padding_mask: torch.Tensor | None = None, device=None):
        self.t = t
        self.key_padding_mask = key_padding_mask
        self.device = key_padding_mask.device if key_padding_mask is not None else device
        self._dense = {}

    @staticmethod
    def _key(query: slice | None):
        return None if query is None else (query.start, query.stop, query.step)

    def dense(self, query: slice | None = None) -> torch.Tensor | None:
        """Bool ``[B or 1, 1, T_q, t]`` rows of the mask for the queries, or None (plain causal)."""
        key = self._key(query)
        if key not in self._dense:
            if self.key_padding_mask is None:
                if query is None:
                    mask = None
                else:
                    pos = torch.arange(self.t, device=self.device)
                    mask = pos[None, :] <= pos[query][:, None]
            else:
                full = self._dense.get(None)
                if full is None:
                    full = self._dense[None] = CausalTransformer.build_attn_mask(self.key_padding_mask)
                mask = full if query is None else full[:, :, query]
            self._dense[key] = mask
        return self._dense[key]


class KVCache:
    """Preallocated per-layer key/value buffers for :meth:`CausalTransformer.forward_cached`.

    ``keys[l]`` and ``values[l]`` have shape ``[B, n_head, capacity, head_dim]``. The caller decides
    which slots new tokens are written to (e.g. a ring buffer) and which cached slots each new
    query may attend to (a boolean mask); slot order is irrelevant because the transformer has no
    positional embedding (softmax attention is invariant to a permutation of the keys).
    """

    def __init__(self, config: TransformerConfig, batch_size: int, capacity: int, *, device=None, dtype=None):
        head_dim = config.embed_dim // config.n_head
        shape = (batch_size, config.n_head, capacity, head_dim)
        self.keys = [torch.zeros(shape, device=device, dtype=dtype) for _ in range(config.n_layer)]
        self.values = [torch.zeros(shape, device=device, dtype=dtype) for _ in range(config.n_layer)]
        self.batch_size = batch_size
        self.capacity = capacity

    def zero_(self, batch_index: torch.Tensor | None = None) -> None:
        """Zero all entries, or those of the batch rows selected by ``batch_index`` (bool ``[B]``)."""
        for buf in (*self.keys, *self.values):
            if batch_index is None:
                buf.zero_()
            else:
                buf.masked_fill_(batch_index.view(-1, 1, 1, 1), 0.0)


class CausalSelfAttention(nn.Module):
    """Multi-head self-attention with a fused QKV projection and SDPA."""

    def __init__(self, config: TransformerConfig):
        super().__init__()
        self.n_head = config.n_head
        self.head_dim = config.embed_dim // config.n_head
        self.qkv = nn.Linear(config.embed_dim, 3 * config.embed_dim, bias=config.bias)
        self.proj = nn.Linear(config.embed_dim, config.embed_dim, bias=config.bias)
        self.attn_dropout = config.attn_dropout

    def _split(self, x: torch.Tensor):
        b, t, _ = x.shape
        q, k, v = self.qkv(x).view(b, t, 3, self.n_head, self.head_dim).permute(2, 0, 3, 1, 4)
        return q, k, v  # each [B, H, T, hd]

    def _merge(self, y: torch.Tensor) -> torch.Tensor:
        b, h, t, hd = y.shape
        return self.proj(y.transpose(1, 2).reshape(b, t, h * hd))

    def forward(
        self, x: torch.Tensor, attn_mask: "CausalMask | torch.Tensor | None" = None, query: slice | None = None
    ) -> torch.Tensor:
        """``x``: ``[B, T, D]``; ``attn_mask``: a :class:`CausalMask`, a bool ``[B, 1, T, T]`` tensor
        (True = may attend) or None (causal).

        ``query``: compute the outputs only at positions ``x[:, query]`` (keys/values still use
        all positions); the result is then ``[B, T_query, D]``.
        """
        p = self.attn_dropout if self.training else 0.0
        b, t, d = x.shape
        if query is None:
            q, k, v = self._split(x)
        else:
            h, hd = self.n_head, self.head_dim
            w, bias = self.qkv.weight, self.qkv.bias
            q = F.linear(x[:, query], w[:d], None if bias is None else bias[:d]).view(b, -1, h, hd).transpose(1, 2)
            k, v = F.linear(x, w[d:], None if bias is None else bias[d:]).view(b, t, 2, h, hd).permute(2, 0, 3, 1, 4)
        if isinstance(attn_mask, CausalMask):
            mask = attn_mask.dense(query)
        elif attn_mask is None:
            mask = None if query is None else CausalMask(t, device=x.device).dense(query)
        else:
            mask = attn_mask if query is None else attn_mask[:, :, query]
        return self._merge(attention(q, k, v, mask, p))

    def forward_cached(
        self, x: torch.Tensor, k_cache: torch.Tensor, v_cache: torch.Tensor, slots: torch.Tensor, attn_mask: torch.Tensor
    ) -> torch.Tensor:
        """Write the new tokens' keys/values at ``slots`` of the caches, then attend over the caches."""
        q, k, v = self._split(x)
        k_cache[:, :, slots] = k
        v_cache[:, :, slots] = v
        p = self.attn_dropout if self.training else 0.0
        return self._merge(attention(q, k_cache, v_cache, attn_mask, p))


class TransformerBlock(nn.Module):
    """Pre-LayerNorm block: ``x + Drop(Attn(LN(x)))`` then ``x + Drop(MLP(LN(x)))``."""

    def __init__(self, config: TransformerConfig):
        super().__init__()
        d = config.embed_dim
        self.ln1 = nn.LayerNorm(d, bias=config.bias)
        self.attn = CausalSelfAttention(config)
        self.ln2 = nn.LayerNorm(d, bias=config.bias)
        self.mlp = nn.Sequential(
            nn.Linear(d, config.mlp_ratio * d, bias=config.bias),
            _ACTIVATIONS[config.activation](),
            nn.Linear(config.mlp_ratio * d, d, bias=config.bias),
        )
        self.drop = nn.Dropout(config.dropout)

    def forward(self, x: torch.Tensor, attn_mask: "CausalMask | torch.Tensor | None" = None, query: slice | None = None) -> torch.Tensor:
        """See :meth:`CausalSelfAttention.forward`; with ``query`` the block outputs ``x[:, query]`` only."""
        y = self.attn(self.ln1(x), attn_mask, query)
        x = (x if query is None else x[:, query]) + self.drop(y)
        return x + self.drop(self.mlp(self.ln2(x)))

    def forward_cached(self, x, k_cache, v_cache, slots, attn_mask) -> torch.Tensor:
        x = x + self.drop(self.attn.forward_cached(self.ln1(x), k_cache, v_cache, slots, attn_mask))
        return x + self.drop(self.mlp(self.ln2(x)))


class CausalTransformer(nn.Module):
    """Stack of pre-LN blocks with a final LayerNorm, over already-embedded tokens.

    Args:
        config: a :class:`TransformerConfig`.

    Padding: ``forward(x, key_padding_mask)`` with ``key_padding_mask`` bool ``[B, T]`` (True = real
    token). A real query attends to real keys at or before its position; a padded query attends
    only to itself (so no row of the softmax is empty and no NaN appears). Outputs at real
    positions therefore never depend on the content of padded positions, as long as that content
    is finite (callers should zero padded inputs, as :class:`~trakdis.modules.DTBackbone` does).
    """

    def __init__(self, config: TransformerConfig):
        super().__init__()
        self.config = config
        self.blocks = nn.ModuleList(TransformerBlock(config) for _ in range(config.n_layer))
        self.ln_f = nn.LayerNorm(config.embed_dim, bias=config.bias)
        self.apply(self._init_weights)
        # GPT-2: scale the residual projections by 1/sqrt(2 * n_layer).
        for block in self.blocks:
            for lin in (block.attn.proj, block.mlp[-1]):
                nn.init.normal_(lin.weight, std=0.02 / math.sqrt(2 * config.n_layer))

    @staticmethod
    def _init_weights(m: nn.Module) -> None:
        if isinstance(m, nn.Linear):
            nn.init.normal_(m.weight, std=0.02)
            if m.bias is not None:
                nn.init.zeros_(m.bias)

    @staticmethod
    def build_attn_mask(key_padding_mask: torch.Tensor) -> torch.Tensor:
        """Causal AND key-padding mask, bool ``[B, 1, T, T]``; the diagonal is always allowed."""
        t = key_padding_mask.shape[-1]
        causal = torch.ones(t, t, dtype=torch.bool, device=key_padding_mask.device).tril_()
        mask = causal & key_padding_mask[:, None, None, :]
        return mask | torch.eye(t, dtype=torch.bool, device=key_padding_mask.device)

    def forward(
        self, x: torch.Tensor, key_padding_mask: torch.Tensor | None = None, output_positions: slice | None = None
    ) -> torch.Tensor:
        """``x``: ``[B, T, D]``; ``key_padding_mask``: bool ``[B, T]`` or None (no padding).

        ``output_positions``: if given (a slice of token positions), only those outputs are
        computed and returned (``[B, T_out, D]``): the last block then skips the queries, MLP
        and LayerNorm of every other token (the Decision Transformer needs only its state tokens).
        """
        if x.dim() != 3 or x.shape[-1] != self.config.embed_dim:
            raise ValueError(f"expected tokens of shape [B, T, {self.config.embed_dim}], got {tuple(x.shape)}")
        attn_mask = CausalMask(x.shape[1], key_padding_mask, device=x.device)  # built once, shared by the layers
        last = len(self.blocks) - 1
        for i, block in enumerate(self.blocks):
            x = block(x, attn_mask, output_positions if i == last else None)
        return self.ln_f(x)

    def forward_cached(
        self, x: torch.Tensor, cache: KVCache, slots: torch.Tensor, attn_mask: torch.Tensor
    ) -> torch.Tensor:
        """Run new tokens ``x`` ``[B, T_new, D]`` against ``cache``.

        Args:
            x: the new tokens.
            cache: a :class:`KVCache` with ``batch_size == B``.
            slots: int64 ``[T_new]``, where the new tokens' keys/values are written (same for every row).
            attn_mask: bool ``[B, 1, T_new, capacity]``: which cache slots each new token attends to;
                it must allow the token's own slot (the caller encodes causality among new tokens).
        """
        if x.shape[0] != cache.batch_size:
            raise ValueError(f"tokens have batch {x.shape[0]} but the cache was built for {cache.batch_size}")
        for block, k_cache, v_cache in zip(self.blocks, cache.keys, cache.values):
            x = block.forward_cached(x, k_cache, v_cache, slots, attn_mask)
        return self.ln_f(x)
