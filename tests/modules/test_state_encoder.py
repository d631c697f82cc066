import pytest
import torch

from trakdis.modules import EncoderEnsemble, StateEncoder, to_float_chw


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


class _DotDecoder(torch.nn.Module):
    """A perfect encoder of a toy scene: one bright pixel per point, read back as (x, y, 0)."""

    def forward(self, pixels):
        x = to_float_chw(pixels)[:, 0]  # [N, H, W]
        n, h, w = x.shape
        out = []
        for rows in (slice(0, h // 2), slice(h // 2, h)):  # point 0 in the top half, point 1 in the bottom
            flat = x[:, rows].reshape(n, -1).argmax(-1)
            col = (flat % w).float() - (w - 1) / 2  # centred: the flip maps col -> -col
            out += [col, torch.zeros(n), torch.zeros(n)]
        return torch.stack(out, -1)


def test_encoder_ensemble_averages_members_and_mirrored_views():
    px = torch.zeros(3, 8, 8, 3, dtype=torch.uint8)
    px[:, 1, 2, 0] = 255  # point 0 at column 2, point 1 at column 6
    px[:, 6, 6, 0] = 255
    exact = _DotDecoder()(px)
    # the flip mirrors x and (here) keeps the point identities: perm = identity, sign = -1 on x
    mirror = (list(range(6)), [-1.0, 1.0, 1.0, -1.0, 1.0, 1.0])
    torch.testing.assert_close(EncoderEnsemble([_DotDecoder()], state_mirror=mirror)(px), exact)
    # a biased member: its bias on x is antisymmetric under the mirror and averages out
    class Biased(_DotDecoder):
        def forward(self, pixels):
            return super().forward(pixels) + torch.tensor([0.5, 0.0, 0.0, 0.5, 0.0, 0.0])

    torch.testing.assert_close(EncoderEnsemble([Biased()], state_mirror=mirror)(px), exact)
    torch.testing.assert_close(EncoderEnsemble([Biased()])(px), exact + 0.5 * torch.tensor([1.0, 0, 0, 1, 0, 0]))
    torch.testing.assert_close(EncoderEnsemble([Biased(), _DotDecoder()])(px), exact + 0.25 * torch.tensor([1.0, 0, 0, 1, 0, 0]))
    # uint8 HWC and float CHW images flip along their width alike
    torch.testing.assert_close(EncoderEnsemble([Biased()], state_mirror=mirror)(to_float_chw(px)), exact)
    with pytest.raises(ValueError, match="at least one member"):
        EncoderEnsemble([])


def test_encoder_ensemble_file_round_trip(tmp_path):
    from trakdis.envs import task_spec
    from trakdis.modules import NormalizedEncoder
    from trakdis.policies import load_encoder, save_encoder

    members = [NormalizedEncoder(StateEncoder(18, channels=(4, 4, 4, 4), hidden_dim=8), torch.randn(18), torch.rand(18) + 0.5)
               for _ in range(2)]
    ens = EncoderEnsemble(members, state_mirror=task_spec("ClothFold").state_mirror).eval()
    save_encoder(tmp_path / "encoder.pt", ens, task="ClothFold", extra={"val_mae": 0.1})
    loaded, data = load_encoder(tmp_path / "encoder.pt", task="ClothFold")
    px = torch.randint(0, 255, (2, 32, 32, 3), dtype=torch.uint8)
    assert isinstance(loaded, EncoderEnsemble) and data["ensemble"]["members"] == 2 and data["val_mae"] == 0.1
    torch.testing.assert_close(loaded(px), ens(px))
    torch.testing.assert_close(ens(px), torch.stack([m(px) for m in members] + [
        m(px.flip(-2))[..., ens.state_mirror[0]] * torch.tensor(ens.state_mirror[1]) for m in members]).mean(0))


def test_encoder_ensemble_file_with_a_bad_member_count_is_refused(tmp_path):
    from trakdis.policies import encoder_from_dict
    from trakdis.utils.checkpoint import FileFormatError

    data = {"kind": "encoder", "encoder_kwargs": {"state_dim": 18}, "state_dict": {}, "ensemble": {"members": 0}}
    with pytest.raises(FileFormatError, match="'members' >= 1"):
        encoder_from_dict(data)
