"""The grasp head: GraspConditionedTanhNormal, the DT actor that outputs it, and the losses and acting on it."""
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import TanhNormal

from trakdis.modules import (DTActingPolicy, DTModelConfig, GraspConditionedTanhNormal, copy_teacher_weights,
                             make_dt_actor, picker_of_dims)
from trakdis.objectives import DTDistillationLoss, MaskedOnlineDTLoss

A, GRASP = 8, (3, 7)  # two pickers: (dx, dy, dz, pick) each


def random_dist(*batch, seed=0):
    g = torch.Generator().manual_seed(seed)
    loc = torch.randn(*batch, 2, A, generator=g)
    scale = torch.rand(*batch, 2, A, generator=g) * 0.5 + 0.1
    logits = torch.randn(*batch, len(GRASP), generator=g) * 2
    return GraspConditionedTanhNormal(loc, scale, logits, grasp_dims=GRASP)


def test_picker_of_dims():
    assert picker_of_dims(8, (3, 7)) == (0, 0, 0, 0, 1, 1, 1, 1)
    assert picker_of_dims(5, (1,)) == (0, 0, 0, 0, 0)
    for bad in ((), (7, 3), (3, 3), (8,), (-1,)):
        with pytest.raises(ValueError, match="grasp_dims"):
            picker_of_dims(8, bad)


def test_log_prob_is_a_bernoulli_times_the_grasp_branchs_tanh_normal():
    d = random_dist(5)
    value = torch.rand(5, A) * 1.8 - 0.9
    value[:, 3] = torch.tensor([1.0, -1.0, 1.0, -1.0, 0.999])
    value[:, 7] = torch.tensor([-1.0, -1.0, 1.0, 1.0, -0.999])
    closed = value[:, list(GRASP)] > 0
    expected = torch.distributions.Bernoulli(logits=d.grasp_logits).log_prob(closed.float()).sum(-1)
    for p, dims in enumerate(([0, 1, 2], [4, 5, 6])):
        branch = closed[:, p].long()
        loc = d.loc[torch.arange(5), branch][:, dims]
        scale = d.scale[torch.arange(5), branch][:, dims]
        expected = expected + TanhNormal(loc, scale, low=-1.0, high=1.0).log_prob(value[:, dims])
    torch.testing.assert_close(d.log_prob(value), expected, rtol=1e-5, atol=1e-4)


def test_movement_is_conditioned_on_the_grasp_decision():
    d = random_dist(3)
    action = d.deterministic_sample
    closed = d.grasp_logits > 0
    assert torch.equal(action[:, list(GRASP)], closed.float() * 2 - 1)
    for p, dims in enumerate(([0, 1, 2], [4, 5, 6])):
        loc = d.loc[torch.arange(3), closed[:, p].long()][:, dims]
        torch.testing.assert_close(action[:, dims], torch.tanh(loc))
    # the branch not taken never moves the picker: change it, the action stays
    other = d.loc.clone()
    for i in range(3):
        other[i, 1 - closed[i, 0].long(), :3] += 10.0
    same = GraspConditionedTanhNormal(other, d.scale, d.grasp_logits, grasp_dims=GRASP).deterministic_sample
    torch.testing.assert_close(same, action)
    assert torch.equal(d.mode, action)


def test_sample_frequencies_and_branches():
    torch.manual_seed(0)
    loc = torch.zeros(1, 2, A)
    loc[0, 0, :3], loc[0, 1, :3] = -3.0, 3.0  # picker 0 moves down when open, up when closed
    scale = torch.full((1, 2, A), 1e-3)
    logits = torch.tensor([[math.log(0.3 / 0.7), 0.0]])
    d = GraspConditionedTanhNormal(loc, scale, logits, grasp_dims=GRASP)
    x = d.sample((4000,))
    assert x.shape == (4000, 1, A)
    closed = x[..., 3] > 0
    assert abs(closed.float().mean().item() - 0.3) < 0.03
    assert torch.all(x[..., 0][closed] > 0.99) and torch.all(x[..., 0][~closed] < -0.99)
    assert set(x[..., 3].unique().tolist()) == {-1.0, 1.0}


def test_entropy_estimate_matches_minus_mean_log_prob_and_has_gradients():
    torch.manual_seed(0)
    d = random_dist(2, seed=1)
    exact_grasp = torch.distributions.Bernoulli(logits=d.grasp_logits).entropy().sum(-1)
    torch.testing.assert_close(d.grasp_entropy(), exact_grasp)
    mc = -d.log_prob(d.sample((20000,))).mean(0)
    torch.testing.assert_close(d.entropy_estimate(20000), mc, rtol=0, atol=0.05)
    loc = d.loc.clone().requires_grad_()
    logits = d.grasp_logits.clone().requires_grad_()
    GraspConditionedTanhNormal(loc, d.scale, logits, grasp_dims=GRASP).entropy_estimate(2).sum().backward()
    assert logits.grad.abs().sum() > 0 and loc.grad.abs().sum() > 0


