import pytest
import torch
from dt_windows import random_window
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import TanhNormal

from trakdis.modules import (CausalTransformer, DTBackbone, StochasticDTActor, DTModelConfig, TransformerConfig, make_dt_actor,
                             recipe_hidden_action_dims)

S, A = 5, 3


def small_config(**kw):
    kw.setdefault("context_len", 6)
    return DTModelConfig(state_dim=S, action_dim=A, embed_dim=32, n_layer=2, n_head=4, **kw)


def window(b=4, k=6, *, generator=None, pad=None):
    return random_window(b, k, S, A, generator=generator, pad=pad)


def run(dt, td):
    return dt(td["observation"], td["action"], td["return_to_go"], td["timestep"], td["mask"])


def test_config_presets_and_validation():
    c = DTModelConfig.paper(18, 8)
    assert (c.embed_dim, c.n_layer, c.n_head, c.context_len, c.max_timestep) == (256, 10, 16, 30, 1024)
    assert DTModelConfig.paper(18, 8, context_len=5).context_len == 5
    d = DTModelConfig(18, 8)
    assert (d.embed_dim, d.n_layer, d.n_head, d.context_len, d.dropout, d.loc_bound, d.log_std_min) == (64, 2, 2, 20, 0.0, 5.0, -2.5)
    with pytest.raises(ValueError, match="divisible"):
        DTModelConfig(18, 8, embed_dim=30, n_head=4)
    with pytest.raises(ValueError, match="log_std_min"):
        DTModelConfig(18, 8, log_std_min=2.0, log_std_max=-5.0)
    with pytest.raises(ValueError, match="activation"):
        TransformerConfig(embed_dim=16, n_layer=1, n_head=2, activation="swish")
    with pytest.raises(ValueError, match="loc_bound"):
        DTModelConfig(18, 8, loc_bound=-1.0)
    assert DTModelConfig(18, 8, loc_bound=0.0).action_eps == 1e-6 and abs(DTModelConfig(18, 8, loc_bound=5.0).action_eps - 9.08e-5) < 1e-7


def test_shapes_and_extra_batch_dims():
    torch.manual_seed(0)
    dt = DTBackbone(small_config()).eval()
    td = window()
    h = run(dt, td)
    assert h.shape == (4, 6, 32)
    td2 = td.reshape(2, 2, 6)
    h2 = dt(td2["observation"], td2["action"], td2["return_to_go"], td2["timestep"], td2["mask"])
    assert h2.shape == (2, 2, 6, 32)
    torch.testing.assert_close(h2.reshape(4, 6, 32), h)


def test_shape_and_timestep_errors_name_the_key():
    dt = DTBackbone(small_config(max_timestep=10)).eval()
    td = window()
    with pytest.raises(ValueError, match="'action' has shape"):
        dt(td["observation"], td["action"][..., :2], td["return_to_go"], td["timestep"], td["mask"])
    with pytest.raises(ValueError, match="'return_to_go'"):
        dt(td["observation"], td["action"], td["return_to_go"][..., 0], td["timestep"], td["mask"])
    with pytest.raises(TypeError, match="'mask' must be bool"):
        dt(td["observation"], td["action"], td["return_to_go"], td["timestep"], td["mask"].long())
    with pytest.raises(ValueError, match="max_timestep"):
        dt(td["observation"], td["action"], td["return_to_go"], td["timestep"] + 8, td["mask"])
    # out-of-range timesteps on padded steps are ignored
    td["timestep"][:, 0] = 999
    td["mask"][:, 0] = False
    run(dt, td)


def test_causality_future_tokens_never_change_earlier_predictions():
    torch.manual_seed(0)
    dt = DTBackbone(small_config()).eval()
    td = window()
    h = run(dt, td)
    for t in range(6):
        td2 = td.clone()
        g = torch.Generator().manual_seed(t)
        td2["observation"][:, t + 1 :] = torch.randn(td2["observation"][:, t + 1 :].shape, generator=g)
        td2["return_to_go"][:, t + 1 :] += 3.0
        td2["action"][:, t:] = -td2["action"][:, t:]  # a_t comes after s_t
        h2 = run(dt, td2)
        torch.testing.assert_close(h2[:, : t + 1], h[:, : t + 1], rtol=0, atol=1e-5)
        if t < 5:
            assert not torch.allclose(h2[:, t + 1 :], h[:, t + 1 :], atol=1e-3)


