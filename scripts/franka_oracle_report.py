"""Scripted-oracle success on the simulated Franka tasks (stack, pour, press), driven through the TorchRL env.

For each task the kinematic oracle (``FrankaTask.oracle``, with its per-episode
variance) runs N seeded episodes (seed i -> ID layout i) under:

* ``ID``: no disturbance (what ``ddp demos`` keeps);
* ``disp``: the task's OOD displacements, the oracle reading the true object
  positions (it re-targets the moved objects: a reactive, omniscient baseline);
* ``disp/ID-frame``: displacements, the oracle acting on the ID positions
  (what a policy that does not see the move would do): must fail, or the
  success check would not follow the objects;
* ``disp+tracking/ID-frame``: the same with the env's oracle tracking (the
  end-effector follows each displacement, and snaps back on two-stage rows).

Success = the task's success at any step of the episode, unless it fails for good (press: an
over-press) at any step, as evaluation judges it (episodes run to their end). Also printed: the
steps to the first success (ID) and the cost per executed simulated step. Point clouds
are not rendered (it only measures the oracle).

    python scripts/franka_oracle_report.py --episodes 30
"""

from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from ddp.argtypes import positive_int  # noqa: E402

SETTINGS = {
    "ID": ({}, False),
    "disp": ({"displacement": True}, False),
    "disp/ID-frame": ({"displacement": True}, True),
    "disp+tracking/ID-frame": ({"displacement": True, "oracle_tracking": True}, True),
}


def run(env, oracle, seed: int) -> tuple[int | None, int]:
    """One whole episode, as evaluation runs it (to its end: a later failure for good, press's over-press,
    revokes an earlier success); (steps to the first success, or None when it did not succeed, and the
    steps executed)."""
    oracle.reset()
    td = env.reset(seed=seed)
    first = None
    for t in range(env.config.episode_steps):
        td["action"] = torch.as_tensor(oracle(td))
        td = env.step(td)["next"]
        if bool(td["failed"]):  # failed for good: the episode fails whatever came before
            return None, t + 1
        if first is None and bool(td["success"]):
            first = t + 1
    return first, env.config.episode_steps


TASKS = ("stack", "pour", "press")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=positive_int, default=20, help="seeded episodes per task and setting")
    parser.add_argument("--first-seed", type=int, default=0, help="the first episode's seed (default 0)")
    parser.add_argument("--tasks", nargs="*", default=list(TASKS), choices=list(TASKS))
    parser.add_argument("--settings", nargs="*", default=list(SETTINGS), choices=list(SETTINGS))
    args = parser.parse_args(argv)
    try:
        import robosuite  # noqa: F401
    except ImportError:
        print('robosuite is not installed: pip install -e ".[sim]" (the simulated Franka tasks need it)', file=sys.stderr)
        return 1
    from ddp.envs.franka.env import FrankaEnv, FrankaEnvConfig, make_sim_backend

    seeds = range(args.first_seed, args.first_seed + args.episodes)
    print(f"| task | {' | '.join(args.settings)} | steps to success (ID: min / median / max) | ms per step |")
    print("|---|" + "---|" * (len(args.settings) + 2))
    for task in args.tasks:
        backend = make_sim_backend(FrankaEnvConfig(task=task))
        cells, lengths, ms = [], [], float("nan")
        try:
            for name in args.settings:
                options, id_frame = SETTINGS[name]
                env = FrankaEnv(FrankaEnvConfig(task=task, render_point_cloud=False, **options), backend=backend)
                oracle = env.task.oracle(id_frame=id_frame)
                start, steps, results = time.perf_counter(), 0, []
                for seed in seeds:
                    n, executed = run(env, oracle, seed)
                    results.append(n)
                    steps += executed
                if name == "ID":
                    lengths = [n for n in results if n is not None]
                    ms = 1e3 * (time.perf_counter() - start) / max(1, steps)
                ok = sum(n is not None for n in results)
                cells.append(f"{ok}/{len(results)}")
        finally:
            backend.close()
        span = f"{min(lengths)} / {int(np.median(lengths))} / {max(lengths)}" if lengths else "-"
        timing = f"{ms:.1f}" if lengths or "ID" in args.settings else "- (ID not run)"
        print(f"| {task} | {' | '.join(cells)} | {span} | {timing} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
