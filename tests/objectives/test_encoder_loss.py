import pytest
import torch
from tensordict import TensorDict
from torch import nn

from trakdis.objectives import EncoderLoss
from trakdis.transforms import horizontal_flip, mirror_state, random_flip, random_shift

H = W = 16
# state = (x_left, y_left, x_right, y_right): two dots, identities by left/right order, x centred.
PERM, SIGN = [2, 3, 0, 1], [-1.0, 1.0, -1.0, 1.0]


def dot_images(n, seed=0):
    """Images with two bright pixels (uint8 HWC) and the labels they encode."""
    g = torch.Generator().manual_seed(seed)
    imgs = torch.zeros(n, H, W, 3, dtype=torch.uint8)
    state = torch.zeros(n, 4)
    for i in range(n):
        # away from the border, so a shift of up to 2 pixels keeps both dots in the image
        cols = (torch.randperm(W - 6, generator=g)[:2] + 3).sort().values
        rows = torch.randint(3, H - 3, (2,), generator=g)
        imgs[i, rows, cols] = 255
        state[i] = torch.tensor([cols[0] - (W - 1) / 2, rows[0], cols[1] - (W - 1) / 2, rows[1]], dtype=torch.float)
    return imgs, state


class DotDecoder(nn.Module):
    """A perfect 'encoder' for dot_images: reads the two bright pixels back (float CHW input)."""

    def __init__(self):
        super().__init__()
        self.bias = nn.Parameter(torch.zeros(4))

    def forward(self, x):
        out = []
        for img in x:
            rows, cols = torch.nonzero(img[0] > 0.5, as_tuple=True)
            order = cols.argsort()
            rows, cols = rows[order].float(), cols[order].float() - (W - 1) / 2
            out.append(torch.stack([cols[0], rows[0], cols[1], rows[1]]))
        return torch.stack(out) + self.bias


def test_flip_relabels_consistently():
    imgs, state = dot_images(16)
    x = imgs.permute(0, 3, 1, 2).float() / 255
    dec = DotDecoder()
    torch.testing.assert_close(dec(x), state)
    torch.testing.assert_close(dec(horizontal_flip(x)), mirror_state(state, PERM, SIGN))
    xf, sf = random_flip(x, state, PERM, SIGN, prob=0.5, generator=torch.Generator().manual_seed(0))
    flipped = (xf != x).flatten(1).any(1)
    assert 0 < flipped.sum() < 16
    torch.testing.assert_close(dec(xf), sf)
    # a plain reflection of the labels without the identity swap would be wrong
    assert not torch.allclose(dec(horizontal_flip(x)), state * torch.tensor(SIGN))


def test_encoder_loss_with_perfect_encoder_is_zero_under_flip_and_not_with_wrong_mirror():
    imgs, state = dot_images(32)
    td = TensorDict(pixels=imgs, state=state, batch_size=[32])
    loss = EncoderLoss(DotDecoder(), state_mirror=(PERM, SIGN), flip_prob=1.0, pad=0)
    out = loss(td)
    assert out["loss_encoder"].item() == 0.0 and out["mae"].item() == 0.0
    wrong = EncoderLoss(DotDecoder(), state_mirror=([0, 1, 2, 3], SIGN), flip_prob=1.0, pad=0)
    assert wrong(td)["loss_encoder"] > 1.0
    # no mirror given: no flip, still exact
    assert EncoderLoss(DotDecoder(), pad=0)(td)["loss_encoder"].item() == 0.0
    # the default does not shift: the labels of an image stay its own (only the flip transforms them)
    assert EncoderLoss(DotDecoder(), flip_prob=0.0)(td)["loss_encoder"].item() == 0.0


