"""D_R-I separability of a trained checkpoint: ID against displaced episodes, chunk by chunk.

Runs the base policy with the world model forecasting every cycle on N
held-out ID layouts and on the same layouts with the env's displacements
(the ``ood_base`` protocol), then prints per chunk the ID and displaced D_R-I
and their AUROC, and per displaced episode the first chunk above tau (the
recipe's, or calibrated as ``ddp eval`` does). Writes ``separability.json``
and ``separability.png`` (ID band, displaced lines, tau) to --output-dir.
Use it to set ``controller.detector.tau`` or to see why a detector fires
late (see ddp/separability.py).

    python scripts/discrepancy_report.py --checkpoint runs/franka_cpu_stack/last.pt --episodes 10
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True, help="a checkpoint written by ddp train (its recipe is inside)")
    parser.add_argument("--episodes", type=int, default=10, help="ID episodes, and as many displaced ones")
    parser.add_argument("--seed", type=int, default=None, help="first layout seed (default: eval.seed)")
    parser.add_argument("--tau", type=float, default=None, help="threshold (default: the recipe's, else calibrated)")
    parser.add_argument("--output-dir", default=None, help="default: <checkpoint dir>/separability")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument("--trust-plugins", action="store_true",
                        help="import the plugin modules the checkpoint's recipe lists (runs their code)")
    args = parser.parse_args(argv)

    from ddp import results_json
    from ddp.experiment import experiment_from_checkpoint
    from ddp.separability import format_report, plot_separability, separability

    exp = experiment_from_checkpoint(args.checkpoint, trust_plugins=args.trust_plugins)
    rep = separability(exp, episodes=args.episodes, seed=args.seed, tau=args.tau, progress=not args.quiet)
    out = Path(args.output_dir or Path(args.checkpoint).parent / "separability")
    out.mkdir(parents=True, exist_ok=True)
    (out / "separability.json").write_text(results_json.dumps(rep))
    plot_separability(rep, out / "separability.png")
    print(format_report(rep))
    print(f"wrote {out / 'separability.json'} and {out / 'separability.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
