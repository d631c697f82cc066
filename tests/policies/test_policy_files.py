"""Policy and encoder files (trakdis.policies.files): written, read back, refused when they do not fit."""
import pytest
import torch
from tiny_policies import tiny_actor

from trakdis.modules import NormalizedEncoder, StateEncoder
from trakdis.policies import PolicyHandle, load_encoder, load_policy, load_teacher, save_encoder, save_policy
from trakdis.utils.checkpoint import FileFormatError, save_checkpoint


def test_policy_and_encoder_files(tmp_path):
    cfg, actor = tiny_actor()
    save_policy(tmp_path / "policy.pt", kind="teacher", task="ClothFoldDiagonalPinned", horizon=10, dt_config=cfg,
                actor=actor, observation_key="state", target_return=-1.0, rtg_scale=1.0)
    h = load_policy(tmp_path)  # a run directory works too
    assert h.kind == "teacher" and h.task == "ClothFoldDiagonalPinned" and h.horizon == 10 and h.encoder is None
    for a, b in zip(actor.parameters(), h.actor.parameters()):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="ClothFold"):
        load_policy(tmp_path / "policy.pt", task="ClothFold")
    assert load_policy("expert", task="ClothFold").kind == "expert"
    with pytest.raises(ValueError, match="--task"):
        load_policy("expert")
    enc = NormalizedEncoder(StateEncoder(5, channels=(4, 4, 4, 4), hidden_dim=8), torch.arange(5.0), torch.full((5,), 2.0))
    save_encoder(tmp_path / "encoder.pt", enc, task="ClothFold")
    enc2, data = load_encoder(tmp_path / "encoder.pt")
    px = torch.randint(0, 255, (2, 32, 32, 3), dtype=torch.uint8)
    assert torch.allclose(enc.eval()(px), enc2(px))
    with pytest.raises(FileFormatError, match="teacher"):
        load_encoder(tmp_path / "policy.pt")
    with pytest.raises(ValueError, match="is for ClothFold, not ClothFoldDiagonalUnpinned"):
        load_encoder(tmp_path, task="ClothFoldDiagonalUnpinned")
    assert load_teacher(tmp_path, task="ClothFoldDiagonalPinned", horizon=10).kind == "teacher"
    for kw in ({"task": "ClothFold"}, {"horizon": 5}):
        with pytest.raises(FileFormatError, match="expected a teacher"):
            load_teacher(tmp_path, **kw)
    save_policy(tmp_path / "student.pt", kind="student", task="ClothFold", horizon=10, dt_config=cfg, actor=actor,
                observation_key="state", target_return=-1.0, rtg_scale=1.0, encoder_file=data)
    with pytest.raises(FileFormatError, match="a student for ClothFold .*expected a teacher$"):
        load_teacher(tmp_path / "student.pt")
    save_checkpoint(tmp_path / "bad.pt", {"kind": "encoder", "task": "ClothFold", "dt_config": {}, "actor": {},
                                          "observation_key": "state"})
    with pytest.raises(FileFormatError, match="not a policy"):
        load_policy(tmp_path / "bad.pt")


def test_image_networks_of_another_rendering_are_refused(tmp_path, monkeypatch):
    import trakdis.envs.model
    from trakdis.envs import render_version
    from trakdis.utils.checkpoint import read_checkpoint

    task = "ClothFoldDiagonalUnpinned"
    enc = NormalizedEncoder(StateEncoder(15, channels=(4, 4, 4, 4), hidden_dim=8), torch.zeros(15), torch.ones(15))
    save_encoder(tmp_path / "encoder.pt", enc, task=task)
    _, data = load_encoder(tmp_path / "encoder.pt", task=task)  # today's rendering: loads
    assert data["render_version"] == render_version(task)
    cfg, actor = tiny_actor("state_estimate")
    save_policy(tmp_path / "student.pt", kind="student", task=task, horizon=10, dt_config=cfg, actor=actor,
                observation_key="state_estimate", target_return=-1.0, rtg_scale=1.0, encoder_file=data)
    assert load_policy(tmp_path / "student.pt").encoder is not None
    # an encoder file from before the unpinned fold's wider camera (no version recorded: version 2)
    old = {k: v for k, v in read_checkpoint(tmp_path / "encoder.pt").items() if k != "render_version"}
    save_checkpoint(tmp_path / "old.pt", old)
    with pytest.raises(FileFormatError, match=f"old.pt: .*rendering version 2; this trakdis renders {task} at version 3"):
        load_encoder(tmp_path / "old.pt")
    # the task's rendering changes after the files were written: encoder and student are both refused
    monkeypatch.setitem(trakdis.envs.model.RENDER_VERSIONS, task, render_version(task) + 1)
    with pytest.raises(FileFormatError, match="encoder.pt: .*version 3; this trakdis renders .* at version 4"):
        load_encoder(tmp_path / "encoder.pt")
    with pytest.raises(FileFormatError, match=r"student.pt \(its encoder\): .*version 3"):
        load_policy(tmp_path / "student.pt")


