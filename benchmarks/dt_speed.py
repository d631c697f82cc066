"""Decision Transformer speed: training-step throughput and per-step acting latency.

Compares ``trakdis.modules`` (SDPA transformer, ``MaskedOnlineDTLoss``, ``DTActingPolicy``) with TorchRL's
``OnlineDTActor`` (HuggingFace GPT-2 backend) + ``OnlineDTLoss`` at the same size (width, depth,
heads, MLP width 4x, dropout), at context lengths 5, 30 and 100, on the CPU and on CUDA when
available. All ratios printed come from this one run.

* training step: a batch of ``--batch`` windows, forward (log-likelihood + 1-sample entropy),
  backward and an Adam step; reported in samples (windows) per second, best and median of
  ``--rounds`` rounds of ``--steps`` steps alternating between the two implementations. A
  ``where`` line splits profiled steps of each into matrix products (mm/addmm/bmm), the Adam
  step and everything else, and gives the ratio that would be reached if everything but our
  matrix products and Adam step took no time (the best ratio times our profiled total over
  our matmul + Adam time): an upper bound for the training-step ratio at this size.
* acting: per-step latency for ``--envs`` environments at steps 10, 100 and 1000 of one long
  episode (the fastest of the 10 steps starting there: robust to other processes on the CPU). TorchRL has no stateful acting
  wrapper; its per-step cost is one forward over the last-K window (what
  ``DecisionTransformerInferenceWrapper`` does), measured on a ready-made window.

Needs ``pip install transformers`` for the TorchRL part (skipped with a message otherwise).

    python benchmarks/dt_speed.py                 # small model on the CPU (a few minutes)
    python benchmarks/dt_speed.py --size paper    # embedding 256, 10 layers, 16 heads
"""
from __future__ import annotations

import argparse
import gc
import importlib.util
import statistics
import time

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, TanhNormal
from torchrl.objectives import OnlineDTLoss

from trakdis.modules import DTActingPolicy, DTModelConfig, make_dt_actor
from trakdis.objectives import MaskedOnlineDTLoss

STATE_DIM, ACTION_DIM = 18, 8  # ClothFold
HAS_TRANSFORMERS = importlib.util.find_spec("transformers") is not None


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


# The sizes and action head this benchmark measures (its README numbers): "small" is 128 wide, 3 layers,
# 4 heads; both sizes with dropout 0.1 and Online DT's unbounded mean and log-std >= -5.
_HEAD = dict(dropout=0.1, attn_dropout=0.1, loc_bound=0.0, log_std_min=-5.0)


def make_config(size: str, k: int) -> DTModelConfig:
    if size == "paper":
        return DTModelConfig.paper(STATE_DIM, ACTION_DIM, context_len=k, **_HEAD)
    return DTModelConfig(STATE_DIM, ACTION_DIM, embed_dim=128, n_layer=3, n_head=4, context_len=k, **_HEAD)


def make_torchrl_actor(cfg: DTModelConfig, device):
    from torchrl.modules import DecisionTransformer, OnlineDTActor

    tcfg = DecisionTransformer.DTConfig(
        n_embd=cfg.embed_dim, n_layer=cfg.n_layer, n_head=cfg.n_head, n_inner=cfg.mlp_ratio * cfg.embed_dim,
        activation="gelu", n_positions=1024, resid_pdrop=cfg.dropout, attn_pdrop=cfg.attn_dropout,
    )
    net = OnlineDTActor(STATE_DIM, ACTION_DIM, transformer_config=tcfg, device=device)
    module = TensorDictModule(net, in_keys=["observation", "action", "return_to_go"], out_keys=["loc", "scale"])
    return ProbabilisticActor(
        module, in_keys=["loc", "scale"], out_keys=["action"], distribution_class=TanhNormal,
        distribution_kwargs={"low": -1.0, "high": 1.0},
        spec=Bounded(-1.0, 1.0, shape=(ACTION_DIM,), device=device),
    )


