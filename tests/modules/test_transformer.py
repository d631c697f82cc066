import pytest
import torch
import torch.nn.functional as F

from trakdis.modules import CausalTransformer, TransformerConfig
from trakdis.modules.transformer import Dropout, attention, fast_dropout


def test_fast_dropout_statistics_and_gradient():
    torch.manual_seed(0)
    x = torch.ones(400, 500, requires_grad=True)
    y = fast_dropout(x, 0.1)
    kept = y != 0
    assert abs(kept.float().mean().item() - 0.9) < 0.005
    assert abs(y.mean().item() - 1.0) < 0.01  # unbiased
    torch.testing.assert_close(y[kept], torch.full_like(y[kept], 1 / 0.9), rtol=1e-4, atol=0)
    y.sum().backward()
    torch.testing.assert_close(x.grad, y.detach())  # d(sum)/dx = keep / q
    assert fast_dropout(x, 0.1, training=False) is x
    # fresh masks per call, reproducible under a seed
    torch.manual_seed(1)
    a = fast_dropout(torch.ones(1000), 0.5)
    torch.manual_seed(1)
    b = fast_dropout(torch.ones(1000), 0.5)
    assert torch.equal(a, b) and not torch.equal(a, fast_dropout(torch.ones(1000), 0.5))
    d = Dropout(0.3).eval()
    assert torch.equal(d(x), x)


def test_manual_cpu_attention_path_matches_sdpa():
    # a tiny dropout probability keeps every weight but takes the hand-written CPU path
    torch.manual_seed(0)
    q, k, v = torch.randn(3, 2, 3, 7, 8).unbind(0)
    mask = torch.rand(2, 1, 7, 7) > 0.3
    mask |= torch.eye(7, dtype=torch.bool)
    torch.testing.assert_close(attention(q, k, v, None, 1e-9), F.scaled_dot_product_attention(q, k, v, is_causal=True))
    torch.testing.assert_close(attention(q, k, v, mask, 1e-9), F.scaled_dot_product_attention(q, k, v, attn_mask=mask))
    torch.manual_seed(0)
    out = attention(q, k, v, None, 0.5)
    assert out.shape == q.shape and torch.isfinite(out).all()


def test_output_positions_match_full_forward():
    torch.manual_seed(0)
    tr = CausalTransformer(TransformerConfig(embed_dim=16, n_layer=3, n_head=2)).eval()
    x = torch.randn(2, 12, 16)
    pad = torch.ones(2, 12, dtype=torch.bool)
    pad[1, :4] = False
    for m in (None, pad):
        full = tr(x, m)
        sub = tr(x, m, output_positions=slice(1, None, 3))
        torch.testing.assert_close(sub, full[:, 1::3], rtol=0, atol=1e-5)


def _recorded_masks(monkeypatch):
    """Record the attention keep-masks the chunked CPU path draws (one per chunk, in order)."""
    from trakdis.modules import transformer as tr_mod

    masks, orig = [], tr_mod._keep_mask

    def keep_mask(shape, p, device, dtype=torch.float32):
        m, q = orig(shape, p, device, dtype)
        masks.append(m)
        return m, q

    monkeypatch.setattr(tr_mod, "_keep_mask", keep_mask)
    return masks


@pytest.mark.parametrize(
    "t, query, pad, n_chunks",
    [
        (100, None, False, 3),  # several chunks, causal upper triangle skipped
        (100, None, True, 3),
        (100, slice(1, None, 3), True, 1),  # state-token queries (last DT layer)
        (200, slice(1, 190, 3), True, 2),  # strided chunks, none of them sees every key
        (9, None, False, 1),
    ],
)
def test_chunked_attention_matches_dense_reference_with_the_same_dropout(monkeypatch, t, query, pad, n_chunks):
    from trakdis.modules.transformer import CausalMask, _ChunkedAttention, _dropout_threshold

    torch.manual_seed(0)
    b, h, hd, p = 2, 3, 8, 0.3
    qkv = torch.randn(3, b, h, t, hd, dtype=torch.float64, requires_grad=True)
    kpm = None
    if pad:
        kpm = torch.ones(b, t, dtype=torch.bool)
        kpm[0, : t // 3] = False
    masks = _recorded_masks(monkeypatch)
    plan = CausalMask(t, kpm).plan(query, torch.float64)
    assert len(plan) == n_chunks
    if query is None:
        out = _ChunkedAttention.apply(qkv, None, plan, p)
    else:
        out = _ChunkedAttention.apply(qkv[0][:, :, query], qkv[1:], plan, p)
    g = torch.randn_like(out)
    (grad,) = torch.autograd.grad(out, qkv, g)
    # dense reference with the same keep-masks (entries outside the chunks are masked anyway)
    pos = torch.arange(t)
    qpos = pos if query is None else pos[query]
    keep = torch.zeros(b * h, len(qpos), t, dtype=torch.float64)
    assert len(masks) == len(plan)
    for (q0, q1, k1, _, _), m in zip(plan, masks):
        keep[:, q0:q1, :k1] = m
    allowed = pos[None, :] <= qpos[:, None]
    if kpm is not None:
        allowed = (allowed & kpm[:, None, None, :]) | (pos[None, :] == qpos[:, None])
    q = qkv[0] if query is None else qkv[0][:, :, query]
    scores = (q / hd**0.5) @ qkv[1].transpose(-2, -1)
    weights = scores.masked_fill(~allowed, float("-inf")).softmax(-1) * keep.view(b, h, len(qpos), t)
    ref = weights @ qkv[2] / _dropout_threshold(p)[1]
    (grad_ref,) = torch.autograd.grad(ref, qkv, g)
    torch.testing.assert_close(out, ref, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(grad, grad_ref, rtol=1e-10, atol=1e-10)


def test_training_path_matches_eval_path_without_dropout():
    # a negligible attention dropout keeps every weight but takes the chunked CPU path
    torch.manual_seed(0)
    cfg = TransformerConfig(embed_dim=16, n_layer=3, n_head=2, dropout=0.0, attn_dropout=1e-9)
    tr = CausalTransformer(cfg).double()
    x = torch.randn(3, 80, 16, dtype=torch.float64)
    pad = torch.ones(3, 80, dtype=torch.bool)
    pad[1, :30] = False
    for m in (None, pad):
        for pos in (None, slice(1, None, 3)):
            grads = []
            for train in (True, False):
                tr.train(train)
                tr.zero_grad()
                y = tr(x, m, output_positions=pos)
                y.pow(2).sum().backward()
                grads.append((y.detach(), [p.grad.clone() for p in tr.parameters()]))
            torch.testing.assert_close(grads[0][0], grads[1][0])
            for a, b in zip(grads[0][1], grads[1][1]):
                torch.testing.assert_close(a, b)
