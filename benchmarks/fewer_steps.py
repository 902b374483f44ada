"""Latency of DDP with fewer denoising steps against the DP3 baseline's obs->action at its own step count, in one process.

For each step count k, the recipe's policy and world model sample with DDIM-k; the baseline is the same
recipe with the world model off at the recipe's own step count (DDIM-10 in every recipe). Few steps
sample best with ``timestep_spacing: trailing`` (the first step at the top noise level); the timing
does not depend on it. Success at each k is measured
separately (``ddp eval ... --set policy.scheduler.num_inference_steps=k --set
world_model.scheduler.num_inference_steps=k``); the README lists it.

    python benchmarks/fewer_steps.py [--recipe recipes/metaworld/quickstart_ddp.yaml] [--steps 10,5,3,2,1]
"""

from __future__ import annotations

import argparse
import os
import statistics

import torch

from ddp import build
from ddp.bench import baseline_of, bench

ROWS = ("obs_to_action_ms", "controller_latency_ms", "control_cycle_ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recipe", default="recipes/metaworld/quickstart_ddp.yaml")
    parser.add_argument("--steps", default="10,5,3,2,1", help="comma-separated DDIM step counts")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    recipe = os.path.join(root, args.recipe)
    baseline = baseline_of(build(recipe))
    base = bench(baseline, repeats=args.repeats, train_steps=1)
    # every ratio is against the baseline's obs->action: issue #12's targets are set against DP3's predict
    print(f"{args.recipe}: batch 1, {args.threads} threads, medians of {args.repeats}; DP3 baseline "
          f"(DDIM-{baseline.recipe.policy.scheduler.get('num_inference_steps')}) obs->action "
          f"{base['obs_to_action_ms']:.1f} ms first; each row's ratios divide by the median of the baseline's timings "
          f"up to that row (timed again beside every step count)")
    print(f"| DDIM steps | {' | '.join(ROWS)} | DP3 baseline obs->action, timed beside it |")
    print("|---|" + "---|" * (len(ROWS) + 1))
    timings = [base["obs_to_action_ms"]]
    for k in (int(s) for s in args.steps.split(",")):
        exp = build(recipe, [f"policy.scheduler.num_inference_steps={k}", f"world_model.scheduler.num_inference_steps={k}"])
        mine = bench(exp, repeats=args.repeats, train_steps=1)
        # the baseline timed again beside each step count (a slow spell of a shared machine reaches both),
        # the denominator the median of its timings so far
        again = bench(baseline, repeats=args.repeats, train_steps=1)["obs_to_action_ms"]
        timings.append(again)
        denominator = statistics.median(timings)
        cells = [f"{mine[r]:.1f} ({mine[r] / denominator:.2f}x)" for r in ROWS]
        print(f"| {k} | {' | '.join(cells)} | {again:.1f} |")


if __name__ == "__main__":
    main()
