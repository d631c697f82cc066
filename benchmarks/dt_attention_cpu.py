"""The paper preset's CPU training step with the chunked CPU attention and without it.

One-off measurement for docs/benchmarks.md, taken before the chunked attention path and
``fast_dropout`` were removed from ``trakdis.modules.transformer``. It reuses
``benchmarks/dt_speed.py``'s model, batch and alternating timer (``--size paper``, context 30,
batch 32, ``MaskedOnlineDTLoss`` forward + backward + Adam) and times, in rounds that alternate:

* ``chunked``: the chunked attention with ``fast_dropout`` (dropout 0.1, attention dropout 0.1);
* ``sdpa+fast``: ``F.scaled_dot_product_attention(dropout_p=0.1)``, residual/embedding dropout still ``fast_dropout``;
* ``sdpa``: ``F.scaled_dot_product_attention(dropout_p=0.1)`` and ``nn.Dropout`` (the single path kept);
* ``p=0``: dropout 0 everywhere (one SDPA call, no dropout; the same code before and after).

    python benchmarks/dt_attention_cpu.py --threads 1
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys

import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(__file__))
import dt_speed  # noqa: E402

from trakdis.modules import make_dt_actor  # noqa: E402
from trakdis.modules import transformer as tr_mod  # noqa: E402
from trakdis.objectives import MaskedOnlineDTLoss  # noqa: E402

ORIGINAL_FORWARD = tr_mod.CausalSelfAttention.forward
ORIGINAL_DROPOUT = tr_mod.fast_dropout


def sdpa_forward(self, x, attn_mask=None, query=None):
    """The single SDPA path of ``CausalSelfAttention.forward`` (what the module keeps)."""
    p = self.attn_dropout if self.training else 0.0
    b, t, d = x.shape
    h, hd = self.n_head, self.head_dim
    if query is None:
        q, k, v = self.qkv(x).view(b, t, 3, h, hd).permute(2, 0, 3, 1, 4)
    else:
        w, bias = self.qkv.weight, self.qkv.bias
        q = F.linear(x[:, query], w[:d], None if bias is None else bias[:d]).view(b, -1, h, hd).transpose(1, 2)
        k, v = F.linear(x, w[d:], None if bias is None else bias[d:]).view(b, t, 2, h, hd).permute(2, 0, 3, 1, 4)
    if isinstance(attn_mask, tr_mod.CausalMask):
        mask = attn_mask.dense(query)
    elif attn_mask is None:
        mask = None if query is None else tr_mod.CausalMask(t, device=x.device).dense(query)
    else:
        mask = attn_mask if query is None else attn_mask[:, :, query]
    if mask is None:
        y = F.scaled_dot_product_attention(q, k, v, dropout_p=p, is_causal=True)
    else:
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=p)
    return self._merge(y)


def torch_dropout(x, p, training=True):
    return F.dropout(x, p, training)


class Variant:
    """A training step run with the attention forward and dropout function of one variant."""

    def __init__(self, step, forward, dropout):
        self.step, self.forward, self.dropout, self.td = step, forward, dropout, step.td

    def __call__(self):
        tr_mod.CausalSelfAttention.forward = self.forward
        tr_mod.fast_dropout = self.dropout
        try:
            self.step()
        finally:
            tr_mod.CausalSelfAttention.forward = ORIGINAL_FORWARD
            tr_mod.fast_dropout = ORIGINAL_DROPOUT


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--context", type=int, default=30)
    p.add_argument("--steps", type=int, default=3, help="timed training steps per round")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    td = dt_speed.batch_windows(args.batch, args.context, torch.device("cpu"))
    variants = {}
    for name, forward, dropout, drop_p in [
        ("chunked", ORIGINAL_FORWARD, ORIGINAL_DROPOUT, 0.1),
        ("sdpa+fast", sdpa_forward, ORIGINAL_DROPOUT, 0.1),
        ("sdpa", sdpa_forward, torch_dropout, 0.1),
        ("p=0", sdpa_forward, torch_dropout, 0.0),
    ]:
        cfg = dt_speed.make_config("paper", args.context)
        cfg.dropout = cfg.attn_dropout = drop_p
        torch.manual_seed(0)
        actor = make_dt_actor(cfg)
        step = dt_speed.TrainStep(MaskedOnlineDTLoss(actor, lambda_entropy=0.1), ["loss_nll", "loss_entropy"], td)
        variants[name] = Variant(step, forward, dropout)
    print(f"torch {torch.__version__} | threads {torch.get_num_threads()} | paper preset, context {args.context}, "
          f"batch {args.batch} | {args.rounds} rounds x {args.steps} steps, alternating")
    rates = dt_speed.time_train(variants, torch.device("cpu"), args.steps, args.rounds)
    ms = {name: [args.batch / r * 1e3 for r in rs] for name, rs in rates.items()}
    for name, m in ms.items():
        print(f"{name:10s} ms/step best {min(m):7.1f} median {statistics.median(m):7.1f} | rounds "
              + " ".join(f"{x:.0f}" for x in m))
    base = ms["chunked"]
    for name in ("sdpa+fast", "sdpa", "p=0"):
        print(f"{name} / chunked: best {min(ms[name]) / min(base):.2f}x, median "
              f"{statistics.median(ms[name]) / statistics.median(base):.2f}x (time ratio)")


if __name__ == "__main__":
    main()
