"""Franka env cost: simulated step, policy-camera frame (depth render + cloud), tracking frame, reset.

    python benchmarks/franka_env.py [--task stack] [--steps 200] [--height 120 --width 160 --points 256]

Prints medians in milliseconds (one process, MUJOCO_GL=egl). "step" is one env
action without rendering (robosuite OSC step + observation); "render" is the
policy camera's depth frame alone; "cloud" back-projection + crop + pre-sample
+ farthest point sampling; "tracking" the second camera's depth + segmentation.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
import torch  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="stack")
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--height", type=int, default=120)
    p.add_argument("--width", type=int, default=160)
    p.add_argument("--points", type=int, default=256)
    p.add_argument("--presample", type=int, default=4000)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    from ddp.envs.franka.env import FrankaEnv, FrankaEnvConfig

    t0 = time.perf_counter()
    env = FrankaEnv(FrankaEnvConfig(task=args.task, num_points=args.points, presample=args.presample,
                                    image_height=args.height, image_width=args.width, tracking_camera=True,
                                    obs_every=10**6))  # fmt: skip
    build = time.perf_counter() - t0
    oracle = env.task.oracle()
    td = env.reset(seed=0)
    steps, renders, clouds, tracks, resets = [], [], [], [], []
    for i in range(args.steps):
        td["action"] = torch.as_tensor(oracle(td))
        t = time.perf_counter()
        td = env.step(td)["next"]
        steps.append(time.perf_counter() - t)
        t = time.perf_counter()
        frame = env.backend.render("policy")
        renders.append(time.perf_counter() - t)
        t = time.perf_counter()
        cloud = env._cloud_fn(frame, np.random.default_rng(i))
        clouds.append(time.perf_counter() - t)
        t = time.perf_counter()
        env.backend.render("tracking")
        tracks.append(time.perf_counter() - t)
        if bool(td["done"]):
            t = time.perf_counter()
            oracle.reset()
            td = env.reset()
            resets.append(time.perf_counter() - t)
    ms = lambda v: 1e3 * float(np.median(v[5:] if len(v) > 10 else v))  # noqa: E731
    print(f"task {args.task}: build {build:.2f} s; per step (median ms): step {ms(steps):.1f}, "
          f"policy depth {args.height}x{args.width} {ms(renders):.1f}, "
          f"cloud ({args.presample} -> {cloud.shape[0]} points) {ms(clouds):.1f}, "
          f"tracking depth+segmentation {ms(tracks):.1f}"
          + (f", reset {ms(resets):.1f}" if resets else ""))
    env.close()


if __name__ == "__main__":
    main()
