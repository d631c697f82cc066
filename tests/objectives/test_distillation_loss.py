import pytest
import torch
from dt_windows import random_window

from trakdis.modules import DTModelConfig, StateEncoder, copy_teacher_weights, find_dt_actor, make_dt_actor
from trakdis.objectives import DTDistillationLoss

S, A, B, K = 5, 3, 3, 4


def cfg():
    return DTModelConfig(state_dim=S, action_dim=A, embed_dim=32, n_layer=2, n_head=4, context_len=K, dropout=0.0, attn_dropout=0.0)


@pytest.fixture
def actors():
    torch.manual_seed(0)
    teacher = make_dt_actor(cfg(), observation_key="state")
    student = make_dt_actor(cfg(), observation_key="state_estimate")
    return student, teacher


def window(seed=0, pad=(0, 1, 3)):
    return random_window(B, K, S, A, pad=pad, seed=seed, state_keys=("state", "state_estimate"), pixels=32)


def test_loss_is_student_nll_of_teacher_mean_action(actors):
    student, teacher = actors
    td = window()
    out = DTDistillationLoss(student, teacher)(td.clone())
    assert set(out.keys()) == {"loss_distill", "teacher_student_mse"}
    with torch.no_grad():
        t_mean = torch.tanh(teacher.get_dist(td.clone()).root_dist.loc)
        s_dist = student.get_dist(td.clone())
        m = td["mask"]
        expected = -s_dist.log_prob(t_mean)[m].mean()
        mse = (torch.tanh(s_dist.root_dist.loc) - t_mean).pow(2).mean(-1)[m].mean()
    torch.testing.assert_close(out["loss_distill"], expected)
    torch.testing.assert_close(out["teacher_student_mse"], mse)
    # padded content never changes it
    td2 = td.clone()
    td2["state"][~m] = float("nan")
    td2["state_estimate"][~m] = 1e5
    torch.testing.assert_close(DTDistillationLoss(student, teacher)(td2)["loss_distill"], out["loss_distill"], rtol=0, atol=1e-5)


@pytest.mark.parametrize("loss_function", ["nll", "mse"])
def test_grasp_labels_leave_a_policy_without_grasp_head_unchanged(actors, loss_function):
    student, teacher = actors
    td = window()
    losses = [DTDistillationLoss(student, teacher, loss_function=loss_function, grasp_labels=g)(td.clone())["loss_distill"]
              for g in ("probability", "decision")]
    torch.testing.assert_close(losses[0], losses[1], rtol=0, atol=0)
    assert DTDistillationLoss(student, teacher).teacher_dist(td.clone())[3] is None


@pytest.mark.parametrize("direction", ["teacher_student", "student_teacher"])
def test_gradients_reach_only_the_student(actors, direction):
    student, teacher = actors
    encoder = StateEncoder(S)
    td = window()
    td["state_estimate"] = encoder(td["pixels"])  # part of the encoder's graph
    loss = DTDistillationLoss(student, teacher, kl_coef=0.5, kl_direction=direction)
    teacher_params = set(teacher.parameters())
    assert not teacher_params & set(loss.parameters())
    assert set(loss.parameters()) == set(loss.student_network_params.values(True, True))
    torch.manual_seed(0)
    out = loss(td)
    assert torch.isfinite(out["loss_kl"])
    (out["loss_distill"] + out["loss_kl"]).backward()
    assert all(p.grad is None for p in teacher.parameters())
    assert all(p.grad is None for p in encoder.parameters())
    grads = [p.grad for p in loss.student_network_params.values(True, True)]
    assert all(g is not None for g in grads) and sum(g.abs().sum() for g in grads) > 0


def test_kl_is_zero_for_identical_policies_and_positive_otherwise(actors):
    student, teacher = actors
    td = window()
    td["state_estimate"] = td["state"].clone()
    for direction in ("teacher_student", "student_teacher"):
        torch.manual_seed(0)
        far = DTDistillationLoss(student, teacher, kl_coef=1.0, kl_direction=direction)(td.clone())
        assert far["loss_kl"] > 0.05
        # exact closed form: agrees with a large Monte-Carlo estimate on the TanhNormals
        with torch.no_grad():
            pt, ps = teacher.get_dist(td.clone()), student.get_dist(td.clone())
            p, q = (pt, ps) if direction == "teacher_student" else (ps, pt)
            u = p.root_dist.sample((20000,))
            mc = (p.root_dist.log_prob(u) - q.root_dist.log_prob(u)).sum(-1).mean(0)[td["mask"]].mean()
        torch.testing.assert_close(far["loss_kl"], mc, rtol=0.05, atol=0.02)
    copy_teacher_weights(student, teacher)
    for direction in ("teacher_student", "student_teacher"):
        out = DTDistillationLoss(student, teacher, kl_coef=1.0, kl_direction=direction)(td.clone())
        assert abs(out["loss_kl"].item()) < 1e-6
        assert out["teacher_student_mse"].item() < 1e-10


