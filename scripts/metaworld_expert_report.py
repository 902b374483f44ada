"""Scripted-expert success on the paper's ten MetaWorld OOD tasks, driven through the TorchRL env.

For each task, MetaWorld's scripted expert (``metaworld.policies.ENV_POLICY_MAP``)
is run for N seeded episodes (seed i -> MT1 train task i) under:

* ``ID``: no disturbance.
* ``disp``: the paper's mid-episode displacement, no tracking.
* ``disp+oracle``: displacement plus the paper's oracle tracking (and snap-back).

The displaced settings are run with two observation models (five columns in all):

* ``state`` expert: reads the true 39-d state, so it re-targets the moved
  object by itself (an omniscient, reactive baseline);
* ``ID-frame`` expert: reads the state with the applied shifts removed
  (``ddp.envs.metaworld_tasks.id_frame_state``), i.e. it keeps acting as if
  the scene were still the ID one, like a policy that does not see the move.
  This is the setting the oracle protocol is designed for: with tracking
  the hand and the object move together, so ID behaviour should succeed.

Success = MetaWorld's ``success`` at any step of the episode (DP3's protocol).
Point clouds are not rendered (state-only env) to keep it fast.

    python scripts/metaworld_expert_report.py --episodes 20
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings

import numpy as np

from ddp.argtypes import positive_int
from ddp.percent import percent


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=positive_int, default=20,
                        help="seeded episodes per task and setting (seeds 0..N-1)")
    parser.add_argument("--tasks", nargs="*", default=None, help="subset of the ten tasks (default: all)")
    parser.add_argument("--max-steps", type=positive_int, default=200, help="episode length")
    args = parser.parse_args(argv)
    warnings.filterwarnings("ignore", message="Constant")  # metaworld's policies warn about their own gains

    try:
        import metaworld  # noqa: F401
    except ImportError:
        print('metaworld is not installed: pip install "ddp[sim]"', file=sys.stderr)
        return 1
    from ddp.data.sources.metaworld_expert import MetaWorldExpert, expert_succeeds
    from ddp.envs.metaworld import MetaWorldEnv, MetaWorldEnvConfig
    from ddp.envs.metaworld_tasks import PAPER_TASKS

    tasks = args.tasks or list(PAPER_TASKS)
    unknown = [t for t in tasks if t not in PAPER_TASKS]
    if unknown:
        print(f"unknown task(s) {unknown}; choose from {list(PAPER_TASKS)}", file=sys.stderr)
        return 2
    settings = [  # (column, displacement, oracle tracking, ID-frame expert)
        ("ID", False, False, False),
        ("disp, state expert", True, False, False),
        ("disp+oracle, state expert", True, True, False),
        ("disp, ID-frame expert", True, False, True),
        ("disp+oracle, ID-frame expert", True, True, True),
    ]
    rows = []
    start = time.time()
    for task in tasks:
        cells = []
        for _, displace, oracle, id_frame in settings:
            cfg = MetaWorldEnvConfig(
                task=task,
                render_point_cloud=False,
                max_episode_steps=args.max_steps,
                displacement=displace,
                oracle_tracking=oracle,
            )
            env = MetaWorldEnv(cfg)
            expert = MetaWorldExpert(task, id_frame=id_frame)
            wins = sum(expert_succeeds(env, expert, seed) for seed in range(args.episodes))
            env.close()
            cells.append(wins / args.episodes)
        rows.append((task, cells))
        print(f"{task}: " + ", ".join(f"{percent(c)} %" for c in cells), file=sys.stderr, flush=True)

    d = PAPER_TASKS
    print(f"\nScripted expert success in % over {args.episodes} seeded episodes ({args.max_steps} steps), "
          f"{time.time() - start:.0f} s\n")
    print("| task | displacement (chunk, delta) | " + " | ".join(s[0] for s in settings) + " |")
    print("|---|---|" + "---|" * len(settings))
    for task, cells in rows:
        disp = d[task].displacement
        what = f"{'+'.join(disp.bodies)} @ {disp.chunk}, {list(disp.delta)}"
        if disp.snap_back_chunk is not None:
            what += f", back @ {disp.snap_back_chunk}"
        print(f"| {task} | {what} | " + " | ".join(percent(c) for c in cells) + " |")
    means = np.mean([cells for _, cells in rows], axis=0)
    print("| mean | | " + " | ".join(percent(m, 1) for m in means) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
