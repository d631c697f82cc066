"""The image baselines' modules: ImageTrunk, the BC actor, and a trunk in front of a BC or DT head."""
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from trakdis.modules import (BCConfig, DTActingPolicy, DTModelConfig, ImageTrunk, ImageTrunkConfig, make_bc_actor,
                             make_dt_actor, with_image_trunk)
from trakdis.objectives import BehaviourCloningLoss, MaskedOnlineDTLoss

SMALL = dict(channels=(4, 4, 4, 4), hidden_dim=16)


def pixels(*shape, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (*shape, 32, 32, 3), dtype=torch.uint8, generator=g)


def test_trunk_shapes_keys_and_shift_in_training_only():
    torch.manual_seed(0)  # the weights too: with some draws the tiny trunk's ReLUs are all dead and its output constant
    trunk = ImageTrunk(8, pad=2, **SMALL)
    x = pixels(2, 3)
    assert not torch.allclose(trunk.eval()(x)[0, 0], trunk.eval()(x)[1, 2])  # the output depends on the image
    assert trunk(x).shape == (2, 3, 8) and trunk(x[0, 0]).shape == (8,)
    assert trunk(x.movedim(-1, -3).float() / 255).shape == (2, 3, 8)  # float CHW too
    trunk.eval()
    assert torch.equal(trunk(x), trunk(x))  # eval: no augmentation
    trunk.train()
    torch.manual_seed(0)
    assert not torch.allclose(trunk(x), trunk.eval()(x))  # training: random shift
    assert ImageTrunk(8, pad=0, **SMALL).train()(x).shape == (2, 3, 8)
    again = ImageTrunk.from_config(trunk.config)
    again.load_state_dict(trunk.state_dict())
    assert torch.equal(again.eval()(x), trunk.eval()(x))
    assert trunk.config["feature_dim"] == 8 and trunk.config["pad"] == 2
    assert isinstance(ImageTrunkConfig(feature_dim=5, channels=(4, 4, 4, 4), hidden_dim=8).make(), ImageTrunk)


def test_trunk_bad_input_names_shape():
    trunk = ImageTrunk(8, **SMALL)
    with pytest.raises(ValueError, match="uint8 images must be HWC"):
        trunk(torch.zeros(2, 3, 32, 32, dtype=torch.uint8))
    with pytest.raises(ValueError, match="resize them first"):
        trunk(torch.zeros(2, 16, 16, 3, dtype=torch.uint8))
    with pytest.raises(ValueError, match="feature_dim"):
        ImageTrunk(0)
    with pytest.raises(ValueError, match="pad"):
        ImageTrunk(8, pad=-1)


def test_bc_actor_keys_shapes_and_initial_std():
    cfg = BCConfig(feature_dim=8, action_dim=4, hidden_dims=(16,), init_log_std=0.0)
    actor = make_bc_actor(cfg)
    td = TensorDict({"image_features": torch.randn(5, 8)}, [5])
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = actor(td)
    assert out["action"].shape == (5, 4) and out["loc"].shape == (5, 4)
    assert torch.allclose(out["scale"], torch.ones(5, 4), atol=1e-5)  # log-std starts at init_log_std
    assert torch.allclose(out["action"], torch.tanh(out["loc"]))
    assert out["action"].abs().max() <= 1 and out["loc"].abs().max() < cfg.loc_bound
    with pytest.raises(ValueError, match="image_features"):
        actor(TensorDict({"image_features": torch.randn(5, 7)}, [5]))
    with pytest.raises(ValueError, match="init_log_std"):
        BCConfig(8, 4, init_log_std=5.0)
    with pytest.raises(ValueError, match="action_dim"):
        BCConfig(8, 0)
    with pytest.raises(TypeError, match="with_image_trunk"):
        with_image_trunk(torch.nn.Linear(2, 2), ImageTrunk(8, **SMALL))