def test_training_the_student_matches_the_teacher(actors):
    student, teacher = actors
    td = window()
    td["state_estimate"] = td["state"] + 0.05 * torch.randn(B, K, S)  # a decent encoder
    loss = DTDistillationLoss(student, teacher)
    opt = torch.optim.Adam(loss.parameters(), lr=3e-3)
    start = loss(td)["teacher_student_mse"].item()
    for _ in range(60):
        out = loss(td)
        opt.zero_grad()
        out["loss_distill"].backward()
        opt.step()
    assert loss(td)["teacher_student_mse"].item() < 0.3 * start


def test_set_keys_and_errors(actors):
    student, teacher = actors
    loss = DTDistillationLoss(student, teacher)
    assert {"state", "state_estimate", "mask"} <= set(loss.in_keys)
    td = window()
    td["valid"] = td["mask"].clone()
    td["valid"][:, :2] = False  # the loss's own mask may exclude more steps than the actors' "mask"
    loss.set_keys(mask="valid")
    with pytest.raises(KeyError, match="'valid'"):
        loss(td.exclude("valid"))
    out = loss(td.clone())
    with torch.no_grad():
        t_mean = torch.tanh(teacher.get_dist(td.clone()).root_dist.loc)
        expected = -student.get_dist(td.clone()).log_prob(t_mean)[td["valid"]].mean()
    torch.testing.assert_close(out["loss_distill"], expected)
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss.set_keys(state="x")
    with pytest.raises(ValueError, match="kl_direction"):
        DTDistillationLoss(student, teacher, kl_direction="both")
    with pytest.raises(ValueError, match="distinct"):
        DTDistillationLoss(student, student)
    with pytest.raises(KeyError):
        loss(window().exclude("state_estimate"))


def test_teacher_targets_are_deterministic_even_if_teacher_is_in_train_mode():
    torch.manual_seed(0)
    c = DTModelConfig(state_dim=S, action_dim=A, embed_dim=32, n_layer=2, n_head=4, context_len=K, dropout=0.5, attn_dropout=0.5)
    teacher = make_dt_actor(c, observation_key="state").train()
    student = make_dt_actor(c, observation_key="state_estimate").eval()
    loss = DTDistillationLoss(student, teacher)
    td = window()
    a, b = loss(td.clone()), loss(td.clone())
    torch.testing.assert_close(a["loss_distill"], b["loss_distill"], rtol=0, atol=0)
    assert teacher.training  # the flag is restored


def test_mse_loss_is_squared_error_of_mean_actions(actors):
    student, teacher = actors
    td = window()
    out = DTDistillationLoss(student, teacher, loss_function="mse")(td.clone())
    with torch.no_grad():
        t_mean = torch.tanh(teacher.get_dist(td.clone()).root_dist.loc)
        s_mean = torch.tanh(student.get_dist(td.clone()).root_dist.loc)
        expected = (s_mean - t_mean).pow(2).sum(-1)[td["mask"]].mean()
    torch.testing.assert_close(out["loss_distill"], expected)
    out["loss_distill"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in student.parameters())


def test_mse_ignores_a_gap_the_actions_do_not_show():
    """Where both policies saturate, a pre-tanh gap changes no action: the NLL still charges it
    (in units of the student's std), the action-space squared error does not."""
    torch.manual_seed(0)
    c = DTModelConfig(state_dim=S, action_dim=A, embed_dim=32, n_layer=2, n_head=4, context_len=K, dropout=0.0,
                      attn_dropout=0.0, loc_bound=5.0, log_std_min=-2.5)
    teacher = make_dt_actor(c, observation_key="state")
    student = make_dt_actor(c, observation_key="state_estimate")
    td = window(pad=(0, 0, 0))
    td["state_estimate"] = td["state"].clone()

    def set_heads(actor, loc_bias):
        head = find_dt_actor(actor)
        head.head_loc.weight.zero_()
        head.head_loc.bias.fill_(loc_bias)  # loc = 5 tanh(bias / 5): 4.9997 (40) or 4.92 (12)
        head.head_log_std.weight.zero_()
        head.head_log_std.bias.fill_(-10.0)  # clamped to the floor, std = exp(-2.5)

    with torch.no_grad():
        set_heads(teacher, 40.0)
        copy_teacher_weights(student, teacher)
        set_heads(student, 12.0)
    kw = {"action_eps": c.action_eps}
    gap = {f: DTDistillationLoss(student, teacher, loss_function=f, **kw)(td.clone())["loss_distill"] for f in ("nll", "mse")}
    assert gap["mse"] < 1e-8  # actions 0.99989 and 0.99991
    with torch.no_grad():
        set_heads(student, 40.0)
    nll_same = DTDistillationLoss(student, teacher, **kw)(td.clone())["loss_distill"]
    assert gap["nll"] > nll_same + 1.0  # the same actions, a larger NLL
    with pytest.raises(ValueError, match="loss_function"):
        DTDistillationLoss(student, teacher, loss_function="l1")


