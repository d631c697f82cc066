import torch
import torch.nn.functional as F

from trakdis.modules import CausalTransformer, KVCache, TransformerConfig
from trakdis.modules.transformer import attention


def test_attention_is_sdpa_causal_or_masked():
    torch.manual_seed(0)
    q, k, v = torch.randn(3, 2, 3, 7, 8).unbind(0)
    mask = torch.rand(2, 1, 7, 7) > 0.3
    mask |= torch.eye(7, dtype=torch.bool)
    scores = q @ k.transpose(-2, -1) / 8**0.5
    causal = torch.ones(7, 7, dtype=torch.bool).tril()
    torch.testing.assert_close(attention(q, k, v, None, 0.0), scores.masked_fill(~causal, float("-inf")).softmax(-1) @ v)
    torch.testing.assert_close(attention(q, k, v, mask, 0.0), scores.masked_fill(~mask, float("-inf")).softmax(-1) @ v)


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


def test_attention_dropout_trains_and_differs_from_eval():
    """With attention dropout (and no other dropout) the training pass draws masks from torch's seed,
    differs from the eval pass, stays causal and blind to padded keys, and has finite gradients."""
    torch.manual_seed(0)
    tr = CausalTransformer(TransformerConfig(embed_dim=16, n_layer=2, n_head=2, dropout=0.0, attn_dropout=0.3))
    x = torch.randn(3, 20, 16, requires_grad=True)
    pad = torch.ones(3, 20, dtype=torch.bool)
    pad[1, :6] = False
    for m in (None, pad):
        tr.eval()
        y_eval = tr(x, m)
        tr.train()
        torch.manual_seed(1)
        y = tr(x, m)
        assert not torch.allclose(y, y_eval, atol=1e-3)
        torch.manual_seed(1)
        torch.testing.assert_close(tr(x, m), y, rtol=0, atol=0)  # same seed, same masks
        y.pow(2).sum().backward()
        assert torch.isfinite(x.grad).all() and all(torch.isfinite(p.grad).all() for p in tr.parameters())
        x.grad = None
        tr.zero_grad()
        # causal: changing later tokens leaves earlier outputs unchanged (same masks)
        x2 = x.detach().clone()
        x2[:, 12:] = torch.randn(3, 8, 16)
        if m is not None:
            x2[1, :6] = 100 * torch.randn(6, 16)  # padded keys (finite content) are never read by real queries
        torch.manual_seed(1)
        y2 = tr(x2, m)
        real = slice(None) if m is None else pad[:, :12]
        torch.testing.assert_close(y2[:, :12][real], y.detach()[:, :12][real], rtol=0, atol=1e-6)
        assert not torch.allclose(y2[:, 12:], y.detach()[:, 12:], atol=1e-3)


def test_forward_cached_matches_forward():
    """Feeding tokens one at a time through a (ring) key/value cache gives the full forward's outputs."""
    torch.manual_seed(0)
    cfg = TransformerConfig(embed_dim=16, n_layer=3, n_head=2)
    tr = CausalTransformer(cfg).eval()
    x = torch.randn(2, 9, 16)
    full = tr(x)
    cache = KVCache(cfg, batch_size=2, capacity=12)
    order = torch.randperm(12)[:9]  # slot order does not matter
    outs = []
    with torch.no_grad():
        for t in range(9):
            allowed = torch.zeros(2, 1, 1, 12, dtype=torch.bool)
            allowed[..., order[: t + 1]] = True
            outs.append(tr.forward_cached(x[:, t : t + 1], cache, order[t : t + 1], allowed))
    torch.testing.assert_close(torch.cat(outs, 1), full, rtol=0, atol=1e-5)
    cache.zero_(torch.tensor([True, False]))
    assert cache.keys[0][0].abs().sum() == 0 and cache.keys[0][1].abs().sum() > 0
