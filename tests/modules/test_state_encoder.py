import pytest
import torch

from trakdis.modules import StateEncoder, to_float_chw


def test_uint8_hwc_and_float_chw_agree():
    torch.manual_seed(0)
    enc = StateEncoder(18)
    img = torch.randint(0, 256, (2, 5, 32, 32, 3), dtype=torch.uint8)
    out = enc(img)
    assert out.shape == (2, 5, 18)
    chw = img.permute(0, 1, 4, 2, 3).float() / 255
    torch.testing.assert_close(enc(chw), out)
    assert enc(img[0, 0]).shape == (18,)
    # HWC -> CHW keeps the pixel layout (no transposition of rows/columns)
    x = to_float_chw(img[0, 0])
    assert x[1, 3, 7] == img[0, 0, 3, 7, 1].float() / 255


def test_configurable_size_and_gradients():
    enc = StateEncoder(4, image_size=64, channels=(8, 8, 16, 16), hidden_dim=32)
    out = enc(torch.rand(3, 3, 64, 64))
    assert out.shape == (3, 4)
    out.sum().backward()
    assert all(p.grad is not None for p in enc.parameters())


@pytest.mark.parametrize(
    "bad, match",
    [
        (torch.zeros(2, 3, 32, 32, dtype=torch.uint8), r"uint8 images must be HWC.*\(2, 3, 32, 32\)"),
        (torch.zeros(2, 32, 32, 3), r"float images must be CHW.*\(2, 32, 32, 3\)"),
        (torch.zeros(2, 3, 32, 32, dtype=torch.int32), r"torch.int32"),
        (torch.zeros(2, 3, 16, 16), r"image_size=32.*\(16, 16\)"),
    ],
)
def test_clear_errors(bad, match):
    with pytest.raises(ValueError, match=match):
        StateEncoder(18)(bad)


def test_four_conv_layers():
    enc = StateEncoder(18)
    assert sum(isinstance(m, torch.nn.Conv2d) for m in enc.modules()) == 4
