import pytest
import torch
from tensordict import TensorDict

from trakdis.modules import DTModelConfig, StateEncoder, copy_teacher_weights, make_dt_actor


def cfg(**kw):
    base = dict(state_dim=5, action_dim=3, embed_dim=32, n_layer=2, n_head=4, context_len=4)
    base.update(kw)
    return DTModelConfig(**base)


def test_round_trip_teacher_to_student():
    torch.manual_seed(0)
    teacher = make_dt_actor(cfg(), observation_key="state").eval()
    student = make_dt_actor(cfg(), observation_key="state_estimate").eval()
    td = TensorDict(
        state=torch.randn(2, 4, 5),
        action=torch.rand(2, 4, 3) * 2 - 1,
        return_to_go=torch.randn(2, 4, 1),
        timestep=torch.arange(4).expand(2, 4),
        mask=torch.ones(2, 4, dtype=torch.bool),
        batch_size=[2, 4],
    )
    td["state_estimate"] = td["state"]
    assert not torch.allclose(student.get_dist(td).root_dist.loc, teacher.get_dist(td).root_dist.loc)
    out = copy_teacher_weights(student, teacher)
    assert out is student
    for (n1, p1), (n2, p2) in zip(student.named_parameters(), teacher.named_parameters()):
        assert n1 == n2 and torch.equal(p1, p2) and p1.data_ptr() != p2.data_ptr()
    torch.testing.assert_close(student.get_dist(td).root_dist.loc, teacher.get_dist(td).root_dist.loc)
    # independent copies: training the student leaves the teacher unchanged
    before = teacher.module[0].module.head_loc.weight.clone()
    with torch.no_grad():
        student.module[0].module.head_loc.weight.add_(1.0)
    assert torch.equal(teacher.module[0].module.head_loc.weight, before)


def test_mismatch_lists_names_and_shapes():
    teacher = make_dt_actor(cfg())
    with pytest.raises(ValueError, match=r"shape mismatch: .*embed_state.weight: student \(32, 6\) vs teacher \(32, 5\)"):
        copy_teacher_weights(make_dt_actor(cfg(state_dim=6)), teacher)
    with pytest.raises(ValueError, match=r"only in teacher: .*blocks\.1\."):
        copy_teacher_weights(make_dt_actor(cfg(n_layer=1)), teacher)
    with pytest.raises(ValueError, match=r"only in student"):
        copy_teacher_weights(make_dt_actor(cfg(n_layer=3)), teacher)
    with pytest.raises(ValueError, match="architectures differ"):
        copy_teacher_weights(StateEncoder(5), teacher)
    # nothing was copied on failure
    student = make_dt_actor(cfg(state_dim=6))
    w = student.module[0].module.head_loc.weight.clone()
    with pytest.raises(ValueError):
        copy_teacher_weights(student, teacher)
    assert torch.equal(student.module[0].module.head_loc.weight, w)
