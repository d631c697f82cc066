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