def test_bad_parameters_are_refused():
    d = random_dist(2)
    with pytest.raises(ValueError, match="loc and scale"):
        GraspConditionedTanhNormal(torch.zeros(2, 3, A), torch.ones(2, 3, A), d.grasp_logits, grasp_dims=GRASP)
    with pytest.raises(ValueError, match="grasp_logits"):
        GraspConditionedTanhNormal(d.loc, d.scale, d.grasp_logits[:, :1], grasp_dims=GRASP)
    with pytest.raises(ValueError, match=r"\[-1, 1\]"):
        GraspConditionedTanhNormal(d.loc, d.scale, d.grasp_logits, grasp_dims=GRASP, low=0.0)


# -- the actor ------------------------------------------------------------------------------------
S, K = 6, 4


def grasp_config(**kw):
    return DTModelConfig(state_dim=S, action_dim=A, embed_dim=16, n_layer=1, n_head=2, context_len=K,
                         max_timestep=32, grasp_head=True, grasp_dims=GRASP, **kw)


def window(b=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    action = torch.rand(b, K, A, generator=g) * 2 - 1
    action[..., list(GRASP)] = torch.sign(action[..., list(GRASP)])
    return TensorDict({"state": torch.randn(b, K, S, generator=g), "action": action,
                       "return_to_go": torch.randn(b, K, 1, generator=g),
                       "timestep": torch.arange(K).expand(b, K), "mask": torch.ones(b, K, dtype=torch.bool)}, [b, K])


def test_config_needs_and_fills_grasp_dims():
    with pytest.raises(ValueError, match="grasp_dims"):
        DTModelConfig(state_dim=S, action_dim=A, grasp_head=True)
    with pytest.raises(ValueError, match="grasp_dims"):
        DTModelConfig(state_dim=S, action_dim=A, grasp_head=True, grasp_dims=(3, 9))
    with pytest.raises(ValueError, match="hidden from the action tokens"):
        DTModelConfig(grasp_head=True).for_task(S, A, horizon=10, hidden_action_dims=GRASP, grasp_dims=GRASP)
    cfg = DTModelConfig(grasp_head=True).for_task(S, A, horizon=10, grasp_dims=GRASP)
    assert cfg.grasp_dims == GRASP
    assert DTModelConfig().for_task(S, A, horizon=10, grasp_dims=GRASP).grasp_dims is None  # no head, no dims


def test_actor_outputs_the_grasp_distribution_and_trains_every_head():
    torch.manual_seed(0)
    actor = make_dt_actor(grasp_config(), observation_key="state")
    td = window()
    dist = actor.get_dist(td)
    assert isinstance(dist, GraspConditionedTanhNormal)
    assert dist.loc.shape == (3, K, 2, A) and dist.grasp_logits.shape == (3, K, 2)
    loss = MaskedOnlineDTLoss(actor, lambda_entropy=0.1, action_eps=grasp_config().action_eps)
    out = loss(td)
    assert torch.isfinite(out["loss_nll"]) and torch.isfinite(out["entropy"])
    (out["loss_nll"] + out["loss_entropy"]).backward()
    net = actor.module[0].module
    for layer in (net.head_loc, net.head_log_std, net.head_grasp):
        assert layer.weight.grad.abs().sum() > 0


def test_imitation_learns_the_branch_of_the_label():
    # one state, two labels: close-and-lift and open-and-hover. A factorised policy averages them;
    # the grasp head keeps each movement in its own branch and the grasp probability at the mix.
    torch.manual_seed(0)
    cfg = grasp_config()
    actor = make_dt_actor(cfg, observation_key="state")
    td = window(b=8)
    td["state"] = torch.zeros_like(td["state"])
    td["return_to_go"] = torch.zeros_like(td["return_to_go"])
    lift = torch.zeros(A)
    lift[2], lift[3], lift[7] = 0.9, 1.0, -1.0
    hover = torch.zeros(A)
    hover[2], hover[3], hover[7] = 0.0, -1.0, -1.0
    td["action"] = torch.stack([lift if i < 3 else hover for i in range(8)])[:, None].expand(8, K, A).clone()
    td["mask"][:, :-1] = False  # one-step windows: no earlier action token tells the labels apart
    loss = MaskedOnlineDTLoss(actor, lambda_entropy=0.0, action_eps=cfg.action_eps)
    opt = torch.optim.Adam(actor.parameters(), lr=1e-2)
    for _ in range(300):
        opt.zero_grad()
        loss(td)["loss_nll"].backward()
        opt.step()
    with torch.no_grad():
        dist = actor.get_dist(td)
    p_close = torch.sigmoid(dist.grasp_logits[0, -1, 0]).item()
    assert abs(p_close - 3 / 8) < 0.05
    assert dist.deterministic_sample[0, -1, 3] == -1.0  # unsure: stays open ...
    assert abs(dist.deterministic_sample[0, -1, 2].item()) < 0.1  # ... and hovers, no lift
    assert dist.movement_given(td["action"])[0, -1, 2] > 0.8  # when it closes, it lifts


@pytest.mark.parametrize("mode", ["window", "kv_cache"])
def test_acting_equals_the_training_forward(mode):
    torch.manual_seed(0)
    actor = make_dt_actor(grasp_config(), observation_key="state").eval()
    policy = DTActingPolicy(actor, mode=mode)
    g = torch.Generator().manual_seed(1)
    steps = []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for t in range(K):
            td = TensorDict(state=torch.randn(2, S, generator=g), return_to_go=torch.randn(2, 1, generator=g),
                            step_count=torch.full((2, 1), t), batch_size=[2])
            steps.append(policy(td))
    traj = torch.stack(steps, 1)
    ref = TensorDict({"state": traj["state"], "action": traj["action"], "return_to_go": traj["return_to_go"],
                      "timestep": traj["step_count"][..., 0], "mask": torch.ones(2, K, dtype=torch.bool)}, [2, K])
    with torch.no_grad():
        dist = actor.get_dist(ref)
    # the grasps switch at the median of their switch time, from the probabilities along the episode
    stay, closed = torch.ones(2, len(GRASP)), torch.zeros(2, len(GRASP), dtype=torch.bool)
    for t in range(K):
        p = torch.sigmoid(dist.grasp_logits[:, t])
        stay = stay * torch.where(closed, p, 1 - p)
        switch = stay <= 0.5
        stay[switch], closed = 1.0, closed ^ switch
        expected = GraspConditionedTanhNormal(dist.loc[:, t], dist.scale[:, t], dist.grasp_logits[:, t],
                                              grasp_dims=GRASP).action_for(closed)
        torch.testing.assert_close(traj["action"][:, t], expected, rtol=0, atol=1e-5)
    assert set(traj["action"][..., list(GRASP)].unique().tolist()) <= {-1.0, 1.0}
    with set_exploration_type(ExplorationType.RANDOM):
        sampled = policy(steps[0].clone())["action"]
    assert sampled.shape == (2, A)


def copied_student():
    """A grasp-head teacher (seed 0) and its weight-copied student, which reads ``"state_estimate"``."""
    torch.manual_seed(0)
    teacher = make_dt_actor(grasp_config(), observation_key="state")
    return copy_teacher_weights(make_dt_actor(grasp_config(), observation_key="state_estimate"), teacher), teacher


@pytest.mark.parametrize("loss_function", ["nll", "mse"])
@pytest.mark.parametrize("teacher_context", ["window", "step"])
def test_distillation_with_a_grasp_head(loss_function, teacher_context):
    student, teacher = copied_student()
    td = window()
    td["state_estimate"] = td["state"].clone()
    loss = DTDistillationLoss(student, teacher, loss_function=loss_function, teacher_context=teacher_context,
                              grasp_labels="decision")
    out = loss(td)
    assert torch.isfinite(out["loss_distill"])
    if teacher_context == "window":  # the copy on the teacher's own inputs agrees with it
        assert out["teacher_student_mse"] == 0
    out["loss_distill"].backward()
    assert student.module[0].module.head_grasp.weight.grad is not None
    if loss_function == "mse":  # movement error in the teacher's branch + the grasps' cross-entropy
        with torch.no_grad():
            t_action = loss.teacher_dist(td)[0]
            s = student.get_dist(td.select(*student.in_keys))
            move = ((s.movement_given(t_action) - t_action) ** 2 * s.movement_mask).sum(-1)
            bce = torch.nn.functional.binary_cross_entropy_with_logits(
                s.grasp_logits, (t_action[..., list(GRASP)] > 0).float(), reduction="none").sum(-1)
        torch.testing.assert_close(out["loss_distill"].detach(), (move + bce).mean())
    with pytest.raises(ValueError, match="kl_coef"):
        DTDistillationLoss(student, teacher, kl_coef=0.1)(td)


@pytest.mark.parametrize("loss_function", ["nll", "mse"])
def test_soft_imitation_of_a_sure_teacher_is_the_loss_of_its_action(loss_function):
    # a teacher sure of every grasp: its probabilities are its decisions, the other branch weighs nothing
    student, teacher = random_dist(4, 3, seed=1), random_dist(4, 3, seed=2)
    teacher = GraspConditionedTanhNormal(teacher.loc, teacher.scale, teacher.grasp_logits.sign() * 40.0,
                                         grasp_dims=GRASP)
    action = teacher.deterministic_sample
    if loss_function == "nll":
        expected = -student.log_prob(action.clamp(-1 + 1e-6, 1 - 1e-6))
    else:
        expected = ((student.movement_given(action) - action) ** 2 * student.movement_mask).sum(-1) + \
            torch.nn.functional.binary_cross_entropy_with_logits(
                student.grasp_logits, (action[..., list(GRASP)] > 0).float(), reduction="none").sum(-1)
    got = student.soft_imitation_loss(teacher, loss_function=loss_function)
    assert got.shape == (4, 3)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-4)


