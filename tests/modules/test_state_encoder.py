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


def test_spatial_soft_argmax_finds_a_peak():
    from trakdis.modules import SpatialSoftArgmax

    maps = torch.zeros(2, 3, 8, 8)
    maps[0, 0, 2, 5] = maps[1, 2, 7, 0] = 50.0  # sharp peaks: (x, y) of their pixels in [-1, 1]
    out = SpatialSoftArgmax(8, 8)(maps).view(2, 3, 2)
    grid = torch.linspace(-1, 1, 8)
    torch.testing.assert_close(out[0, 0], torch.stack([grid[5], grid[2]]), atol=1e-4, rtol=0)
    torch.testing.assert_close(out[1, 2], torch.stack([grid[0], grid[7]]), atol=1e-4, rtol=0)
    torch.testing.assert_close(out[0, 1], torch.zeros(2), atol=1e-6, rtol=0)  # a flat map: the centre


def test_coordinate_channels():
    from trakdis.modules import coordinate_channels

    x = coordinate_channels(torch.zeros(2, 3, 4, 5))
    assert x.shape == (2, 5, 4, 5)
    torch.testing.assert_close(x[0, 3, 0], torch.linspace(-1, 1, 5))  # x along the width
    torch.testing.assert_close(x[1, 4, :, 0], torch.linspace(-1, 1, 4))  # y along the height


@pytest.mark.parametrize("kw", [{}, {"head": "flatten", "stem_stride": 2, "coord_channels": False},
                                {"head": "flatten", "stem_stride": 2, "coord_channels": True}])
def test_layouts_shapes_gradients_and_config(kw):
    enc = StateEncoder(7, channels=(4, 4, 4, 6), hidden_dim=16, **kw)
    out = enc(torch.rand(3, 3, 32, 32))
    assert out.shape == (3, 7)
    out.sum().backward()
    assert all(p.grad is not None for p in enc.parameters())
    rebuilt = StateEncoder(**{k: v for k, v in enc.config.items()})
    rebuilt.load_state_dict(enc.state_dict())
    torch.testing.assert_close(rebuilt(torch.ones(1, 3, 32, 32)), enc(torch.ones(1, 3, 32, 32)))
    with pytest.raises(ValueError, match="head"):
        StateEncoder(7, head="mlp")
