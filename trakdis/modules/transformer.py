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
    "Dropout",
    "fast_dropout",
    "attention",
    "chunked_attention",
]

_ACTIVATIONS = {"gelu": nn.GELU, "relu": nn.ReLU, "gelu_tanh": lambda: nn.GELU(approximate="tanh")}


@dataclass
class TransformerConfig:
    """Size of a :class:`CausalTransformer`, as :meth:`~trakdis.modules.DTConfig.transformer_config`
    builds it (the sizes have no defaults here: :class:`~trakdis.modules.DTConfig` is where they are chosen).

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


def _dropout_threshold(p: float) -> tuple[int, float]:
    """16-bit threshold (keep iff a uniform int16 is >= it) and the exact keep probability."""
    threshold = min(round(p * 65536), 65535) - 32768
    return threshold, 1.0 - (threshold + 32768) / 65536


def _keep_mask(shape, p: float, device, dtype=torch.float32) -> tuple[torch.Tensor | None, float]:
    """Float keep-mask (1 = keep, 0 = drop) from 16-bit uniform integers and the keep probability.

    ``None`` (keep everything) when ``p`` rounds to 0 at 16-bit resolution.
    """
    threshold, q = _dropout_threshold(p)
    if threshold == -32768:
        return None, 1.0
    n = math.prod(shape)
    # random_(-2**63, None) draws full 64-bit integers: four uniform 16-bit lanes per draw
    words = torch.empty((n + 3) // 4, dtype=torch.int64, device=device).random_(-(2**63), None)
    bits = words.view(torch.int16)[:n].view(shape)
    # clamp-and-shift gives {0, 1} (no int16 overflow since threshold > -32768); much faster
    # on the CPU than `bits >= threshold` followed by a bool -> float cast
    return bits.clamp(threshold - 1, threshold).sub_(threshold - 1).to(dtype), q


def fast_dropout(x: torch.Tensor, p: float, training: bool = True) -> torch.Tensor:
    """Inverted dropout; on the CPU it draws 16-bit random integers instead of ``bernoulli_``.

    PyTorch's CPU dropout is bound by its random number generation (~10x slower than drawing
    raw 64-bit integers and slicing them into four 16-bit uniforms). ``p`` is quantised to
    multiples of 1/65536 and the output is rescaled by the exact keep probability, so it stays
    unbiased. The mask is a float tensor of ``{0, 1/q}`` (a multiplication is much cheaper
    forward and backward than ``torch.where`` on the CPU). On other devices this is
    ``torch.nn.functional.dropout``.
    """
    if not training or p == 0.0:
        return x
    if x.device.type != "cpu":
        return F.dropout(x, p, True)
    keep, q = _keep_mask(x.shape, p, x.device, x.dtype)
    if keep is None:
        return x
    return x * keep.mul_(1.0 / q)


class Dropout(nn.Dropout):
    """``nn.Dropout`` with the fast CPU path of :func:`fast_dropout`."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return fast_dropout(x, self.p, self.training)


# -- attention ------------------------------------------------------------------------------
# A chunk of a CPU attention plan: query rows [q0, q1) attend keys [0, k1); ``bias`` (additive,
# 0 / -inf, or None) is added to the scores of keys [kb, k1) and broadcasts to [B, H, q1 - q0, k1 - kb].
Chunk = tuple  # (q0, q1, k1, kb, bias)

CHUNK_ROWS = 32  # query rows per chunk of the CPU attention (tuned on 1 thread; see _chunk_bounds)


def _chunk_bounds(n_rows: int, rows: int | None = None) -> list[tuple[int, int]]:
    n = max(1, round(n_rows / (CHUNK_ROWS if rows is None else rows)))
    edges = [round(i * n_rows / n) for i in range(n + 1)]
    return list(zip(edges[:-1], edges[1:]))


def _neg_inf_bias(allowed: torch.Tensor, dtype) -> torch.Tensor:
    return torch.zeros(allowed.shape, dtype=dtype, device=allowed.device).masked_fill_(~allowed, float("-inf"))


def causal_plan(
    t: int, positions: slice | None = None, key_padding_mask: torch.Tensor | None = None, *, dtype=torch.float32, device=None
) -> list[Chunk]:
    """Chunks of causal attention over ``t`` keys for the queries at ``positions`` (all when None).

    A query at position ``i`` attends keys ``j <= i`` that are real (``key_padding_mask``, bool
    ``[B, t]``) and always itself. Each chunk of queries only computes scores for the keys up to
    its last query: the upper triangle beyond the chunk is skipped (about half of the work for
    long sequences).
    """
    pos = range(t)[positions] if positions is not None else range(t)
    if key_padding_mask is not None:
        device = key_padding_mask.device
    plan = []
    for a, b in _chunk_bounds(len(pos)):
        p0, p1 = pos[a], pos[b - 1]
        k1 = p1 + 1
        rows = torch.arange(p0, p1 + 1, pos.step, device=device)[:, None]
        if key_padding_mask is None:
            cols = torch.arange(p0, k1, device=device)
            allowed = cols <= rows
            bias = None if bool(allowed.all()) else _neg_inf_bias(allowed, dtype)
            plan.append((a, b, k1, p0, bias))
        else:
            cols = torch.arange(k1, device=device)
            allowed = ((cols <= rows) & key_padding_mask[:, None, None, :k1]) | (cols == rows)
            plan.append((a, b, k1, 0, _neg_inf_bias(allowed, dtype)))
    return plan