def test_handle_save_writes_what_save_policy_writes(tmp_path):
    from trakdis.transforms import state_normalizer
    from trakdis.utils.checkpoint import read_checkpoint

    cfg, actor = tiny_actor("state_estimate")
    norm = state_normalizer(torch.zeros(5), torch.full((5,), 2.0), keys=("state", "state_estimate"))
    fields = dict(kind="student", task="ClothFold", horizon=10, actor=actor, observation_key="state_estimate",
                  target_return=-0.5, rtg_scale=2.0, normalizer=norm, env_kwargs={"picker_size": 0.03})
    extra = {"encoder_file": {"task": "ClothFold"}, "extra": {"weight_copy": False}}
    save_policy(tmp_path / "a.pt", dt_config=cfg, **fields, **extra)
    PolicyHandle(**fields).save(tmp_path / "b.pt", cfg, **extra)
    a, b = read_checkpoint(tmp_path / "a.pt"), read_checkpoint(tmp_path / "b.pt")
    assert a.keys() == b.keys() and b["weight_copy"] is False and b["env_kwargs"] == {"picker_size": 0.03}
    for k in a:
        if k in ("actor", "normalizer"):
            assert a[k].keys() == b[k].keys() and all(same(a[k][n], b[k][n]) for n in a[k]), k
        else:
            assert a[k] == b[k], k


def same(x, y) -> bool:
    return torch.equal(x, y) if torch.is_tensor(x) else x == y


def test_a_students_held_corner_is_saved_and_checked(tmp_path):
    """hold_radius rides in the student's file with its picker odometry and reaches the acting env's PickerOdometry;
    a value out of range, or one without the odometry, is refused naming the entry."""
    from trakdis.envs import close_env

    task = "ClothFoldDiagonalPinned"
    enc = NormalizedEncoder(StateEncoder(15, channels=(4, 4, 4, 4), hidden_dim=8), torch.zeros(15), torch.ones(15))
    save_encoder(tmp_path / "encoder.pt", enc, task=task)
    _, data = load_encoder(tmp_path / "encoder.pt", task=task)
    cfg, actor = tiny_actor("state_estimate")

    def student(name, **extra):
        return save_policy(tmp_path / name, kind="student", task=task, horizon=10, dt_config=cfg, actor=actor,
                           observation_key="state_estimate", target_return=-1.0, rtg_scale=1.0, encoder_file=data,
                           extra=extra)

    handle = load_policy(student("held.pt", picker_odometry=True, hold_radius=0.03))
    assert handle.hold_radius == 0.03
    env = handle.make_env()
    try:
        (odometry,) = [t for t in env.transform if type(t).__name__ == "PickerOdometry"]
        assert odometry.hold_radius == 0.03 and odometry.corner_starts == [0]
    finally:
        close_env(env)
    assert load_policy(student("plain.pt", picker_odometry=True)).hold_radius == 0.0  # files written before it
    for name, extra in (("neg.pt", dict(picker_odometry=True, hold_radius=-0.01)),
                        ("text.pt", dict(picker_odometry=True, hold_radius="3 cm")),
                        ("alone.pt", dict(picker_odometry=False, hold_radius=0.03))):
        with pytest.raises(FileFormatError, match=f"{name}: 'hold_radius' must be a distance"):
            load_policy(student(name, **extra))
