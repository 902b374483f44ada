"""DDP against its DP3 baseline at the paper-sim and Simple sizes, in one process.

For each recipe, ``ddp.bench.compare`` times the DDP model and the same recipe with the
world model off (the DP3-baseline path, same code paths otherwise) in alternating rounds, and
prints obs->action, the full control cycle and the training step with their cost ratios (DDP /
baseline; baseline / DDP for samples per second). The baseline takes the same fast paths as DDP
(point blocking, the winners-only pool backward, the im2col weight gradient): the training ratios
are against DP3 on those paths; ``benchmarks/train_step.py`` also times the eager DP3 baseline
(the paths off), which issue #12's training target names. Numbers, not assertions.

    python benchmarks/ddp_vs_dp3.py --threads 2 [--repeats 5] [--train-steps 2] [--batch 32]
"""

from __future__ import annotations

import argparse
import os
import platform

import torch

from ddp import build
from ddp.bench import compare

RECIPES = [("paper sim", "recipes/base/ddp_sim.yaml"), ("Simple", "recipes/base/simple_ddp.yaml")]
ROWS = ("obs_to_action_ms", "controller_latency_ms", "control_cycle_ms", "train_step_ms", "train_samples_per_s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--train-steps", type=int, default=2)
    parser.add_argument("--batch", type=int, default=32, help="training batch (the recipes' own is 128)")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {platform.processor() or platform.machine()}, {args.threads} threads, "
          f"batch 1 for latency, batch {args.batch} for training, {args.repeats} repeats")
    print(f"| size | {' | '.join(ROWS)} |")
    print("|---|" + "---|" * len(ROWS))
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    for label, recipe in RECIPES:
        exp = build(os.path.join(root, recipe), [f"train.batch_size={args.batch}"])
        rows = compare(exp, repeats=args.repeats, device=args.device, train_steps=args.train_steps)
        cells = []
        for k in ROWS:
            v, b, ratio = rows[k]
            cells.append(f"{v:.1f} vs {b:.1f} ({ratio:.2f}x)")
        print(f"| {label} | {' | '.join(cells)} |")


if __name__ == "__main__":
    main()