def batch_windows(b, k, device):
    g = torch.Generator().manual_seed(0)
    mask = torch.ones(b, k, dtype=torch.bool)
    mask[: b // 4, : k // 2] = False  # a quarter of the windows left-padded
    return TensorDict(
        observation=torch.randn(b, k, STATE_DIM, generator=g),
        action=torch.rand(b, k, ACTION_DIM, generator=g) * 1.8 - 0.9,
        return_to_go=torch.randn(b, k, 1, generator=g),
        timestep=torch.arange(k).expand(b, k).clone(),
        mask=mask,
        batch_size=[b, k],
    ).to(device)


class TrainStep:
    """One optimisation step (forward, backward, Adam) of a loss module on a fixed batch."""

    def __init__(self, loss_module, loss_keys, td):
        self.loss_module, self.loss_keys, self.td = loss_module, loss_keys, td
        self.opt = torch.optim.Adam(loss_module.parameters(), lr=1e-4)

    def __call__(self):
        out = self.loss_module(self.td)
        total = sum(out[k] for k in self.loss_keys)
        self.opt.zero_grad(set_to_none=True)
        total.backward()
        self.opt.step()


def time_train(steps_by_name: dict, device, steps: int, rounds: int, warmup: int = 2) -> dict:
    """Samples/s per step function over rounds that alternate between them: ``{name: [per round]}``.

    Alternating and keeping the best round makes the ratio robust to other processes
    competing for the CPU (this benchmark is meant to run on a shared machine too).
    """
    for fn in steps_by_name.values():
        for _ in range(warmup):
            fn()
    rates = {name: [] for name in steps_by_name}
    for _ in range(rounds):
        for name, fn in steps_by_name.items():
            gc.collect()
            sync(device)
            t0 = time.perf_counter()
            for _ in range(steps):
                fn()
            sync(device)
            rates[name].append(steps * fn.td.shape[0] / (time.perf_counter() - t0))
    return rates


MATMUL_OPS = {"aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm", "aten::addmm_", "aten::baddbmm_"}


def profile_train(fn, device, steps: int = 3) -> dict:
    """ms per step (profiled, so a little slower than timed) in matrix products, Adam, and the rest."""
    activities = [torch.profiler.ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    with torch.profiler.profile(activities=activities) as prof:
        for _ in range(steps):
            fn()
        sync(device)
    events = prof.key_averages()
    attr = "self_device_time_total" if device.type == "cuda" else "self_cpu_time_total"
    total = sum(getattr(e, attr) for e in events) / steps / 1e3
    matmul = sum(getattr(e, attr) for e in events if e.key in MATMUL_OPS) / steps / 1e3
    adam = sum(e.cpu_time_total for e in events if e.key.startswith("Optimizer.step")) / steps / 1e3
    return {"total": total, "matmul": matmul, "adam": adam, "other": total - matmul - adam}


@torch.no_grad()
def time_acting(policy, n_envs, device, checkpoints=(10, 100, 1000)):
    g = torch.Generator().manual_seed(1)
    obs = torch.randn(n_envs, STATE_DIM, generator=g).to(device)
    td = TensorDict(observation=obs, return_to_go=torch.zeros(n_envs, 1, device=device), batch_size=[n_envs], device=device)
    for t in range(20):  # warm-up; step_count 0 below starts a fresh context
        td["step_count"] = torch.full((n_envs, 1), t, dtype=torch.long, device=device)
        policy(td)
    gc.collect()
    last = max(checkpoints) + 10
    times = []
    for t in range(last):
        td["step_count"] = torch.full((n_envs, 1), t, dtype=torch.long, device=device)
        sync(device)
        t0 = time.perf_counter()
        policy(td)
        sync(device)
        times.append(time.perf_counter() - t0)
    return {c: min(times[c : c + 10]) for c in checkpoints}


@torch.no_grad()
def time_window_forward(actor, td, device, steps=30):
    gc.collect()
    for _ in range(3):
        actor(td.clone())
    sync(device)
    times = []
    for _ in range(steps):
        x = td.clone()
        t0 = time.perf_counter()
        actor(x)
        sync(device)
        times.append(time.perf_counter() - t0)
    return min(times)


def run_device(device, args):
    print(f"\n=== device {device} | size {args.size} | batch {args.batch} | envs {args.envs} | threads {torch.get_num_threads()} ===")
    if not HAS_TRANSFORMERS:
        print("transformers is not installed: skipping TorchRL's DecisionTransformer (pip install transformers)")
    for k in args.contexts:
        cfg = make_config(args.size, k)
        torch.manual_seed(0)
        ours = make_dt_actor(cfg).to(device)
        n_ours = sum(p.numel() for p in ours.parameters())
        td = batch_windows(args.batch, k, device)
        steps = {"trakdis": TrainStep(MaskedOnlineDTLoss(ours, lambda_entropy=0.1), ["loss_nll", "loss_entropy"], td)}
        theirs = None
        if HAS_TRANSFORMERS:
            torch.manual_seed(0)
            theirs = make_torchrl_actor(cfg, device)
            n_theirs = sum(p.numel() for p in theirs.parameters())
            steps["torchrl"] = TrainStep(
                OnlineDTLoss(theirs, alpha_init=0.1, fixed_alpha=True), ["loss_log_likelihood", "loss_entropy"], td
            )
        rates = time_train(steps, device, args.steps, args.rounds)
        best = {name: max(r) for name, r in rates.items()}
        med = {name: statistics.median(r) for name, r in rates.items()}
        line = f"K={k:4d} train  trakdis {best['trakdis']:9.1f} samples/s (median {med['trakdis']:.1f}; {n_ours / 1e6:.2f}M params)"
        if theirs is not None:
            line += (
                f" | torchrl {best['torchrl']:9.1f} samples/s (median {med['torchrl']:.1f}; {n_theirs / 1e6:.2f}M params)"
                f" | ratio {best['trakdis'] / best['torchrl']:5.2f}x best, {med['trakdis'] / med['torchrl']:5.2f}x median"
            )
        print(line, flush=True)
        if args.profile:
            split = {name: profile_train(fn, device) for name, fn in steps.items()}
            line = f"K={k:4d} where  " + " | ".join(
                f"{name} {p['total']:7.1f} ms/step = matmul {p['matmul']:6.1f} ({p['matmul'] / p['total']:4.0%}) + Adam {p['adam']:4.1f} + other {p['other']:6.1f}"
                for name, p in split.items()
            )
            if theirs is not None:
                # the timed ratio if our non-matmul, non-Adam work took no time at all
                o = split["trakdis"]
                bound = best["trakdis"] / best["torchrl"] * o["total"] / (o["matmul"] + o["adam"])
                line += f" | ratio bound (our other = 0) {bound:4.2f}x"
            print(line, flush=True)
        ours.eval()
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            lat_by_mode = {}
            for mode in ("kv_cache", "window"):
                lat = lat_by_mode[mode] = time_acting(DTActingPolicy(ours, mode=mode), args.envs, device)
                print(f"K={k:4d} act    trakdis {mode:8s} ms/step at step " + "  ".join(f"{c}: {v * 1e3:7.3f}" for c, v in lat.items()), flush=True)
            if theirs is not None:
                theirs.eval()
                win = batch_windows(args.envs, k, device).exclude("timestep", "mask")
                lat_t = time_window_forward(theirs, win, device)
                print(
                    f"K={k:4d} act    torchrl  window ms/step (any step) {lat_t * 1e3:7.3f} | torchrl / trakdis at step 1000: "
                    f"kv_cache {lat_t / lat_by_mode['kv_cache'][1000]:5.2f}x, window {lat_t / lat_by_mode['window'][1000]:5.2f}x",
                    flush=True,
                )


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size", choices=["small", "paper"], default="small")
    p.add_argument("--contexts", type=int, nargs="+", default=[5, 30, 100])
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--envs", type=int, default=1)
    p.add_argument("--steps", type=int, default=5, help="timed training steps per round")
    p.add_argument("--rounds", type=int, default=7, help="alternating timing rounds (best and median reported)")
    p.add_argument("--no-profile", dest="profile", action="store_false", help="skip the profiled time split")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--devices", nargs="+", default=None, help="default: cpu, plus cuda when available")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    devices = args.devices or (["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
    for dev in devices:
        run_device(torch.device(dev), args)


if __name__ == "__main__":
    main()