def test_past_tokens_do_change_predictions():
    torch.manual_seed(0)
    dt = DTBackbone(small_config()).eval()
    td = window()
    td2 = td.clone()
    td2["action"][:, 2] += 0.5
    assert not torch.allclose(run(dt, td2)[:, 3:], run(dt, td)[:, 3:], atol=1e-4)


def test_hidden_action_dims_are_not_read_and_the_others_are():
    torch.manual_seed(0)
    dt = DTBackbone(small_config(hidden_action_dims=(1,))).eval()
    td = window()
    hidden, shown = td.clone(), td.clone()
    hidden["action"][..., 1] = torch.randn(hidden["action"][..., 1].shape)
    shown["action"][..., 0] += 0.5
    torch.testing.assert_close(run(dt, hidden), run(dt, td), rtol=0, atol=0)
    assert not torch.allclose(run(dt, shown)[:, 1:], run(dt, td)[:, 1:], atol=1e-4)
    # derived from the config, not saved with the weights: a plain DT's state dict loads into it
    assert set(dt.state_dict()) == set(DTBackbone(small_config()).state_dict())


def test_hidden_action_dims_config():
    assert DTModelConfig(18, 8).hidden_action_dims is None  # a DT built directly hides nothing
    assert DTModelConfig(18, 8, hidden_action_dims=[3, 7]).hidden_action_dims == (3, 7)  # e.g. from config.json
    for bad in ((8,), (-1,), (3, 3)):
        with pytest.raises(ValueError, match="hidden_action_dims"):
            DTModelConfig(18, 8, hidden_action_dims=bad)
    # the recipes fill in the task's grasp dims unless the config sets its own (empty: none)
    assert DTModelConfig().for_task(18, 8, 100, hidden_action_dims=(3, 7)).hidden_action_dims == (3, 7)
    assert DTModelConfig(hidden_action_dims=()).for_task(18, 8, 100, hidden_action_dims=(3, 7)).hidden_action_dims == ()
    assert DTModelConfig().for_task(18, 8, 100).hidden_action_dims == ()
    with pytest.raises(ValueError, match="hidden_action_dims"):
        DTModelConfig(hidden_action_dims=(3, 7)).for_task(15, 4, 100)
    # the recipes' default: ClothFold's grasp commands; none on the diagonal folds
    assert recipe_hidden_action_dims("ClothFold") == (3, 7)
    assert recipe_hidden_action_dims("ClothFoldDiagonalPinned") == recipe_hidden_action_dims("ClothFoldDiagonalUnpinned") == ()


def test_padding_content_never_changes_valid_outputs():
    torch.manual_seed(0)
    dt = DTBackbone(small_config()).eval()
    pad = [0, 2, 5, 3]
    td = window(pad=pad)
    h = run(dt, td)
    td2 = td.clone()
    td2["observation"][~td2["mask"]] = float("nan")
    td2["action"][~td2["mask"]] = float("inf")
    td2["return_to_go"][~td2["mask"]] = 1e6
    td2["timestep"][~td2["mask"]] = 5000
    h2 = run(dt, td2)
    assert torch.isfinite(h2).all()
    torch.testing.assert_close(h2[td["mask"]], h[td["mask"]], rtol=0, atol=1e-5)
    # a left-padded window equals the unpadded, shorter window
    for i, p in enumerate(pad):
        short = td[i : i + 1, p:]
        torch.testing.assert_close(run(dt, short)[0], h[i, p:], rtol=0, atol=1e-5)


def test_all_true_mask_fast_path_matches_explicit_mask():
    torch.manual_seed(0)
    tr = CausalTransformer(TransformerConfig(embed_dim=32, n_layer=2, n_head=4)).eval()
    x = torch.randn(3, 9, 32)
    torch.testing.assert_close(tr(x, torch.ones(3, 9, dtype=torch.bool)), tr(x), rtol=0, atol=1e-5)