def test_step_context_labels_each_step_from_its_own_tokens(actors):
    student, teacher = actors
    td = window()
    m = td["mask"]
    loss = DTDistillationLoss(student, teacher, loss_function="mse", teacher_context="step")
    out = loss(td.clone())
    # the label of step k is the teacher's action on the one-step window (rtg_k, s_k, t_k)
    with torch.no_grad():
        labels = torch.zeros(B, K, A)
        for b in range(B):
            for k in range(K):
                one = td[b : b + 1, k : k + 1].clone()
                one["mask"] = torch.ones(1, 1, dtype=torch.bool)
                labels[b, k] = torch.tanh(teacher.get_dist(one).root_dist.loc)[0, 0]
        s_act = torch.tanh(student.get_dist(td.clone()).root_dist.loc)
        expected = (s_act - labels).pow(2).sum(-1)[m].mean()
    torch.testing.assert_close(out["loss_distill"], expected)
    # the acting policy's action history no longer changes the labels...
    td2 = td.clone()
    td2["action"] = torch.rand_like(td2["action"]) * 2 - 1
    with torch.no_grad():
        t2 = loss.teacher_dist(td2)[0]
    torch.testing.assert_close(t2[m], labels[m])
    # ...while the whole-window teacher reads it
    t_window = DTDistillationLoss(student, teacher, teacher_context="window").teacher_dist(td2)[0]
    assert not torch.allclose(t_window[m], labels[m])
    with pytest.raises(ValueError, match="teacher_context"):
        DTDistillationLoss(student, teacher, teacher_context="history")


def test_expert_term_is_student_nll_of_the_windows_own_actions(actors):
    student, teacher = actors
    td = window()
    td["action"] = td["action"].clamp(-0.9, 0.9)
    base = DTDistillationLoss(student, teacher)(td.clone())
    out = DTDistillationLoss(student, teacher, expert_coef=0.5)(td.clone())
    assert set(out.keys()) == {"loss_distill", "loss_expert", "teacher_student_mse"}
    torch.testing.assert_close(out["loss_distill"], base["loss_distill"])  # the teacher's term is unchanged
    with torch.no_grad():
        expected = -student.get_dist(td.clone()).log_prob(td["action"])[td["mask"]].mean()
    torch.testing.assert_close(out["loss_expert"], 0.5 * expected)
    # its targets are the "action" key (set_keys), which the student also reads as its action tokens
    loss = DTDistillationLoss(student, teacher, expert_coef=1.0)
    assert "action" in loss.in_keys
    td["demo"] = -td["action"]
    loss.set_keys(action="demo")
    with torch.no_grad():
        flipped = -student.get_dist(td.clone()).log_prob(td["demo"])[td["mask"]].mean()
    torch.testing.assert_close(loss(td.clone())["loss_expert"], flipped)
    # gradients reach the student alone, through both terms
    student.zero_grad()
    total = sum(v for k, v in loss(td.clone()).items() if k.startswith("loss_"))
    total.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in student.parameters())
    assert all(p.grad is None for p in teacher.parameters())
    with pytest.raises(ValueError, match="expert_coef"):
        DTDistillationLoss(student, teacher, expert_coef=-1.0)
    with pytest.raises(ValueError, match="expert_coef"):
        DTDistillationLoss(student, teacher, expert_coef=float("nan"))


def test_former_name_warns_and_is_the_same_class():
    import trakdis.objectives as objectives

    with pytest.warns(FutureWarning, match="DTDistillationLoss"):
        assert objectives.DistillationLoss is DTDistillationLoss
    with pytest.raises(AttributeError, match="NoSuchLoss"):
        objectives.NoSuchLoss