def test_bc_image_gradients_reach_the_trunk_and_a_tiny_batch_is_overfitted():
    torch.manual_seed(0)
    trunk = ImageTrunk(8, pad=0, **SMALL)
    cfg = BCConfig(8, 4, hidden_dims=(32,))
    actor = with_image_trunk(make_bc_actor(cfg), trunk)
    target = torch.rand(6, 4) * 1.6 - 0.8
    target[:, 3] = torch.tensor([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])  # saturated grasp commands
    batch = TensorDict({"pixels": pixels(6), "action": target}, [6])
    loss = BehaviourCloningLoss(actor, action_eps=cfg.action_eps)
    out = loss(batch)
    out["loss_bc"].backward()
    assert trunk.encoder.convs[0].weight.grad.abs().sum() > 0
    first = {"loss_bc": out["loss_bc"].item(), "action_mse": out["action_mse"].item()}
    opt = torch.optim.Adam(loss.parameters(), lr=3e-3)
    for _ in range(120):
        out = loss(batch)
        opt.zero_grad()
        out["loss_bc"].backward()
        opt.step()
    # the NLL fits the saturated grasp commands slowly (their pre-tanh targets sit at the mean's
    # soft bound), so its mean action improves more slowly than the squared error's
    assert out["loss_bc"].item() < first["loss_bc"] - 10 and out["action_mse"].item() < 0.8 * first["action_mse"]
    torch.manual_seed(0)
    mse = BehaviourCloningLoss(with_image_trunk(make_bc_actor(cfg), ImageTrunk(8, pad=0, **SMALL)), loss_function="mse")
    opt = torch.optim.Adam(mse.parameters(), lr=3e-3)
    for _ in range(100):
        out = mse(batch)
        opt.zero_grad()
        out["loss_bc"].backward()
        opt.step()
    assert out["loss_bc"].item() < 0.05
    assert "action" in loss.in_keys and "pixels" in loss.in_keys


def _window(b, k, action_dim, seed=0):
    g = torch.Generator().manual_seed(seed)
    mask = torch.ones(b, k, dtype=torch.bool)
    mask[0, :1] = False  # one left-padded window
    return TensorDict({"pixels": pixels(b, k, seed=seed), "action": torch.rand(b, k, action_dim, generator=g) * 2 - 1,
                       "return_to_go": -torch.rand(b, k, 1, generator=g), "timestep": torch.arange(k).expand(b, k).clone(),
                       "mask": mask}, [b, k])


def test_dt_image_trains_end_to_end():
    torch.manual_seed(0)
    trunk = ImageTrunk(8, pad=1, **SMALL)
    cfg = DTModelConfig(state_dim=8, action_dim=4, embed_dim=16, n_layer=1, n_head=1, context_len=3, dropout=0.0,
                        attn_dropout=0.0, loc_bound=5.0)
    head = make_dt_actor(cfg, observation_key="image_features")
    actor = with_image_trunk(head, trunk)
    assert actor.in_keys[0] == "pixels" and "image_features" not in actor.in_keys
    batch = _window(4, 3, 4)
    loss = MaskedOnlineDTLoss(actor, lambda_entropy=0.0, action_eps=cfg.action_eps)
    opt = torch.optim.Adam(loss.parameters(), lr=3e-3)
    before = [p.detach().clone() for p in trunk.parameters()]
    first = None
    for _ in range(60):
        out = loss(batch)
        first = float(out["loss_nll"]) if first is None else first
        opt.zero_grad()
        out["loss_nll"].backward()
        opt.step()
    assert float(out["loss_nll"]) < first - 1.0
    assert any(not torch.equal(a, b) for a, b in zip(before, trunk.parameters()))


def test_dt_image_acting_on_env_features_equals_the_training_actor():
    """The trunk in the env (features per step) + DTActingPolicy on the head computes what the
    training actor computes on the window of images (the CNN reads each frame on its own)."""
    torch.manual_seed(0)
    trunk = ImageTrunk(8, **SMALL).eval()
    cfg = DTModelConfig(state_dim=8, action_dim=4, embed_dim=16, n_layer=1, n_head=1, context_len=3)
    head = make_dt_actor(cfg, observation_key="image_features").eval()
    actor = with_image_trunk(head, trunk).eval()
    policy = DTActingPolicy(head)
    frames, rtg = pixels(1, 3, seed=3), torch.tensor([[-1.0], [-0.8], [-0.5]])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        for t in range(3):
            step = TensorDict({"image_features": trunk(frames[0, t]).unsqueeze(0), "return_to_go": rtg[t].view(1, 1),
                               "step_count": torch.tensor([[t]])}, [1])
            acted = policy(step)["action"]
        actions = torch.zeros(1, 3, 4)
        actions[0, :2] = policy._act[0, :2]  # the actions the policy took before the last step
        window = TensorDict({"pixels": frames, "action": actions, "return_to_go": rtg.view(1, 3, 1),
                             "timestep": torch.arange(3).view(1, 3), "mask": torch.ones(1, 3, dtype=torch.bool)}, [1, 3])
        loc = actor.get_dist_params(window)["loc"][:, -1]
    torch.testing.assert_close(acted, torch.tanh(loc), atol=1e-5, rtol=1e-4)
