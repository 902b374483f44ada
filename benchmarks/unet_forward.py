"""Parameter count and per-forward latency of the 1D U-Nets at the paper's sizes.

One forward = one denoising pass at batch 1 (a DDIM-10 chunk costs 10 of them):
policy pi_theta on an action chunk (H=16, action dim 4, global condition
M x 128 = 256); world model W_phi on the future latents (N=8, latent 128,
history 2 x 128 = 256 repeated over the steps, executed actions 8 x 4 = 32
as the global condition).

    python benchmarks/unet_forward.py --threads 2

On a machine shared with other busy processes, set OMP_WAIT_POLICY=PASSIVE
(or use --threads 1): spinning OpenMP threads otherwise inflate the median
by up to 10x.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import torch

from ddp.config import from_dict
from ddp.registry import get

# (label, plugin, down_dims, context, horizon)
SIZES = [
    ("policy (DDP sim)", "unet1d", [256, 512, 1024], {"input_dim": 4, "global_cond_dim": 256}, 16),
    ("policy (Simple DDP)", "unet1d", [128, 256, 384], {"input_dim": 4, "global_cond_dim": 256}, 16),
    (
        "world model (DDP sim)",
        "unet1d_wm",
        [256, 512, 1024],
        {"input_dim": 128, "global_cond_dim": 32, "local_cond_dim": 256},
        8,
    ),
    (
        "world model (Simple DDP)",
        "unet1d_wm",
        [128, 256, 512],
        {"input_dim": 128, "global_cond_dim": 32, "local_cond_dim": 256},
        8,
    ),
    ("policy (DP3)", "unet1d", [512, 1024, 2048], {"input_dim": 4, "global_cond_dim": 256}, 16),
]


def time_forward(net, inputs: dict, *, warmup: int, repeats: int, device: torch.device) -> list[float]:
    """Seconds per ``predict`` call, after ``warmup`` untimed calls."""

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    times = []
    with torch.inference_mode():
        for _ in range(warmup):
            net.predict(**inputs)
        sync()
        for _ in range(repeats):
            start = time.perf_counter()
            net.predict(**inputs)
            sync()
            times.append(time.perf_counter() - start)
    return times


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=2, help="torch.set_num_threads (default: 2)")
    parser.add_argument("--warmup", type=int, default=5, help="untimed forwards before timing (default: 5)")
    parser.add_argument("--repeats", type=int, default=30, help="timed forwards per size (default: 30)")
    parser.add_argument("--no-dp3", action="store_true", help="skip DP3's [512,1024,2048] U-Net (~255 M params)")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    args = parser.parse_args(argv)

    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    cpu = platform.processor() or platform.machine()
    print(
        f"torch {torch.__version__}, {args.threads} threads, device {device} ({cpu}), batch 1, "
        f"median of {args.repeats} forwards after {args.warmup} warm-up, torch.inference_mode"
    )
    header = f"{'model':<26} {'down_dims':<18} {'T':>3} {'params':>13} {'median ms':>10} {'min ms':>8}"
    print(header)
    print("-" * len(header))
    for label, name, down_dims, context, horizon in SIZES:
        if args.no_dp3 and down_dims == [512, 1024, 2048]:
            continue
        plugin = get("denoiser", name)
        torch.manual_seed(0)
        net = plugin.factory(from_dict(plugin.config_cls, {"down_dims": down_dims}), **context).to(device).eval()
        n_params = sum(p.numel() for p in net.parameters())
        inputs = {
            "sample": torch.randn(1, horizon, context["input_dim"], device=device),
            "timestep": torch.tensor([10], device=device),
            "global_cond": torch.randn(1, context["global_cond_dim"], device=device),
        }
        if "local_cond_dim" in context:
            inputs["local_cond"] = torch.randn(1, context["local_cond_dim"], device=device)
        times = time_forward(net, inputs, warmup=args.warmup, repeats=args.repeats, device=device)
        print(
            f"{label:<26} {str(down_dims):<18} {horizon:>3} {n_params:>13,} "
            f"{1e3 * statistics.median(times):>10.2f} {1e3 * min(times):>8.2f}"
        )
        del net


if __name__ == "__main__":
    main()
