"""Point-cloud tracker error against the oracle displacement on the simulated Franka stack task.

Runs the task's scripted oracle (it follows the true object positions) with the
paper's OOD schedule (``displacement: true``: the pink block moved 15 cm at chunk
2 while the arm approaches it, the green one 15 cm at chunk 10 while the pink
block is carried), calls the tracker once per chunk on the tracking camera's
frame, as the DDP controller does, and reports:

* for each displaced object, the error ``|Delta p_tracker - Delta p_oracle|``
  in millimetres on the first observation after the move where the tracker
  sees the object (and how many chunks after the move that was; the
  controller reads the offsets when it enters OOD mode, usually the first
  observation after the move, where the arm may hide the object);
* spurious offsets: chunks where an object that the oracle says is not
  displaced (and the tracker does not see carried) gets a non-zero offset;
* the tracker's time per call.

    python benchmarks/tracker_error.py --seeds 20
    python benchmarks/tracker_error.py --seeds 20 --size 240x320 --masks geometry
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from tensordict import TensorDict  # noqa: E402


def run(seeds: list[int], size: tuple[int, int], masks: str, refine: str, metric: str, table_height) -> dict:
    from ddp.envs.franka.env import FrankaEnv, FrankaEnvConfig
    from ddp.trackers.pointcloud import IsolationConfig, PointCloudTracker, PointCloudTrackerConfig

    h, w = size
    cfg = FrankaEnvConfig(task="stack", tracking_camera=True, render_point_cloud=False, displacement=True,
                          tracking_image_height=h, tracking_image_width=w, obs_every=8, obs_history=1)
    env = FrankaEnv(cfg)
    task = env.task
    rows = cfg.displacement_schedule()
    names = list(task.object_names)
    expected = [list(0.5 * (np.asarray(task.id_lines[n][0]) + np.asarray(task.id_lines[n][1]))) for n in names]
    errors = {n: [] for n in names}  # at the first observation after the move where the tracker sees it
    delays = {n: [] for n in names}  # chunks from the move to that observation (1 = the first one)
    hidden = {n: 0 for n in names}  # moves whose object is not visible on the first observation after it
    lost = {n: 0 for n in names}  # ... nor on any later one of the episode
    spurious, spurious_max, calls, seconds = 0, 0.0, 0, 0.0
    for seed in seeds:
        tracker = PointCloudTracker(PointCloudTrackerConfig(
            num_objects=len(names), segmentation=masks, refine=refine, icp_metric=metric,
            isolation=IsolationConfig(expected_positions=expected, table_height=table_height),
        ))
        oracle = task.oracle()
        td = env.reset(seed=seed)
        pending = {}  # object index -> chunk of its move, until the tracker sees it
        for step in range(cfg.episode_steps + 1):
            if step % cfg.chunk_len == 0:
                chunk = step // cfg.chunk_len
                for r in rows:
                    if r.chunk + 1 == chunk:  # the observation at the end of chunk k shows chunk k's move
                        for name in r.bodies:
                            pending[names.index(name)] = r.chunk
                obs = td.clone()
                obs.set("chunk_index", torch.tensor([chunk]))
                t0 = time.perf_counter()
                out = tracker(obs)
                seconds += time.perf_counter() - t0
                calls += 1
                off = out["ddp", "offsets"].double().numpy()
                carried = out["ddp", "object_carried"].numpy()
                visible = out["ddp", "object_visible"].numpy()
                truth = td["privileged", "displacement"].double().numpy()
                for k in list(pending):
                    if chunk == pending[k] + 1 and not visible[k]:
                        hidden[names[k]] += 1
                    if visible[k] and not carried[k]:
                        errors[names[k]].append(1000.0 * float(np.linalg.norm(off[k] - truth[k])))
                        delays[names[k]].append(chunk - pending.pop(k))
                for k in range(len(names)):
                    if k in pending or carried[k] or np.linalg.norm(truth[k]) > 0:
                        continue
                    if np.linalg.norm(off[k]) > 0:
                        spurious += 1
                        spurious_max = max(spurious_max, 1000.0 * float(np.linalg.norm(off[k])))
            if step == cfg.episode_steps:
                break
            action = torch.as_tensor(oracle(td))
            td = env.step(TensorDict({"action": action}, batch_size=[]))["next"]
        for k in pending:
            lost[names[k]] += 1
    env.close()
    return {"errors": errors, "delays": delays, "hidden": hidden, "lost": lost, "spurious": spurious,
            "spurious_max": spurious_max, "calls": calls, "ms_per_call": 1000.0 * seconds / max(calls, 1),
            "rows": [(r.bodies, r.chunk, r.delta) for r in rows]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--first-seed", type=int, default=1000)
    p.add_argument("--size", default="120x160", help="tracking camera HxW (the env's default: 120x160)")
    p.add_argument("--masks", default="mask", choices=["auto", "mask", "geometry"])
    p.add_argument("--refine", default="translation", choices=["none", "translation", "rigid"])
    p.add_argument("--metric", default="plane", choices=["point", "plane"])
    p.add_argument("--table-height", type=float, default=None, help="known table z (geometry masks); default RANSAC")
    args = p.parse_args()
    torch.set_num_threads(1)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    r = run(list(range(args.first_seed, args.first_seed + args.seeds)), size, args.masks, args.refine, args.metric,
            args.table_height)
    print(f"stack, {args.seeds} seeds, tracking camera {size[0]}x{size[1]}, masks={args.masks}, "
          f"refine={args.refine}/{args.metric}; moves: "
          + "; ".join(f"{'+'.join(b)} {list(d)} at chunk {c}" for b, c, d in r["rows"]))
    print("| object | moves | hidden on the first observation | error (mm) mean / median / max | "
          "chunks after the move (mean) | never seen |")
    print("|---|---|---|---|---|---|")
    for name, e in r["errors"].items():
        n = len(e) + r["lost"][name]
        if n == 0:
            continue
        e = np.asarray(e) if e else np.full(1, np.nan)
        d = np.mean(r["delays"][name]) if r["delays"][name] else float("nan")
        print(f"| {name} | {n} | {r['hidden'][name]} | {e.mean():.1f} / {np.median(e):.1f} / {e.max():.1f} | "
              f"{d:.2f} | {r['lost'][name]} |")
    print(f"spurious offsets (object not displaced, not carried, offset != 0): {r['spurious']} of "
          f"{r['calls']} calls x {len(r['errors'])} objects (largest {r['spurious_max']:.1f} mm); "
          f"{r['ms_per_call']:.1f} ms per call")


if __name__ == "__main__":
    main()