def test_actor_head_bounds_and_distribution():
    torch.manual_seed(0)
    cfg = small_config()
    net = StochasticDTActor(cfg).eval()
    td = window()
    with torch.no_grad():
        net.head_log_std.bias.fill_(100.0)
        _, scale_hi = net(td["observation"], td["action"], td["return_to_go"], td["timestep"], td["mask"])
        net.head_log_std.bias.fill_(-100.0)
        _, scale_lo = net(td["observation"], td["action"], td["return_to_go"], td["timestep"], td["mask"])
    torch.testing.assert_close(scale_hi, torch.full_like(scale_hi, cfg.log_std_max).exp())
    torch.testing.assert_close(scale_lo, torch.full_like(scale_lo, cfg.log_std_min).exp())

    actor = make_dt_actor(cfg, observation_key="state")
    assert actor.in_keys == ["state", "action", "return_to_go", "timestep", "mask"]
    td = window().rename_key_("observation", "state")
    dist = actor.get_dist(td)
    assert isinstance(dist, TanhNormal)
    assert dist.log_prob(td["action"]).shape == (4, 6)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = actor(td.clone())
    torch.testing.assert_close(out["action"], torch.tanh(out["loc"]))
    with set_exploration_type(ExplorationType.RANDOM):
        torch.manual_seed(1)
        s1 = actor(td.clone())["action"]
        torch.manual_seed(2)
        s2 = actor(td.clone())["action"]
    assert not torch.allclose(s1, s2)
    assert s1.abs().max() <= 1.0


def test_gradients_reach_all_actor_parameters():
    torch.manual_seed(0)
    actor = make_dt_actor(small_config())
    td = window(pad=[0, 1, 2, 3])
    actor.get_dist(td).log_prob(td["action"]).mean().backward()
    no_grad = [n for n, p in actor.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert no_grad == []


def test_training_mode_with_dropout_keeps_causality_and_padding_invariance():
    # same seed -> same dropout masks; attention with dropout must still be causal and
    # blind to padded content (the eval-mode tests above go through SDPA)
    torch.manual_seed(0)
    dt = DTBackbone(small_config(context_len=40, dropout=0.2, attn_dropout=0.3)).train()
    pad = [0, 7, 39, 20]
    td = window(k=40, pad=pad)
    torch.manual_seed(1)
    h = run(dt, td)
    td2 = td.clone()
    td2["observation"][~td2["mask"]] = float("nan")
    td2["action"][~td2["mask"]] = float("inf")
    td2["return_to_go"][~td2["mask"]] = 1e6
    torch.manual_seed(1)
    h2 = run(dt, td2)
    assert torch.isfinite(h2).all()
    torch.testing.assert_close(h2[td["mask"]], h[td["mask"]], rtol=0, atol=1e-5)
    td3 = td.clone()
    td3["observation"][:, 30:] += 1.0
    td3["action"][:, 29:] = -td3["action"][:, 29:]  # a_29 comes after s_29; a_39 is never seen
    torch.manual_seed(1)
    h3 = run(dt, td3)
    torch.testing.assert_close(h3[:, :30], h[:, :30], rtol=0, atol=1e-5)
    assert not torch.allclose(h3[:, 30:], h[:, 30:], atol=1e-3)


def test_actor_takes_float64_and_names_empty_or_non_float_inputs():
    """Empty batches and float64 windows used to fail inside torch (reshape / matmul dtype errors)."""
    actor = make_dt_actor(small_config(), observation_key="observation").eval()
    td = window()
    td64 = td.clone()
    for key in ("observation", "action", "return_to_go"):
        td64[key] = td[key].double()
    # float64 windows are cast to the model's dtype, as DTActingPolicy already did when acting
    torch.testing.assert_close(actor.get_dist(td64).root_dist.loc, actor.get_dist(td).root_dist.loc)
    assert actor(td64.clone())["action"].dtype == torch.float32
    with pytest.raises(ValueError, match=r"empty input: 'observation' has shape \(0, 6, 5\)"):
        actor(td[:0].clone())
    with pytest.raises(ValueError, match=r"empty input: 'observation' has shape \(4, 0, 5\)"):
        actor.get_dist(td[:, :0].clone())
    bad = td.clone()
    bad["observation"] = torch.ones(4, 6, S, dtype=torch.long)
    with pytest.raises(TypeError, match="'observation' must be a floating-point tensor, got torch.int64"):
        actor(bad)