def test_random_shift_translates_and_keeps_labels_within_pad():
    imgs, state = dot_images(24, seed=1)
    x = imgs.permute(0, 3, 1, 2).float() / 255
    pad = 2
    xs = random_shift(x, pad, generator=torch.Generator().manual_seed(0))
    padded = torch.nn.functional.pad(x, (pad,) * 4, mode="replicate")
    offsets = set()
    for i in range(24):
        hits = [(dy, dx) for dy in range(2 * pad + 1) for dx in range(2 * pad + 1) if torch.equal(xs[i], padded[i, :, dy : dy + H, dx : dx + W])]
        assert hits, f"image {i} is not a crop of its padded version"
        offsets.add(hits[0])
    assert len(offsets) > 3  # per-image shifts
    # EncoderLoss keeps the labels under a shift: a perfect decoder is off by at most `pad` pixels
    td = TensorDict(pixels=imgs, state=state, batch_size=[24])
    torch.manual_seed(0)
    out = EncoderLoss(DotDecoder(), pad=pad)(td)
    assert 0 < out["mae"].item() <= pad


def test_eval_mode_disables_augmentation_and_shapes():
    torch.manual_seed(0)
    enc = nn.Sequential(nn.Flatten(), nn.Linear(3 * H * W, 4))
    imgs, state = dot_images(6)
    td = TensorDict(pixels=imgs.view(2, 3, H, W, 3), state=state.view(2, 3, 4), batch_size=[2, 3])
    loss = EncoderLoss(enc, state_mirror=(PERM, SIGN), flip_prob=1.0, pad=2).eval()
    pred = enc(imgs.permute(0, 3, 1, 2).float() / 255)
    out = loss(td)
    torch.testing.assert_close(out["loss_encoder"], (pred - state).pow(2).mean())
    torch.testing.assert_close(out["mae"], (pred - state).abs().mean().detach())
    loss.train()
    out = loss(td)
    out["loss_encoder"].backward()
    assert all(p.grad is not None for p in enc.parameters())
    assert not out["mae"].requires_grad


def test_keys_and_errors():
    imgs, state = dot_images(4)
    td = TensorDict(image=imgs, label=state, batch_size=[4])
    loss = EncoderLoss(DotDecoder(), pad=0, in_key="image", target_key="label")
    assert loss.in_keys == ["image", "label"]
    assert loss(td)["loss_encoder"].item() == 0.0
    loss2 = EncoderLoss(DotDecoder(), pad=0)
    loss2.set_keys(pixels="image", state="label")
    assert loss2(td)["loss_encoder"].item() == 0.0
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss2.set_keys(action="a")
    with pytest.raises(ValueError, match="not a permutation"):
        EncoderLoss(DotDecoder(), state_mirror=([0, 0, 1, 2], SIGN))
    with pytest.raises(ValueError, match="width 4"):
        EncoderLoss(DotDecoder(), state_mirror=([0, 1], [1.0, 1.0]))(td.rename_key_("image", "pixels").rename_key_("label", "state"))
    with pytest.raises(ValueError, match="uint8 images must be HWC"):
        loss(TensorDict(image=imgs.permute(0, 3, 1, 2).contiguous(), label=state, batch_size=[4]))
    with pytest.raises(ValueError, match="'label' has shape"):
        loss(TensorDict(image=imgs, label=state[:, None].expand(4, 2, 4), batch_size=[4]))


def test_ensemble_members_learn_from_their_own_errors():
    from trakdis.modules import EncoderEnsemble

    imgs, state = dot_images(4)
    a, b = DotDecoder(), DotDecoder()
    with torch.no_grad():
        a.bias.fill_(1.0)
        b.bias.fill_(-1.0)
    loss = EncoderLoss(EncoderEnsemble([a, b]), state_mirror=(PERM, SIGN), flip_prob=0.5)
    out = loss(TensorDict({"pixels": imgs, "state": state}, batch_size=[4]))
    # each member is off by 1 everywhere: the loss is their own MSE (1), the mean estimate is exact
    assert out["loss_encoder"].item() == pytest.approx(1.0) and out["mae"].item() == pytest.approx(0.0)
    out["loss_encoder"].backward()
    # d/d bias of mean_m mean_i (err_m)^2 = 2 err_m / (members * dims): +-0.25 per dim
    torch.testing.assert_close(a.bias.grad, torch.full((4,), 0.25))
    torch.testing.assert_close(b.bias.grad, torch.full((4,), -0.25))
