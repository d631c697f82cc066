"""Probe: the teacher's labels against the expert's executed actions on the distillation windows (expert data).
python labels.py TEACHER_DIR ENCODER_DIR [n_batches]"""
import sys, torch
from trakdis.data import DataConfig, load_encoded_dataset, student_buffer
from trakdis.envs import task_spec
from trakdis.objectives import DistillationLoss
from trakdis.policies import load_teacher_and_encoder, weight_copied_student
from trakdis.transforms import PickerOdometry
torch.manual_seed(0)
teacher, encoder, enc_file, enc_path = load_teacher_and_encoder(sys.argv[1], sys.argv[2], root="runs", device="cpu")
task, horizon = teacher.task, teacher.horizon
student_handle, dt_cfg = weight_copied_student(teacher, encoder, weight_copy=True, device="cpu",
                                               normalizer_keys=("state", "state_estimate"), picker_odometry=True)
student = student_handle.actor.eval()
teacher.actor.eval()
loss = DistillationLoss(student, teacher.actor, action_eps=dt_cfg.action_eps)
buf = student_buffer(200, dt_cfg.context_len, horizon, teacher.rtg_scale, normalizer=student_handle.normalizer,
                     distill=True, seed=0, relabel_return_to_go=True)
data, lengths, path = load_encoded_dataset(DataConfig(), encoder, task=task, horizon=horizon, seed=0,
                                           keys=("action", "reward", "state"), log=print, progress=False)
data.set("state_estimate", PickerOdometry.for_task(task, teacher.env_kwargs).filter(data["state_estimate"], data["action"]))
buf.load_offline(data, lengths)
import copy
others = {}
for f in sys.argv[4:]:
    ck = torch.load(f, weights_only=False, map_location="cpu")
    sd = ck["actor"] if "actor" in ck else {k[len("student_network_params."):]: v for k, v in ck["updater"]["loss_module"].items() if k.startswith("student_network_params.")}
    m = copy.deepcopy(student); missing = m.load_state_dict(sd, strict=False); m.eval(); others[f] = m
O = {f: [] for f in others}
T, E, C, M, P, PM, TS = [], [], [], [], [], [], []
with torch.no_grad():
    for _ in range(int(sys.argv[3]) if len(sys.argv) > 3 else 30):
        td = buf.sample(256)
        t = loss.teacher_dist(td)[0][:, -1]
        c = student.get_dist(td.select(*student.in_keys, strict=False)).deterministic_sample[:, -1]
        [O[f].append(m.get_dist(td.select(*m.in_keys, strict=False)).deterministic_sample[:, -1]) for f, m in others.items()]
        T.append(t); C.append(c); E.append(td["action"][:, -1]); M.append(td["mask"][:, -1]); P.append(td["action"][:, -2]); PM.append(td["mask"][:, -2]); TS.append(td["timestep"][:, -1].reshape(-1))
T, E, C, M, P, PM, TS = (torch.cat(x) for x in (T, E, C, M, P, PM, TS))
O = {f: torch.cat(v)[M] for f, v in O.items()}
T, E, C, P, PM, TS = T[M], E[M].clamp(-1, 1), C[M], P[M].clamp(-1, 1), PM[M], TS[M]
print(task, "windows", len(T))
for name, a, b in (("teacher-expert", T, E), ("copy-teacher", C, T), ("copy-expert", C, E)):
    print(f"{name}: per-dim MSE", [f"{v:.4f}" for v in (a - b).pow(2).mean(0).tolist()])
g = E.shape[1] - 1
print("grasp sign agreement teacher/expert", ((T[:, g] > 0) == (E[:, g] > 0)).float().mean().item(),
      "copy/expert", ((C[:, g] > 0) == (E[:, g] > 0)).float().mean().item(),
      "copy/teacher", ((C[:, g] > 0) == (T[:, g] > 0)).float().mean().item())
close = E[:, g] > 0
print(f"expert closed {close.float().mean():.3f}; teacher closes where expert closes {(T[close, g] > 0).float().mean():.3f}, "
      f"where expert open {(T[~close, g] > 0).float().mean():.3f}")
print("movement |teacher|, |expert| mean", T[:, :g].abs().mean(0).tolist(), E[:, :g].abs().mean(0).tolist())

prev_closed = (P[:, g] > 0) & PM
now = E[:, g] > 0
phases = {"open, never closed before (approach)": ~now & ~prev_closed, "onset": now & ~prev_closed,
          "carrying": now & prev_closed, "release": ~now & prev_closed}
for k, m in phases.items():
    if m.sum() == 0: continue
    print(f"{k}: n={int(m.sum())} teacher-expert MSE", [f"{v:.3f}" for v in (T[m]-E[m]).pow(2).mean(0).tolist()],
          f"teacher closes {(T[m, g] > 0).float().mean():.2f}; dz teacher {T[m, 2].mean():+.2f} expert {E[m, 2].mean():+.2f}; copy closes {(C[m, g] > 0).float().mean():.2f}; others close " + " ".join(f"{(o[m, g] > 0).float().mean():.2f}" for o in O.values()) + "; others-expert MSE " + " ".join(str([round(v, 3) for v in (o[m]-E[m]).pow(2).mean(0).tolist()]) for o in O.values()))
