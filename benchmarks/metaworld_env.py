"""Per-step costs of the MetaWorld env: simulation, rendering, point cloud, FPS.

Prints median milliseconds for one task:

* raw MetaWorld step (no TorchRL, no rendering),
* TorchRL env step without rendering (``render_point_cloud=False``),
* depth render alone, back-projection + crop, farthest point sampling,
* rendered frame + point cloud (what a consumed observation costs),
* TorchRL env step with a point cloud at every step.

    python benchmarks/metaworld_env.py --task button-press --image-size 84
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import torch


def median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Per-step costs of the MetaWorld env (median ms).")
    parser.add_argument("--task", default="button-press", help="MetaWorld v3 task name")
    parser.add_argument("--image-size", type=int, default=84, help="depth image height = width")
    parser.add_argument("--num-points", type=int, default=512, help="points after FPS")
    parser.add_argument("--repeats", type=int, default=200, help="timed repetitions per measurement")
    args = parser.parse_args(argv)

    try:
        from ddp.envs.metaworld import MetaWorldEnv, MetaWorldEnvConfig
        from ddp.envs.pointcloud import crop_points, depth_to_points
        from ddp.envs.pointcloud import farthest_point_sample as fps

        cfg = MetaWorldEnvConfig(task=args.task, image_size=args.image_size, num_points=args.num_points)
        env = MetaWorldEnv(cfg)
    except ImportError as err:
        print(err, file=sys.stderr)
        return 1
    fast = MetaWorldEnv(MetaWorldEnvConfig(task=args.task, render_point_cloud=False))
    td = env.reset(seed=0)
    fast_td = fast.reset(seed=0)
    rng = np.random.default_rng(0)
    n = args.repeats

    def torchrl_step(e, state):
        state["action"] = torch.as_tensor(rng.uniform(-1, 1, 4), dtype=torch.float32)
        out = e.step(state)["next"]
        if e.steps_done >= 150:
            out = e.reset()
        return out

    def step_fast():
        nonlocal fast_td
        fast_td = torchrl_step(fast, fast_td)

    def step_render():
        nonlocal td
        td = torchrl_step(env, td)

    def raw_step():
        if fast.sim.curr_path_length >= 150:
            fast.sim.reset()
        fast.sim.step(rng.uniform(-1, 1, 4))

    data, camera = env.sim.data, env._camera  # the env's CloudCamera: its depth renderer and back-projection
    cam = camera.camera
    env._render_cloud()  # build the renderer, compile FPS

    def render_depth():
        return camera.renderer.depth(data, cam, camera.size)

    depth = render_depth()
    rays = camera._to_cloud.rays

    def back_project():
        world = depth_to_points(depth, rays, data.cam_xpos[cam], data.cam_xmat[cam])
        return crop_points(world, cfg.crop_min, cfg.crop_max)

    points = back_project()

    rows = [
        ("raw MetaWorld step", median_ms(raw_step, n)),
        ("TorchRL step, no rendering", median_ms(step_fast, n)),
        (f"depth render {args.image_size}x{args.image_size}", median_ms(render_depth, n)),
        ("back-project + crop", median_ms(back_project, n)),
        (f"FPS {len(points)} -> {args.num_points} points", median_ms(lambda: fps(points, args.num_points), n)),
        ("rendered frame + point cloud", median_ms(env._render_cloud, n)),
        ("TorchRL step with point cloud", median_ms(step_render, n)),
    ]
    env.close()
    fast.close()
    print(f"task {args.task}, image {args.image_size}px, {args.num_points} points, median of {n} (ms)")
    for name, ms in rows:
        print(f"  {name:<40s} {ms:8.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