def test_soft_imitation_keeps_the_teachers_grasp_probabilities():
    # an unsure teacher (p 0.3 and 0.8): fitted to its probabilities the student keeps them; fitted to its
    # more likely grasps (the decision labels) it learns 0 and 1
    t = random_dist(seed=3)
    teacher = GraspConditionedTanhNormal(t.loc, t.scale, torch.tensor([0.3, 0.8]).logit(), grasp_dims=GRASP)
    fitted = {}
    for labels in ("probability", "decision"):
        logits = torch.zeros(2, requires_grad=True)
        opt = torch.optim.Adam([logits], lr=0.1)
        for _ in range(600):
            student = GraspConditionedTanhNormal(t.loc, t.scale, logits, grasp_dims=GRASP)
            loss = (student.soft_imitation_loss(teacher) if labels == "probability"
                    else -student.log_prob(teacher.deterministic_sample.clamp(-1 + 1e-6, 1 - 1e-6)))
            opt.zero_grad()
            loss.backward()
            opt.step()
        fitted[labels] = torch.sigmoid(logits.detach())
    torch.testing.assert_close(fitted["probability"], torch.tensor([0.3, 0.8]), rtol=0, atol=1e-3)
    assert fitted["decision"][0] < 0.05 and fitted["decision"][1] > 0.95


