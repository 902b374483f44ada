"""Figures for evaluation reports: success bars and D_R-I traces (like the paper's discrepancy figure)."""

from __future__ import annotations

import math
from pathlib import Path

from ddp.atomic_file import atomic_write
from ddp.percent import percent


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(plt, fig, path: str | Path, **savefig) -> Path:
    """Write ``fig`` atomically (a killed process leaves the earlier file or none, never half a PNG) and close
    it whether or not the write succeeds; ``savefig``: matplotlib's options (dpi, bbox_inches)."""
    path = Path(path)
    fmt = path.suffix.lstrip(".").lower() or "png"
    try:
        atomic_write(path, lambda f: fig.savefig(f, format=fmt, **savefig))
    finally:
        plt.close(fig)
    return path


def plot_success(report: dict, path: Path) -> Path | None:
    """Success rate per protocol; None where no protocol's success was judged (a real robot's)."""
    plt = _pyplot()
    names = [n for n in report["protocols"] if report["protocols"][n]["success_rate"] is not None]
    if not names:
        return None
    from ddp.suite.report import wilson

    results = [report["protocols"][n] for n in names]
    rates = [100 * r["success_rate"] for r in results]
    # the 95 % Wilson interval of each rate over its episodes (one seed: the episodes are the only spread)
    bounds = [wilson(r["successes"], r["episodes"]) for r in results]
    lower = [max(0.0, rate - 100 * lo) for rate, (lo, _) in zip(rates, bounds)]
    upper = [max(0.0, 100 * hi - rate) for rate, (_, hi) in zip(rates, bounds)]
    fig, ax = plt.subplots(figsize=(1.2 + 1.1 * len(names), 3.2))
    bars = ax.bar(names, rates, color="#4c72b0", yerr=[lower, upper], capsize=3, error_kw={"lw": 0.9})
    for bar, r, res, up in zip(bars, rates, results, upper):
        ax.text(bar.get_x() + bar.get_width() / 2, min(r + up + 1, 104), f"{percent(r / 100)} ({res['successes']}/"
                f"{res['episodes']})", ha="center", va="bottom", fontsize=7)
    ax.set_ylim(0, 112)
    ax.set_yticks(range(0, 101, 20))
    ax.set_ylabel("success rate (%)")
    ax.set_title(f"{report['recipe']}: {report['episodes']} episodes per protocol\n(error bars: 95 % Wilson interval)",
                 fontsize=9)
    ax.tick_params(axis="x", labelrotation=30)
    fig.tight_layout()
    return save_figure(plt, fig, path, dpi=120)


def plot_discrepancy(episode: dict, tau: float | None, title: str, path: Path) -> Path:
    """The detector's statistic per control cycle (D_R-I when the detector records none) against tau,
    OOD periods shaded, the first chunk at which the disturbance was visible dotted."""
    plt = _pyplot()
    key = "score" if any(not math.isnan(v) for v in episode.get("score", [])) else "discrepancy"
    d = episode[key]
    mode = episode.get("mode", [0] * len(d))
    xs = list(range(len(d)))
    fig, ax = plt.subplots(figsize=(6, 2.6))
    label = "detector statistic" if key == "score" else "$D_{R-I}$"
    ax.plot(xs, [float("nan") if math.isnan(v) else v for v in d], marker="o", ms=3, lw=1.2, label=label)
    if tau is not None and key == "score":
        ax.axhline(tau, color="crimson", ls="--", lw=1, label=r"$\tau$")
    for x, m in zip(xs, mode):
        if m:
            ax.axvspan(x - 0.5, x + 0.5, color="orange", alpha=0.25, lw=0)
    visible = next((c for c, f in enumerate(episode.get("disturbed") or []) if f), None)
    if visible is not None:
        ax.axvline(visible, color="black", ls=":", lw=1, label="first visible")
    ax.set_xlabel("control cycle (action chunk)")
    ax.set_ylabel(label)
    ax.set_title(title + "\nshaded: OOD mode", fontsize=8)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return save_figure(plt, fig, path, dpi=120)


def plot_report(report: dict, out_dir: Path) -> list[Path]:
    """Write success.png and one discrepancy_<protocol>.png per protocol whose detector recorded a statistic."""
    try:
        _pyplot()
    except ImportError:
        return []
    paths = [p for p in [plot_success(report, out_dir / "success.png")] if p is not None]
    for name, res in report["protocols"].items():
        eps = [e for e in res["per_episode"]
               if any(not math.isnan(v) for v in (*e.get("score", []), *e.get("discrepancy", [])))]
        if eps and "detection" in res:
            disturbed = [e for e in eps if any(e.get("disturbed") or [])]
            shown = disturbed or eps
            ep = shown[0]
            which = f"the first of {len(shown)} {'disturbed ' if disturbed else ''}episodes"
            paths.append(plot_discrepancy(ep, res.get("tau"), f"{report['recipe']} / {name}, seed {ep['seed']} "
                                          f"({which})",
                                          out_dir / f"discrepancy_{name}.png"))
    written = {p.name for p in paths}
    for old in [out_dir / "success.png", *out_dir.glob("discrepancy_*.png")]:
        if old.name not in written:  # an earlier evaluation's figure in a reused folder: not this report's
            old.unlink(missing_ok=True)
    return paths
