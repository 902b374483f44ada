"""Training-step time of DDP and its DP3 baseline, with the CPU training fast paths on and off, in one process.

For each recipe four models are built: DDP and its DP3 baseline (world model off), each with the
fast paths (the recipe's defaults: ``encoder.pool_backward: auto``, ``cpu_weight_grad: auto``) and
without them (``dense`` / ``onednn``: the eager path before issue #12's second round). Their training
steps (loss, backward, fused AdamW, EMA; batch ``--batch``, random windows, a fitted normaliser)
are timed interleaved, round after round, so that a noisy neighbour slows all four alike; the
medians and the ratios are printed. Numbers, not assertions.

    python benchmarks/train_step.py --threads 2 [--rounds 6] [--batch 32] [--set KEY=VALUE ...] [RECIPE ...]

``--set`` overrides every model's recipe (the DP3 baseline has no world model: world-model keys leave it as
it is). ``--variant KEY=VALUE`` (repeatable) adds a fifth model, DDP with the fast paths and these overrides
(e.g. ``--variant world_model.batch_fraction=0.5``), timed in the same rounds, with its ratios. A
``world_model.target_refresh_every`` variant pays its table's refresh amortised over ``--frames`` frames.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import torch
from tensordict import TensorDict

from ddp import build
from ddp.bench import baseline_of
from ddp.models.ddp_policy import FRAME_INDEX
from ddp.models.ema import EMA
from ddp.train import make_optimizer

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RECIPES = ["recipes/base/ddp_sim.yaml", "recipes/base/simple_ddp.yaml", "recipes/metaworld/quickstart_ddp.yaml"]
EAGER = ["policy.denoiser.cpu_weight_grad=onednn", "world_model.denoiser.cpu_weight_grad=onednn",
         "encoder.pool_backward=dense"]


def train_step(recipe: str, overrides: list[str], *, dp3: bool, batch_size: int, frames: int = 1974):
    """A closure running one training step of the recipe's model on a fixed random batch.

    With ``world_model.target_refresh_every`` K the future targets come from a table of ``frames``
    random frames, and each step also re-encodes ``frames / K`` of them: the table's refresh, amortised."""
    exp = build(os.path.join(ROOT, recipe), [f"train.batch_size={batch_size}", *overrides])
    if dp3:
        exp = baseline_of(exp)
    torch.manual_seed(0)
    model, r = exp.model.train(), exp.recipe
    M, N, P, D = r.policy.obs_steps, r.policy.action_steps, r.task.num_points, r.task.agent_pos_dim
    T = model.window
    g = torch.Generator().manual_seed(0)
    pc = 0.3 * torch.randn(batch_size, T, P, r.task.point_dim, generator=g)
    pos = torch.rand(batch_size, T, D, generator=g)
    act = 2 * torch.rand(batch_size, T, r.task.action_dim, generator=g) - 1
    model.normalizer.fit({"point_cloud": pc.reshape(-1, pc.shape[-1]), "agent_pos": pos.reshape(-1, D),
                          "action": act.reshape(-1, act.shape[-1])})
    batch = TensorDict({"point_cloud": pc, "agent_pos": pos, "action": act}, batch_size=[batch_size])
    optimizer, ema = make_optimizer(model, r.train), EMA(model, r.ema)
    refresh = model.target_refresh_every if model.uses_target_table else 0
    if refresh:
        table_pc = 0.3 * torch.randn(frames, P, r.task.point_dim, generator=g)
        table_pos = torch.rand(frames, D, generator=g)
        model.refresh_target_table(table_pc, table_pos)
        batch.set(FRAME_INDEX, torch.randint(frames, (batch_size, T), generator=g))
        per_step = -(-frames // refresh)

    def step() -> None:
        if refresh:  # the table's refresh (all frames every K steps), amortised over the K steps
            with torch.no_grad():
                model.encode(table_pc[:per_step], table_pos[:per_step])
        loss = model.loss(batch)["loss"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        ema.update(model)

    step()  # warm-up
    return step


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recipes", nargs="*", default=RECIPES)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--batch", type=int, default=32, help="training batch (the base recipes' own is 128)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="recipe override for every model (repeatable)")
    parser.add_argument("--variant", action="append", default=[], metavar="KEY=VALUE",
                        help="also time DDP (fast paths) with these overrides (repeatable)")
    parser.add_argument("--frames", type=int, default=1974,
                        help="training frames whose target-table refresh a world_model.target_refresh_every variant "
                             "pays, amortised (default 1974: the quickstart's 20 drawer-open demos)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {platform.processor() or platform.machine()}, {args.threads} threads, "
          f"batch {args.batch}, medians of {args.rounds} interleaved rounds"
          + (f", overrides {' '.join(args.overrides)}" if args.overrides else ""))
    print("| recipe | DDP fast | DP3 fast | DDP / DP3 fast | DDP eager | DP3 eager (baseline) | DDP / DP3 eager "
          "| DDP fast / DP3 eager | speed-up DDP | speed-up DP3 |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    variants = []
    for recipe in args.recipes:
        steps = {(method, path): train_step(recipe, [*args.overrides, *([] if path == "fast" else EAGER)],
                                            dp3=method == "dp3",
                                            batch_size=args.batch)
                 for method in ("ddp", "dp3") for path in ("fast", "eager")}
        if args.variant:
            steps["ddp", "variant"] = train_step(recipe, [*args.overrides, *args.variant], dp3=False,
                                                 batch_size=args.batch, frames=args.frames)
        times = {k: [] for k in steps}
        for _ in range(args.rounds):
            for k, step in steps.items():
                t = time.perf_counter()
                step()
                times[k].append(1000 * (time.perf_counter() - t))
        ms = {k: statistics.median(v) for k, v in times.items()}
        df, pf, de, pe = ms["ddp", "fast"], ms["dp3", "fast"], ms["ddp", "eager"], ms["dp3", "eager"]
        print(f"| {recipe} | {df:.0f} ms | {pf:.0f} ms | {df / pf:.2f}x | {de:.0f} ms | {pe:.0f} ms | {de / pe:.2f}x "
              f"| {df / pe:.2f}x | {de / df:.2f}x | {pe / pf:.2f}x |", flush=True)
        if args.variant:
            dv = ms["ddp", "variant"]
            variants.append(f"| {recipe} | {dv:.0f} ms | {dv / df:.2f}x | {dv / pf:.2f}x | {dv / pe:.2f}x |")
    if args.variant:
        print(f"\nDDP with {' '.join(args.variant)} (fast paths), same rounds:\n")
        print("| recipe | DDP variant | / DDP fast | / DP3 fast | / DP3 eager (baseline) |")
        print("|---|---|---|---|---|")
        print("\n".join(variants))


if __name__ == "__main__":
    main()
