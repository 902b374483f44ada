"""How well a trained policy reproduces its own training actions: a check that needs no simulator run.

For each checkpoint, the policy samples action chunks for N windows drawn from the recipe's demonstrations
(the observation steps it conditions on) and compares them with the demonstrated chunk: the mean squared
error, against the demonstrated actions' variance across windows (what always predicting the mean action
would score). A policy that learned its demos scores far under the variance; one near it has learned
nothing usable, whatever its training loss says (e.g. FlowPolicy's consistency objective on Adroit door
after 3000 steps). Actions are in the dataset's units.

    python scripts/policy_fit.py runs/suites/adroit_cpu/door__dp3__seed0/last.pt \\
        runs/suites/adroit_cpu/door__flowpolicy__seed0/last.pt --windows 64
"""

from __future__ import annotations

import argparse
import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")


def fit(checkpoint: str, windows: int, seed: int) -> dict:
    import torch

    from ddp.checkpoint import load_checkpoint, stored_recipe
    from ddp.data.sequence import SequenceDataset
    from ddp.experiment import Experiment

    # the recipe stored in the checkpoint; its plugin modules are not imported (as ddp eval without --trust-plugins)
    state = load_checkpoint(checkpoint)
    exp = Experiment(stored_recipe(checkpoint, state), checkpoint, trust_plugins=False)
    exp.load_checkpoint(checkpoint, state=state)
    pol = exp.recipe.policy
    data = SequenceDataset(exp.episodes(), pol.horizon, pad_before=pol.obs_steps - 1,
                           pad_after=pol.action_steps - 1, keys=["point_cloud", "agent_pos", "action"])
    picks = torch.randint(0, len(data), (windows,), generator=torch.Generator().manual_seed(seed))
    batch = torch.stack([data[int(i)] for i in picks])
    obs = batch[:, : pol.obs_steps].select("point_cloud", "agent_pos")
    obs.batch_size = [windows]
    torch.manual_seed(seed)
    with torch.no_grad():
        predicted = exp.model(obs)["action_chunk"]
    demo = batch["action"]
    return {"mse": float(((predicted - demo) ** 2).mean()), "variance": float(demo.var(0).mean()),
            "horizon": pol.horizon, "action_dim": demo.shape[-1]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoints", nargs="+", help="last.pt files written by ddp train")
    parser.add_argument("--windows", type=int, default=64, help="demonstration windows sampled (at least 2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the windows drawn and of the sampling noise")
    args = parser.parse_args(argv)
    if args.windows < 2:
        parser.error(f"--windows: at least 2 (a variance needs two windows); got {args.windows}")
    from ddp.errors import DDPError

    rows = []
    for path in args.checkpoints:  # every checkpoint read before the table: a bad path fails in one line
        try:
            rows.append((path, fit(path, args.windows, args.seed)))
        except DDPError as err:
            print(f"ddp: error: {err}", file=sys.stderr)
            return 2
    print("| checkpoint | horizon x action dims | MSE to the demos | their variance | ratio |")
    print("|---|---|---|---|---|")
    for path, r in rows:
        ratio = f"{r['mse'] / r['variance']:.3g}" if r["variance"] > 0 else "- (constant demos)"
        print(f"| {path} | {r['horizon']} x {r['action_dim']} | {r['mse']:.3g} | {r['variance']:.3g} | {ratio} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