def test_soft_imitation_weighs_each_branch_by_the_teachers_probability():
    # the movement term of each branch, by hand: p(open) x branch 0's NLL + p(closed) x branch 1's
    student, teacher = random_dist(seed=4), random_dist(seed=5)
    got = student.soft_imitation_loss(teacher)
    p = torch.sigmoid(teacher.grasp_logits)
    expected = torch.nn.functional.binary_cross_entropy_with_logits(student.grasp_logits, p, reduction="none").sum()
    for picker, dims in enumerate(([0, 1, 2], [4, 5, 6])):
        for branch, weight in ((0, 1 - p[picker]), (1, p[picker])):
            target = torch.tanh(teacher.loc[branch, dims]).clamp(-1 + 1e-6, 1 - 1e-6)
            nll = -TanhNormal(student.loc[branch, dims], student.scale[branch, dims], low=-1.0,
                              high=1.0).log_prob(target)
            expected = expected + weight * nll
    torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-3)
    with pytest.raises(ValueError, match="loss_function"):
        student.soft_imitation_loss(teacher, loss_function="kl")
    with pytest.raises(ValueError, match="do not match"):
        student.soft_imitation_loss(random_dist(2))


@pytest.mark.parametrize("loss_function", ["nll", "mse"])
@pytest.mark.parametrize("teacher_context", ["window", "step"])
def test_distillation_grasp_labels(loss_function, teacher_context):
    student, teacher = copied_student()
    td = window()
    td["state_estimate"] = td["state"] + 0.3 * torch.randn_like(td["state"])
    soft = DTDistillationLoss(student, teacher, loss_function=loss_function, teacher_context=teacher_context)
    hard = DTDistillationLoss(student, teacher, loss_function=loss_function, teacher_context=teacher_context,
                              grasp_labels="decision")
    assert soft.grasp_labels == "probability"  # the default
    with torch.no_grad():
        _, t_loc, t_scale, t_logits = soft.teacher_dist(td)
        s = student.get_dist(td.select(*student.in_keys))
        t = GraspConditionedTanhNormal(t_loc, t_scale, t_logits, grasp_dims=GRASP)
        expected = s.soft_imitation_loss(t, loss_function=loss_function).mean()
    out = soft(td)
    torch.testing.assert_close(out["loss_distill"].detach(), expected)
    assert not torch.allclose(out["loss_distill"], hard(td)["loss_distill"])  # an unsure teacher's labels differ
    out["loss_distill"].backward()
    assert student.module[0].module.head_grasp.weight.grad is not None
    with pytest.raises(ValueError, match="grasp_labels"):
        DTDistillationLoss(student, teacher, grasp_labels="soft")