def dense_plan(attn_mask: torch.Tensor, dtype=torch.float32) -> list[Chunk]:
    """One chunk for an arbitrary bool mask ``[.., T_q, T_k]`` (True = may attend)."""
    return [(0, attn_mask.shape[-2], attn_mask.shape[-1], 0, _neg_inf_bias(attn_mask, dtype))]


class _ChunkedAttention(torch.autograd.Function):
    """Softmax attention with dropout on the weights, computed chunk by chunk (CPU training path).

    Forward per chunk: ``S = q k^T / sqrt(hd) (+ bias)``, ``P = softmax(S)``, ``O = (P * M) v / q``
    with a ``{0, 1}`` keep-mask ``M``; chunk ``i`` of queries only scores the keys it may see. The
    backward is written out (no autograd graph per chunk), so the per-chunk key/value gradients are
    accumulated into one buffer instead of going through slice-backward zero-fills.

    Inputs: ``qkv`` ``[3, B, H, T, hd]`` and ``kv=None`` (self-attention of all tokens: one
    gradient for the fused projection), or ``q`` ``[B, H, T_q, hd]`` and ``kv`` ``[2, B, H, T, hd]``;
    any strides (e.g. permuted views of the projection output).
    """

    @staticmethod
    def forward(ctx, qkv, kv, plan, dropout_p):
        fused = kv is None
        q = qkv[0] if fused else qkv
        kv = qkv[1:] if kv is None else kv
        b, h, tq, hd = q.shape
        tk = kv.shape[-2]
        scale = 1.0 / math.sqrt(hd)
        # one pass each: q / sqrt(hd) into a contiguous buffer, k and v into another
        q3 = torch.mul(q, scale, out=q.new_empty(b, h, tq, hd)).view(b * h, tq, hd)
        kv3 = kv.contiguous().view(2, b * h, tk, hd)
        k3, v3 = kv3[0], kv3[1]
        outs, saved, keep_prob = [], [], 1.0
        for q0, q1, k1, kb, bias in plan:
            c = q1 - q0
            # batched GEMMs read strided views of q/k/v at full speed; in-place ones into strided
            # outputs do not (ATen then loops over the batch), hence fresh outputs and a final cat
            s = torch.bmm(q3[:, q0:q1], k3[:, :k1].transpose(1, 2))
            if bias is not None:
                s.view(b, h, c, k1)[..., kb:].add_(bias)
            prob = torch.softmax(s, -1)
            keep = None
            if dropout_p > 0.0:
                keep, keep_prob = _keep_mask(prob.shape, dropout_p, prob.device, prob.dtype)
            weights = prob if keep is None else prob * keep
            outs.append(torch.bmm(weights, v3[:, :k1]))
            saved.append((weights, prob, keep))
        out = outs[0] if len(outs) == 1 else torch.cat(outs, 1)
        if keep_prob != 1.0:
            out.mul_(1.0 / keep_prob)
        ctx.save_for_backward(q3, kv3)
        ctx.chunks, ctx.plan, ctx.keep_prob, ctx.fused = saved, plan, keep_prob, fused
        ctx.shape = (b, h, tq, tk, hd)
        return out.view(b, h, tq, hd)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        q3, kv3 = ctx.saved_tensors
        k3, v3 = kv3[0], kv3[1]
        b, h, tq, tk, hd = ctx.shape
        g3 = grad_out.reshape(b * h, tq, hd)
        if ctx.keep_prob != 1.0:
            g3 = g3 * (1.0 / ctx.keep_prob)
        fused = ctx.fused
        grad = q3.new_empty(3 if fused else 2, b * h, tk, hd)  # [dq,] dk, dv
        dk, dv = grad[-2], grad[-1]
        dqs, started = [], False
        # last chunk first: it usually sees every key, so its dk/dv initialise the buffers
        for (q0, q1, k1, _, _), (weights, prob, keep) in reversed(list(zip(ctx.plan, ctx.chunks))):
            g = g3[:, q0:q1]
            dp = torch.bmm(g, v3[:, :k1].transpose(1, 2))
            if keep is not None:
                dp.mul_(keep)
            ds = torch._softmax_backward_data(dp, prob, -1, prob.dtype)
            dqs.append(torch.bmm(ds, k3[:, :k1]))
            if not started and k1 == tk:
                torch.bmm(weights.transpose(1, 2), g, out=dv)
                torch.bmm(ds.transpose(1, 2), q3[:, q0:q1], out=dk)  # q3 holds q / sqrt(hd)
            else:
                if not started:
                    dk.zero_()
                    dv.zero_()
                dv[:, :k1].add_(torch.bmm(weights.transpose(1, 2), g))
                dk[:, :k1].add_(torch.bmm(ds.transpose(1, 2), q3[:, q0:q1]))
            started = True
        ctx.chunks = None
        scale = 1.0 / math.sqrt(hd)
        if fused:
            dq = grad[0]
            if len(dqs) == 1:
                torch.mul(dqs[0], scale, out=dq)
            else:
                torch.cat(dqs[::-1], 1, out=dq).mul_(scale)
            return grad.view(3, b, h, tk, hd), None, None, None
        dq = (dqs[0] if len(dqs) == 1 else torch.cat(dqs[::-1], 1)).mul_(scale)
        return dq.view(b, h, tq, hd), grad.view(2, b, h, tk, hd), None, None


