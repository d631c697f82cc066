"""PickerOdometry: the env's picker motion reproduced exactly, the running-mean fusion, view gating,
the env transform equal to the offline filter, partial resets, errors."""
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torch import nn

from trakdis.transforms import PickerOdometry


def test_predict_reproduces_the_envs_picker_motion_with_clipping():
    from trakdis.envs import ClothEnv

    env = ClothEnv(task="ClothFold", horizon=40)
    obs, _ = env.reset(seed=3)
    odometry = PickerOdometry.for_task("ClothFold")
    pickers = torch.as_tensor(obs["state"][12:], dtype=torch.float32).view(2, 3)
    rng = np.random.default_rng(0)
    clipped = False
    for t in range(40):
        # random moves, out-of-range values (the env clips them), and a long push down onto z = 0
        action = rng.uniform(-1.5, 1.5, size=8) if t < 25 else np.array([0.3, -0.2, -1.0, -1, 0.0, 0.4, -1.0, -1])
        obs, *_ = env.step(action)
        pickers = odometry.predict(pickers, torch.as_tensor(action, dtype=torch.float32))
        true = torch.as_tensor(obs["state"][12:], dtype=torch.float32).view(2, 3)
        torch.testing.assert_close(pickers, true, atol=1e-5, rtol=0)
        clipped |= bool((true[:, 2] == 0).any())
    assert clipped  # the workspace floor was reached and reproduced


def test_filter_is_the_running_mean_of_the_views_carried_by_the_motion():
    # no clipping, every view fused: estimate_t = truth_t + mean_{s <= t} noise_s; corners untouched
    odometry = PickerOdometry([12, 15])
    g = torch.Generator().manual_seed(0)
    T = 30
    action = torch.rand(4, T, 8, generator=g) * 0.2 - 0.1
    truth = torch.zeros(4, T, 18)
    truth[:, 0, 12:] = torch.tensor([-0.1, -0.1, 0.1, 0.1, -0.1, 0.1])
    for t in range(1, T):
        truth[:, t, 12:] = truth[:, t - 1, 12:] + 8 * 0.0075 * action[:, t - 1].view(4, 2, 4)[..., :3].reshape(4, 6)
    truth[..., :12] = torch.randn(4, T, 12, generator=g)
    noise = torch.randn(4, T, 18, generator=g) * 0.02
    fused = odometry.filter(truth + noise, action)
    expected = truth[..., 12:] + noise[..., 12:].cumsum(1) / torch.arange(1, T + 1).view(1, T, 1)
    torch.testing.assert_close(fused[..., 12:], expected, atol=1e-5, rtol=0)
    assert torch.equal(fused[..., :12], (truth + noise)[..., :12])
    assert (fused - truth)[:, -10:, 12:].abs().mean() < 0.25 * noise[:, -10:, 12:].abs().mean()
    # time along another dim
    torch.testing.assert_close(odometry.filter((truth + noise).transpose(0, 1), action.transpose(0, 1), time_dim=0),
                               fused.transpose(0, 1))


def test_views_of_a_picker_out_of_the_image_are_not_fused():
    from trakdis.transforms import fixed_camera_matrix

    odometry = PickerOdometry([0], camera_matrix=fixed_camera_matrix("ClothFold", 32), image_size=32)
    seen, unseen = torch.tensor([[0.0, 0.0, 0.05]]), torch.tensor([[0.0, 0.0, 0.3]])  # centre; lifted out of view
    assert odometry.view.visible(seen.flatten()).item() and not odometry.view.visible(unseen.flatten()).item()
    still = torch.zeros(4)
    observed = torch.tensor([[0.05, 0.05, 0.05]])
    fused, count = odometry.fuse(seen, torch.tensor([1.0]), still, observed)
    torch.testing.assert_close(fused, (seen + observed) / 2) and torch.testing.assert_close(count, torch.tensor([2.0]))
    fused, count = odometry.fuse(unseen, torch.tensor([1.0]), still, observed)
    assert torch.equal(fused, unseen) and count.item() == 1.0


def test_a_close_near_the_source_corner_holds_its_estimate_at_the_picker_until_it_opens():
    # one picker (dims 12-14), its source corner c00 (dims 0-2); 3 cm hold radius; no motion, every view fused
    odometry = PickerOdometry([12], corner_starts=[0], hold_radius=0.03)
    T = 7
    est = torch.zeros(T, 15)
    est[:, 12:] = torch.tensor([0.02, 0.0, 0.01])  # the picker, 2.2 cm from the corner at the origin
    est[4:, :3] = torch.tensor([0.5, 0.5, 0.5])  # a far-off corner view from step 4 on (the lifted corner misread)
    grasp = torch.tensor([-1.0, 1.0, 1.0, 1.0, 1.0, -1.0, 1.0])  # action t: open, closed x4, open, closed
    action = torch.zeros(T, 4)
    action[:, 3] = grasp
    out = odometry.filter(est, action)
    picker = torch.tensor([0.02, 0.0, 0.01])
    # step t+1 holds when action t closes within reach of the corner in the estimate of step t
    held = [False, False, True, True, True, True, False]
    for t in range(T):
        expected = picker if held[t] else est[t, :3]
        torch.testing.assert_close(out[t, :3], expected, msg=f"step {t}")
    # the hold carries over the misread views (steps 4, 5) while closed, then lets go: step 6 reads the view again
    assert torch.equal(out[:, 12:], est[:, 12:])
    far = est.clone()
    far[:, :3] = torch.tensor([0.1, 0.0, 0.0])  # 8 cm away: a close holds nothing
    torch.testing.assert_close(odometry.filter(far, action), far)
    # off (the default): the estimates are the plain filter's
    torch.testing.assert_close(PickerOdometry([12]).filter(est, action), est)