def test_a_saved_teacher_with_a_grasp_head_loads_with_it(tmp_path):
    from trakdis.envs import task_spec
    from trakdis.modules import find_dt_actor
    from trakdis.policies import load_teacher, save_policy

    spec = task_spec("ClothFoldDiagonalPinned")
    cfg = DTModelConfig(embed_dim=16, n_layer=1, n_head=1, context_len=4, grasp_head=True)
    cfg = cfg.for_task(spec.state_dim, spec.action_dim, horizon=10, grasp_dims=spec.grasp_dims)
    actor = make_dt_actor(cfg, observation_key="state")
    save_policy(tmp_path / "policy.pt", kind="teacher", task="ClothFoldDiagonalPinned", horizon=10, dt_config=cfg,
                actor=actor, observation_key="state", target_return=-1.0, rtg_scale=1.0)
    loaded = find_dt_actor(load_teacher(tmp_path).actor)
    assert loaded.config.grasp_head and loaded.config.grasp_dims == spec.grasp_dims
    for (name, a), (_, b) in zip(find_dt_actor(actor).state_dict().items(), loaded.state_dict().items()):
        assert torch.equal(a, b), name


def test_acting_closes_at_the_median_of_the_close_time():
    # p(close) = 0.3 at every step: each step's argmax never closes; a sampled grasp has closed by the second
    # step with probability 0.51, so the deterministic policy closes there; it holds while p(closed) stays high
    # (a hold of p 0.99 per step would release at the step where 0.99^n falls to one half)
    torch.manual_seed(0)
    cfg = DTModelConfig(state_dim=S, action_dim=4, embed_dim=16, n_layer=1, n_head=2, context_len=K, max_timestep=32,
                        grasp_head=True, grasp_dims=(3,))
    actor = make_dt_actor(cfg, observation_key="state").eval()
    head = actor.module[0].module.head_grasp
    policy = DTActingPolicy(actor)
    grasps = []
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        for t in range(6):
            head.bias.fill_(math.log(0.3 / 0.7) if t < 2 else math.log(0.99 / 0.01))
            td = TensorDict(state=torch.zeros(1, S), return_to_go=torch.zeros(1, 1),
                            step_count=torch.full((1, 1), t), batch_size=[1])
            grasps.append(policy(td)["action"][0, 3].item())
        head.bias.fill_(math.log(0.3 / 0.7))  # a reset starts open again
        td = TensorDict(state=torch.zeros(1, S), return_to_go=torch.zeros(1, 1),
                        step_count=torch.zeros(1, 1, dtype=torch.long), batch_size=[1])
        grasps.append(policy(td)["action"][0, 3].item())
    assert grasps == [-1.0, 1.0, 1.0, 1.0, 1.0, 1.0, -1.0]


@pytest.mark.parametrize("field,value", [("grasp_dims", [3.5]), ("grasp_dims", list(range(10))), ("grasp_dims", "37"),
                                         ("grasp_head", "false"), ("grasp_head", 1)])
def test_a_policy_file_with_bad_grasp_fields_is_refused(tmp_path, field, value):
    from trakdis.envs import task_spec
    from trakdis.policies import load_teacher, save_policy
    from trakdis.utils.checkpoint import FileFormatError, read_checkpoint

    spec = task_spec("ClothFoldDiagonalPinned")
    cfg = DTModelConfig(embed_dim=16, n_layer=1, n_head=1, context_len=4, grasp_head=True)
    cfg = cfg.for_task(spec.state_dim, spec.action_dim, horizon=10, grasp_dims=spec.grasp_dims)
    save_policy(tmp_path / "policy.pt", kind="teacher", task="ClothFoldDiagonalPinned", horizon=10, dt_config=cfg,
                actor=make_dt_actor(cfg, observation_key="state"), observation_key="state", target_return=-1.0,
                rtg_scale=1.0)
    payload = read_checkpoint(tmp_path / "policy.pt")
    payload["dt_config"][field] = value
    torch.save(payload, tmp_path / "policy.pt")
    with pytest.raises(FileFormatError, match=field):
        load_teacher(tmp_path)
