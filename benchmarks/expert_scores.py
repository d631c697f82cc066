"""Score the scripted experts: final normalized performance over N episodes per task.

    python benchmarks/expert_scores.py --episodes 100 --split eval            # docs/tasks.md numbers
    python benchmarks/expert_scores.py --episodes 5 --pictures docs           # + start/end PNGs

Episode i uses reset seed ``seed0 + i``. Prints mean, std, quartiles, min and the time per episode.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def run_episode(env, task, seed, expert_action, noise=0.0, rng=None):
    from trakdis.envs import add_movement_noise  # trakdis is imported in main(), after the GL setup

    obs, info = env.reset(seed=seed)
    frames = [obs.get("pixels")]
    for t in range(env.horizon):
        action = expert_action(task, obs["state"], t)
        if noise > 0:  # as ExpertPolicy: noise on the picker movements, the grasp command stays +-1
            add_movement_noise(action, noise, rng)
        obs, reward, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    frames.append(obs.get("pixels"))
    return float(info["normalized_performance"]), bool(info["sim_unstable"]), frames


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=None, help="default: all tasks")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--split", default="eval", choices=["train", "eval"])
    parser.add_argument("--seed0", type=int, default=0)
    parser.add_argument("--noise", type=float, default=0.0, help="expert action noise std")
    parser.add_argument("--pictures", default=None, help="directory for <task>_start.png/<task>_end.png")
    parser.add_argument("--picture-size", type=int, default=256)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    from trakdis.envs import TASKS, ClothEnv, expert_action

    tasks = args.tasks or list(TASKS)
    rng = np.random.default_rng(args.seed0)
    print(f"expert scores: {args.episodes} episodes/task, split={args.split}, seeds {args.seed0}.."
          f"{args.seed0 + args.episodes - 1}, noise={args.noise}")
    print(f"{'task':28s} {'mean':>6s} {'std':>6s} {'min':>6s} {'q25':>6s} {'median':>6s} {'q75':>6s} "
          f"{'max':>6s} {'unstable':>8s} {'s/episode':>9s}")
    for task in tasks:
        env = ClothEnv(task=task, split=args.split)
        scores, unstable = [], 0
        t0 = time.perf_counter()
        for i in range(args.episodes):
            score, bad, _ = run_episode(env, task, args.seed0 + i, expert_action, args.noise, rng)
            scores.append(score)
            unstable += bad
        dt = (time.perf_counter() - t0) / max(args.episodes, 1)
        s = np.array(scores)
        q25, q50, q75 = np.percentile(s, [25, 50, 75])
        print(f"{task:28s} {s.mean():6.3f} {s.std():6.3f} {s.min():6.3f} {q25:6.3f} {q50:6.3f} {q75:6.3f} "
              f"{s.max():6.3f} {unstable:8d} {dt:9.2f}", flush=True)
        if args.pictures:
            import cv2

            os.makedirs(args.pictures, exist_ok=True)
            pic_env = ClothEnv(task=task, split=args.split, from_pixels=True,
                               image_size=args.picture_size, render_supersample=1)
            score, _, frames = run_episode(pic_env, task, args.seed0, expert_action)
            for name, frame in zip(("start", "end"), frames):
                path = os.path.join(args.pictures, f"{task}_{name}.png")
                cv2.imwrite(path, cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
            print(f"  pictures of seed {args.seed0} (score {score:.3f}) -> {args.pictures}/{task}_start|end.png")
            pic_env.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
