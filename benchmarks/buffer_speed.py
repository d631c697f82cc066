"""Sampling cost of TrajectoryReplayBuffer vs. capacity (it should not grow with the buffer size).

Fills buffers of 100, 1000 and 10000 trajectories of 100 steps (state 18, action 8, as ClothFold)
and times ``sample(batch_size)`` windows of ``K`` steps. Prints the mean time per sample at each
capacity and the ratio to the smallest capacity, all measured in this one run.

    python benchmarks/buffer_speed.py [--batch-size 256] [--context-len 20] [--reps 50] [--threads 1]
"""

from __future__ import annotations

import argparse
import time

import torch
from tensordict import TensorDict

from trakdis.data import TrajectoryReplayBuffer


def fill(capacity: int, max_len: int, state_dim: int, action_dim: int) -> TrajectoryReplayBuffer:
    g = torch.Generator().manual_seed(0)
    rb = TrajectoryReplayBuffer(capacity=capacity, context_len=ARGS.context_len, max_len=max_len, seed=0)
    lengths = torch.randint(max_len // 2, max_len + 1, (capacity,), generator=g)
    chunk = 1000
    first = True
    for s in range(0, capacity, chunk):
        n = min(chunk, capacity - s)
        td = TensorDict(
            {
                "state": torch.randn(n, max_len, state_dim, generator=g),
                "action": torch.rand(n, max_len, action_dim, generator=g) * 2 - 1,
                "reward": -torch.rand(n, max_len, 1, generator=g) * 0.05,
            },
            [n, max_len],
        )
        if first:
            rb.load_offline(td, lengths[s : s + n])
            first = False
        else:
            rb.extend(td, lengths[s : s + n])
    return rb


def bench(rb: TrajectoryReplayBuffer, batch_size: int, reps: int) -> float:
    for _ in range(5):
        rb.sample(batch_size)
    t0 = time.perf_counter()
    for _ in range(reps):
        rb.sample(batch_size)
    return (time.perf_counter() - t0) / reps


def main() -> None:
    torch.set_num_threads(ARGS.threads)
    results = {}
    for cap in (100, 1000, 10000):
        rb = fill(cap, ARGS.max_len, 18, 8)
        results[cap] = bench(rb, ARGS.batch_size, ARGS.reps)
        print(
            f"capacity {cap:6d} ({rb.total_steps:8d} steps): {results[cap] * 1e3:7.3f} ms / sample "
            f"[B={ARGS.batch_size}, K={ARGS.context_len}]",
            flush=True,
        )
        del rb
    base = results[100]
    print(" ".join(f"ratio {cap}/100 = {t / base:.2f}" for cap, t in results.items() if cap != 100))


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--context-len", type=int, default=20)
    p.add_argument("--max-len", type=int, default=100)
    p.add_argument("--reps", type=int, default=100)
    p.add_argument("--threads", type=int, default=1)
    ARGS = p.parse_args()
    main()