def chunked_attention(q, k, v, plan: list[Chunk], dropout_p: float) -> torch.Tensor:
    """Attention of ``q`` ``[B, H, T_q, hd]`` over ``k``, ``v`` ``[B, H, T_k, hd]`` following ``plan``."""
    return _ChunkedAttention.apply(q, torch.stack((k, v)), plan, dropout_p)


def attention(q, k, v, attn_mask: torch.Tensor | None, dropout_p: float) -> torch.Tensor:
    """``scaled_dot_product_attention`` (causal when ``attn_mask`` is None).

    With attention dropout on a CPU, SDPA falls back to its math kernel with PyTorch's slow
    dropout (measured ~2x slower fwd+bwd than without dropout); there the same math is computed
    by :func:`chunked_attention` with the cheaper dropout of :func:`fast_dropout`, skipping the
    causal upper triangle chunk by chunk. Measured against SDPA + ``nn.Dropout`` (one
    thread, training steps of batch 64 interleaved in one process, best of 4-12 rounds): 1.40x
    faster at ``--preset paper`` size (context 30), 1.22x at the ``DTConfig`` defaults, 1.12x for
    the recipes' small model with ``--dropout 0.1``; with dropout 0 (the recipes' default) neither
    runs.
    """
    if dropout_p == 0.0 or q.device.type != "cpu":
        if attn_mask is None:
            return F.scaled_dot_product_attention(q, k, v, dropout_p=dropout_p, is_causal=True)
        return F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask, dropout_p=dropout_p)
    if attn_mask is None:
        plan = causal_plan(k.shape[-2], dtype=q.dtype, device=q.device)
    else:
        plan = dense_plan(attn_mask, q.dtype)
    return chunked_attention(q, k, v, plan, dropout_p)


class CausalMask:
    """The attention mask of one :meth:`CausalTransformer.forward` pass, shared by all its layers.

    Causal over ``t`` tokens, combined with an optional key padding mask (bool ``[B, t]``, True =
    real); builds and caches the dense bool masks (SDPA path) and chunk plans (CPU dropout path)
    the layers ask for, so each is built once per batch instead of once per layer.
    """

    def __init__(self, t: int, key_padding_mask: torch.Tensor | None = None, device=None):
        self.t = t
        self.key_padding_mask = key_padding_mask
        self.device = key_padding_mask.device if key_padding_mask is not None else device
        self._dense = {}
        self._plans = {}

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

    def plan(self, query: slice | None, dtype) -> list[Chunk]:
        key = (self._key(query), dtype)
        if key not in self._plans:
            self._plans[key] = causal_plan(self.t, query, self.key_padding_mask, dtype=dtype, device=self.device)
        return self._plans[key]


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
        h, hd = self.n_head, self.head_dim
        manual = p > 0.0 and x.device.type == "cpu"  # chunked CPU path (see `attention`)
        if query is None:
            qkv = self.qkv(x).view(b, t, 3, h, hd).permute(2, 0, 3, 1, 4)  # [3, B, H, T, hd]
            q, kv = qkv, None
        else:
            w, bias = self.qkv.weight, self.qkv.bias
            q = F.linear(x[:, query], w[:d], None if bias is None else bias[:d]).view(b, -1, h, hd).transpose(1, 2)
            kv = F.linear(x, w[d:], None if bias is None else bias[d:]).view(b, t, 2, h, hd).permute(2, 0, 3, 1, 4)
        if manual:
            if isinstance(attn_mask, CausalMask):
                plan = attn_mask.plan(query, x.dtype)
            elif attn_mask is None:
                plan = causal_plan(t, query, dtype=x.dtype, device=x.device)
            else:
                plan = dense_plan(attn_mask if query is None else attn_mask[:, :, query], x.dtype)
            return self._merge(_ChunkedAttention.apply(q, kv, plan, p))
        q, k, v = q.unbind(0) if kv is None else (q, *kv.unbind(0))
        if isinstance(attn_mask, CausalMask):
            mask = attn_mask.dense(query)
        elif attn_mask is None:
            mask = None if query is None else CausalMask(t, device=x.device).dense(query)
        else:
            mask = attn_mask if query is None else attn_mask[:, :, query]
        if mask is None:
            return self._merge(F.scaled_dot_product_attention(q, k, v, dropout_p=p, is_causal=True))
        return self._merge(F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=p))

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
        self.drop = Dropout(config.dropout)

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
