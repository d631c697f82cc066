"""Speed of the cloth environments (one expert episode per measurement, self-collision on).

    python benchmarks/env_speed.py                 # all tasks, 100-step episodes
    python benchmarks/env_speed.py --tasks ClothFold --steps 50 --no-parallel

Per task it prints:
* env steps/s of the TorchRL env (``make_env`` + ``ExpertPolicy``), state-only and with 32x32 pixels,
  and the seconds a 100-step pixel episode takes;
* the ratio of the gym env's step time to a raw ``mj_step`` loop that replays the same physics
  (same model, the same picker positions and grasps recorded from the env, same number of
  ``mj_step`` calls): ``overhead = env / raw - 1``;
* the speed-up of a 2-worker ``ParallelEnv`` over one env (frames/s ratio).
All numbers of one line come from the same run on the same machine; on a shared machine they
move with the load (see ``os.getloadavg`` printed on top).
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time

import numpy as np


class _RecordingMujoco:
    """Stands in for the ``mujoco`` module inside ``cloth_env``: records the inputs of each ``mj_step``."""

    def __init__(self, mujoco):
        self._mujoco = mujoco
        self.records = []

    def __getattr__(self, name):
        return getattr(self._mujoco, name)

    def mj_step(self, m, d):
        self.records.append((d.mocap_pos.copy(), d.eq_active.copy(), m.eq_obj2id.copy(), m.eq_data.copy()))
        self._mujoco.mj_step(m, d)


def gym_vs_raw(task, steps, seed, repeats=3):
    """(env CPU seconds, raw mj_step loop CPU seconds, number of mj_step calls) for one expert episode.

    CPU time of this process (``time.process_time``), which a busy shared machine disturbs less
    than wall-clock time.
    """
    import mujoco

    from trakdis.envs import ClothEnv, cloth_env, expert_action

    env = ClothEnv(task=task, horizon=steps)
    obs, _ = env.reset(seed=seed)
    actions = []
    for t in range(steps):
        a = expert_action(task, obs["state"], t)
        actions.append(a)
        obs, *_ = env.step(a)
    # pass 1: the env replaying the expert's actions (same episode: the env is deterministic),
    # timed `repeats` times; the minimum is the least disturbed by other processes
    env_time = float("inf")
    for _ in range(repeats):
        env.reset(seed=seed)
        t0 = time.process_time()
        for a in actions:
            env.step(a)
        env_time = min(env_time, time.process_time() - t0)
    # pass 2: record the physics inputs of the same episode
    recorder = _RecordingMujoco(mujoco)
    cloth_env.mujoco = recorder
    try:
        obs, _ = env.reset(seed=seed)
        for a in actions:
            env.step(a)
    finally:
        cloth_env.mujoco = mujoco
    model = env.model
    records = recorder.records[10:]  # drop the 10 settle steps of reset (not part of env.step)
    raw_time = float("inf")
    for _ in range(repeats):
        data = mujoco.MjData(model)
        for _ in range(10):
            mujoco.mj_step(model, data)
        t0 = time.process_time()
        for mocap, active, obj2id, eqdata in records:
            data.mocap_pos[:] = mocap
            data.eq_active[:] = active
            model.eq_obj2id[:] = obj2id
            model.eq_data[:] = eqdata
            mujoco.mj_step(model, data)
        raw_time = min(raw_time, time.process_time() - t0)
        # the replay is the env's physics, bit for bit
        assert np.array_equal(data.qpos, env.data.qpos), "raw replay diverged from the env"
    return env_time, raw_time, len(records)


def torchrl_rate(task, steps, seed, from_pixels):
    from trakdis.envs import ExpertPolicy, make_env

    env = make_env(task, from_pixels=from_pixels, seed=seed, horizon=steps)
    policy = ExpertPolicy(task)
    t0 = time.perf_counter()
    env.rollout(steps, policy)
    dt = time.perf_counter() - t0
    env.close()
    return steps / dt


def parallel_speedup(task, steps, seed, from_pixels, use_buffers=None, sleep_wait=False):
    from torchrl.envs import ParallelEnv

    from trakdis.envs import ExpertPolicy, SleepWaitParallelEnv, make_env

    make = functools.partial(make_env, task, from_pixels=from_pixels, horizon=steps)
    single = make()
    single.set_seed(seed)
    policy = ExpertPolicy(task)
    t0 = time.perf_counter()
    single.rollout(steps, policy)
    t_single = time.perf_counter() - t0
    single.close()
    # TorchRL 0.14's shared-memory path makes the main process spin-poll the workers' done flags, which
    # takes a whole core away from 2 workers on a 2-core machine; use_buffers=False pickles every step
    # through the pipes; SleepWaitParallelEnv (the recipes' choice) keeps the buffers and sleeps.
    env = SleepWaitParallelEnv(2, make) if sleep_wait else ParallelEnv(2, make, use_buffers=use_buffers)
    env.set_seed(seed)
    env.reset()  # start the workers outside the timing
    t0 = time.perf_counter()
    env.rollout(steps, policy, break_when_any_done=False)
    t_par = time.perf_counter() - t0
    env.close()
    return (2 * steps / t_par) / (steps / t_single)


def _gym_episode(task, steps, seed, ready=None, go=None):
    from trakdis.envs import ClothEnv, expert_action

    env = ClothEnv(task=task, horizon=steps, from_pixels=True)
    obs, _ = env.reset(seed=seed)
    if ready is not None:
        ready.set()
        go.wait()
    t0 = time.perf_counter()
    for t in range(steps):
        obs, *_ = env.step(expert_action(task, obs["state"], t))
    elapsed = time.perf_counter() - t0
    env.close()
    return elapsed


def two_process_speedup(task, steps, seed):
    """Throughput of 2 plain processes (no TorchRL) over 1: what the machine allows right now.

    Spawned (forking a process that holds an EGL context can hang), timed from a start signal
    sent once both children are ready, so interpreter start-up is not counted.
    """
    import multiprocessing as mp

    t_single = _gym_episode(task, steps, seed)
    ctx = mp.get_context("spawn")
    go = ctx.Event()
    readies = [ctx.Event() for _ in range(2)]
    procs = [ctx.Process(target=_gym_episode, args=(task, steps, seed, r, go)) for r in readies]
    for p in procs:
        p.start()
    for r in readies:
        r.wait()
    t0 = time.perf_counter()
    go.set()
    for p in procs:
        p.join()
    return 2 * t_single / (time.perf_counter() - t0)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=None)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-parallel", action="store_true")
    args = parser.parse_args(argv)

    import torch

    torch.set_num_threads(1)
    from trakdis.envs import TASKS

    print(f"cpu count {os.cpu_count()}, load average {os.getloadavg()}, steps/episode {args.steps}")
    print(f"{'task':28s} {'state sps':>9s} {'pixel sps':>9s} {'s/100 px':>8s} {'env ms':>7s} "
          f"{'raw ms':>7s} {'overhead':>8s} {'2-worker':>8s} {'2w nobuf':>8s} {'2w sleep':>8s} {'2 procs':>8s}")
    for task in args.tasks or TASKS:
        env_t, raw_t, n_steps = gym_vs_raw(task, args.steps, args.seed)
        sps = torchrl_rate(task, args.steps, args.seed, from_pixels=False)
        pps = torchrl_rate(task, args.steps, args.seed, from_pixels=True)
        nan = float("nan")
        speedup = nan if args.no_parallel else parallel_speedup(task, args.steps, args.seed, True)
        speedup_nb = nan if args.no_parallel else parallel_speedup(task, args.steps, args.seed, True, False)
        speedup_sw = nan if args.no_parallel else parallel_speedup(task, args.steps, args.seed, True, sleep_wait=True)
        bound = nan if args.no_parallel else two_process_speedup(task, args.steps, args.seed)
        print(f"{task:28s} {sps:9.1f} {pps:9.1f} {100 / pps:8.2f} {1e3 * env_t / args.steps:7.2f} "
              f"{1e3 * raw_t / args.steps:7.2f} {env_t / raw_t - 1:8.1%} {speedup:7.2f}x {speedup_nb:7.2f}x {speedup_sw:7.2f}x {bound:7.2f}x",
              flush=True)
    print("state/pixel sps: TorchRL env steps per second (expert policy included); env ms / raw ms: "
          "CPU time per step of the gym env vs a raw mj_step replay of the same episode; overhead = env/raw - 1; "
          "2-worker: ParallelEnv(2) frames/s over one env's, with pixels (2w nobuf: use_buffers=False; "
          "2w sleep: trakdis's SleepWaitParallelEnv, the recipes' choice); "
          "2 procs: two plain processes running the gym env over one (the machine's bound right now).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
