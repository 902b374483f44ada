"""Milliseconds per step of the real trainer (data loading, the loss, backward, AdamW, EMA, and a
target-table refresh where one is due), for recipes built with overrides, timed interleaved in one process.

Each variant trains ``--steps`` and then ``2 x --steps`` steps from scratch into temporary directories, round
after round (a noisy neighbour slows every variant alike); a step costs the difference of the two runs' times
over ``--steps``, so what each run pays once (building, the first slow steps, the final checkpoint, whose size
differs between DDP and DP3) cancels. Take ``--steps`` a multiple of ``world_model.target_refresh_every``.
The medians and their ratios to the first variant are printed.
Numbers, not assertions. The quickstart's demos must exist (``ddp demos recipes/metaworld/quickstart_ddp.yaml``).

    python benchmarks/trainer_steps.py --threads 1 --steps 100 --rounds 2 \\
        dp3=recipes/metaworld/quickstart_dp3.yaml ddp=recipes/metaworld/quickstart_ddp.yaml \\
        'table100=recipes/metaworld/quickstart_ddp.yaml world_model.target_refresh_every=100'
"""

from __future__ import annotations

import argparse
import statistics
import tempfile

import torch

from ddp import build


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("variants", nargs="+", metavar="LABEL=RECIPE [KEY=VALUE ...]",
                        help="a label, the recipe, and overrides separated by spaces (quote the whole)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--steps", type=int, default=100, help="training steps per variant and round")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    variants = {}
    for spec in args.variants:
        label, _, rest = spec.partition("=")
        recipe, *overrides = rest.split()
        variants[label] = (recipe, [f"train.num_threads={args.threads}", "train.logger=none", *overrides])
    times = {label: [] for label in variants}
    for r in range(args.rounds):
        for label, (recipe, overrides) in variants.items():
            seconds = []
            for steps in (args.steps, 2 * args.steps):
                with tempfile.TemporaryDirectory() as out:
                    result = build(recipe, [*overrides, f"train.max_steps={steps}"]).train(output_dir=out,
                                                                                           progress=False)
                seconds.append(result.seconds)
            times[label].append(1000.0 * (seconds[1] - seconds[0]) / args.steps)
            print(f"round {r}: {label} {times[label][-1]:.1f} ms/step", flush=True)
    first = statistics.median(times[next(iter(times))])
    print(f"\n{args.threads} threads, {args.steps} steps, medians of {args.rounds} rounds")
    for label, t in times.items():
        m = statistics.median(t)
        print(f"{label:<16} {m:8.1f} ms/step  {m / first:5.2f}x {next(iter(times))}")


if __name__ == "__main__":
    main()