def test_hold_radius_needs_its_corners_and_a_grasp_command():
    with pytest.raises(ValueError, match="needs a grasp command .* corner_starts"):
        PickerOdometry([12], hold_radius=0.03)
    with pytest.raises(ValueError, match="needs a grasp command"):
        PickerOdometry([12], corner_starts=[0], hold_radius=0.03, action_stride=3)
    with pytest.raises(ValueError, match="hold_radius must be a finite distance"):
        PickerOdometry([12], corner_starts=[0], hold_radius=float("nan"))
    # the task's fold plan names each picker's source corner: c00 on the diagonal folds, c0N and cNN on ClothFold
    assert PickerOdometry.for_task("ClothFoldDiagonalPinned", hold_radius=0.03).corner_starts == [0]
    assert PickerOdometry.for_task("ClothFold", hold_radius=0.03).corner_starts == [3, 9]


class _PixelMap(nn.Module):
    """A fixed linear map from a 32x32 image to an 18-dim 'estimate' (any deterministic encoder will do)."""

    def __init__(self):
        super().__init__()
        self.proj = nn.Linear(32 * 32 * 3, 18)
        nn.init.normal_(self.proj.weight, std=1e-4, generator=torch.Generator().manual_seed(0))
        nn.init.zeros_(self.proj.bias)

    def forward(self, pixels):
        return self.proj(pixels.float().flatten(1) / 255.0)


def _roll(picker_odometry: bool, actions, hold_radius: float = 0.0):
    from torchrl.envs.utils import step_mdp

    from trakdis.policies import make_acting_env

    env = make_acting_env("ClothFold", encoder=_PixelMap(), num_envs=2, seed=5, split="eval",
                          picker_odometry=picker_odometry, env_kwargs={"horizon": actions.shape[0]},
                          hold_radius=hold_radius)
    try:
        td = env.reset()
        out = [td["state_estimate"]]
        for action in actions[:-1]:
            td["action"] = action
            td = step_mdp(env.step(td))
            out.append(td["state_estimate"])
        return torch.stack(out, 1), td
    finally:
        env.close()


def test_env_transform_writes_what_the_offline_filter_computes():
    actions = torch.rand(6, 2, 8, generator=torch.Generator().manual_seed(1)) * 2 - 1
    raw, _ = _roll(False, actions)
    fused, td = _roll(True, actions)
    assert "picker_odometry_count" in td.keys() and td["picker_odometry_count"].shape == (2, 2)
    expected = PickerOdometry.for_task("ClothFold").filter(raw, actions.transpose(0, 1))
    torch.testing.assert_close(fused, expected, atol=1e-6, rtol=0)
    assert torch.equal(fused[..., :12], raw[..., :12]) and not torch.equal(fused[..., 12:], raw[..., 12:])
    # with the held corner (a radius that holds on every close): the env writes what the filter computes, too
    held, _ = _roll(True, actions, hold_radius=0.9)
    expected = PickerOdometry.for_task("ClothFold", hold_radius=0.9).filter(raw, actions.transpose(0, 1))
    torch.testing.assert_close(held, expected, atol=1e-6, rtol=0)
    assert not torch.equal(held[..., :12], raw[..., :12])
    with pytest.raises(ValueError, match="held corner is part of the picker odometry"):
        _roll(False, actions, hold_radius=0.03)


def test_partial_reset_keeps_the_running_envs_estimates():
    odometry = PickerOdometry([0])
    previous = TensorDict({"state_estimate": torch.ones(2, 3), "picker_odometry_count": torch.tensor([[4.0], [7.0]]),
                           "_reset": torch.tensor([[True], [False]])}, [2])
    fresh = TensorDict({"state_estimate": torch.zeros(2, 3)}, [2])
    out = odometry._reset(previous, fresh)
    assert out["state_estimate"].tolist() == [[0.0] * 3, [1.0] * 3]
    assert out["picker_odometry_count"].tolist() == [[1.0], [7.0]]
    full = odometry._reset(None, TensorDict({"state_estimate": torch.zeros(2, 3)}, [2]))
    assert full["picker_odometry_count"].tolist() == [[1.0], [1.0]]


def test_bad_inputs_name_what_is_wrong():
    from trakdis.policies import make_acting_env

    odometry = PickerOdometry([12, 15])
    with pytest.raises(ValueError, match="2 picker\\(s\\) x 4 dims = 8"):
        odometry.filter(torch.zeros(5, 18), torch.zeros(5, 4))
    with pytest.raises(ValueError, match="need >= 18 state dims"):
        odometry.filter(torch.zeros(5, 12), torch.zeros(5, 8))
    with pytest.raises(ValueError, match="differ in their batch or time dims"):
        odometry.filter(torch.zeros(5, 18), torch.zeros(4, 8))
    step_in = TensorDict({"state_estimate": torch.zeros(18)}, [])
    with pytest.raises(KeyError, match="'action' is missing"):
        odometry._step(step_in, step_in.clone())
    step_in["action"] = torch.zeros(8)
    with pytest.raises(KeyError, match="picker_odometry_count"):
        odometry._step(step_in, step_in.clone())
    with pytest.raises(RuntimeError, match="along an episode"):
        odometry(step_in)
    with pytest.raises(ValueError, match="one estimate key"):
        PickerOdometry([0], in_keys=["a", "b"])
    with pytest.raises(ValueError, match="low < high"):
        PickerOdometry([0], low=(0, 0, 0), high=(1, 1, 0))
    with pytest.raises(ValueError, match="needs an encoder"):
        make_acting_env("ClothFold", picker_odometry=True)
