"""Can D_R-I tell a displaced episode from an ID one? Per-chunk separability of a trained checkpoint.

The discrepancy detector works when the real latents of a displaced scene
drift from the world model's forecast by more than the forecast error of ID
episodes. :func:`separability` measures both on the same seeds: the base
policy runs with the world model forecasting every cycle (no detector acts,
nothing is tracked) on ``episodes`` held-out ID layouts, then on the same
layouts with the env's displacements (the ``ood_base`` protocol). Per chunk
it reports the ID and displaced D_R-I and the AUROC of displaced against ID
(1.0: a threshold at that chunk separates them all; 0.5: chance), and per
displaced episode the first chunk whose D_R-I exceeds ``tau`` (the recipe's,
or calibrated as ``ddp eval`` does on separate ID seeds). A calibrated report
also gives the detection and false-alarm chunks under per-chunk thresholds
(``controller.detector.per_chunk: true``) from the same calibration rollouts.

``python scripts/discrepancy_report.py --checkpoint runs/<name>/last.pt``
prints the table and draws the ID band against the displaced episodes.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["auroc", "first_above", "separability"]


def auroc(negatives, positives) -> float:
    """P(positive > negative) + P(tie) / 2 over all pairs (NaNs dropped); NaN if either side is empty."""
    x = np.asarray(negatives, dtype=np.float64)
    y = np.asarray(positives, dtype=np.float64)
    x, y = x[~np.isnan(x)], y[~np.isnan(y)]
    if x.size == 0 or y.size == 0:
        return float("nan")
    greater = (y[:, None] > x[None, :]).mean()
    ties = (y[:, None] == x[None, :]).mean()
    return float(greater + 0.5 * ties)


def first_above(values, tau) -> int | None:
    """Index of the first value above ``tau`` (a number, or one threshold per index, the last repeated;
    NaNs are never above), or None."""
    taus = list(tau) if isinstance(tau, (list, tuple)) else None
    for i, v in enumerate(values):
        t = tau if taus is None else taus[min(i, len(taus) - 1)]
        if not math.isnan(v) and v > t:
            return i
    return None


def _per_chunk(results: list[dict]) -> list[list[float]]:
    """D_R-I per chunk across episodes: ``out[c]`` holds chunk c of every episode that reached it."""
    chunks = max((len(r.get("discrepancy", [])) for r in results), default=0)
    return [[r["discrepancy"][c] for r in results if c < len(r.get("discrepancy", []))] for c in range(chunks)]


def separability(exp, *, episodes: int = 10, seed: int | None = None, tau: float | None = None,
                 progress: bool = True) -> dict:
    """ID against displaced D_R-I of ``exp``'s model, per chunk (see the module docstring).

    ``tau``: the threshold for the detection chunks; None takes the recipe's discrepancy tau or,
    when that is null too, calibrates one from ``eval.calibration_episodes`` ID episodes on seeds
    ``seed + 100000 ...`` (as ``ddp eval`` does).
    """
    from ddp.eval_runner import calibration_values, env_overrides, rollout_episodes
    from ddp.protocols.base import get_protocol

    if not exp.model.has_world_model:
        raise ValueError(f"{exp.recipe.name}: D_R-I needs a world model (world_model.enabled is false)")
    cfg = exp.recipe.eval
    seed = cfg.seed if seed is None else seed
    runs = {}
    for name in ("id", "ood_base"):
        ctrl = exp.make_controller(detector={"name": "never"}, tracker=False, forecast_every_cycle=True)
        runs[name] = rollout_episodes(exp, ctrl, episodes=episodes, seed=seed,
                                      overrides=env_overrides(exp, get_protocol(name), cfg.max_steps),
                                      desc=f"D_R-I {name}", progress=progress)
    calibrated, per_chunk = False, None
    if tau is None:
        section = exp.recipe.controller.detector
        tau = section.get("tau") if section.get("name") == "discrepancy" else None
    if tau is None:  # calibrated as ddp eval does; per-chunk thresholds from the same rollouts
        values, chunks = calibration_values(exp, episodes=cfg.calibration_episodes, seed=seed + 100_000,
                                            progress=progress)
        single = exp.make_controller(detector={"name": "discrepancy", "tau": None}, tracker=False).detector
        tau = single.calibrate(values, chunks=chunks)
        detector = exp.make_controller(detector={"name": "discrepancy", "tau": None, "per_chunk": True},
                                       tracker=False).detector
        detector.calibrate(values, chunks=chunks)
        per_chunk = [*detector.tau_per_chunk, detector.tau]  # past the table: the global tau
        calibrated = True
    id_chunks, ood_chunks = _per_chunk(runs["id"]), _per_chunk(runs["ood_base"])
    rows = []
    for c in range(max(len(id_chunks), len(ood_chunks))):
        ids = np.asarray(id_chunks[c] if c < len(id_chunks) else [], dtype=np.float64)
        ood = np.asarray(ood_chunks[c] if c < len(ood_chunks) else [], dtype=np.float64)
        ids, ood = ids[~np.isnan(ids)], ood[~np.isnan(ood)]
        if ids.size == 0 and ood.size == 0:
            continue  # the first chunk: nothing forecast yet
        rows.append({
            "chunk": c,
            "id_median": float(np.median(ids)) if ids.size else None,
            "id_max": float(ids.max()) if ids.size else None,
            "ood_median": float(np.median(ood)) if ood.size else None,
            "ood_min": float(ood.min()) if ood.size else None,
            "auroc": auroc(ids, ood),
        })
    detections = [first_above(r["discrepancy"], tau) for r in runs["ood_base"]]
    false_alarms = [first_above(r["discrepancy"], tau) for r in runs["id"]]
    if per_chunk is not None:
        detections_pc = [first_above(r["discrepancy"], per_chunk) for r in runs["ood_base"]]
        false_alarms_pc = [first_above(r["discrepancy"], per_chunk) for r in runs["id"]]
    return {
        "recipe": exp.recipe.name,
        "episodes": episodes,
        "seed": seed,
        "tau": float(tau),
        "tau_calibrated": calibrated,
        "chunks": rows,
        "detection_chunk": detections,
        "false_alarm_chunk": false_alarms,
        "tau_per_chunk": per_chunk,
        "detection_chunk_per_chunk": detections_pc if per_chunk is not None else None,
        "false_alarm_chunk_per_chunk": false_alarms_pc if per_chunk is not None else None,
        "success": {name: [bool(r["success"]) for r in res] for name, res in runs.items()},
        "discrepancy": {name: [r["discrepancy"] for r in res] for name, res in runs.items()},
    }


def format_report(rep: dict) -> str:
    """The per-chunk table and the detection summary as plain text."""
    def num(v, fmt="{:.4g}"):
        return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else fmt.format(v)

    lines = [
        f"{rep['recipe']}: {rep['episodes']} ID and {rep['episodes']} displaced episodes from seed {rep['seed']}; "
        f"tau {rep['tau']:.4g} ({'calibrated' if rep['tau_calibrated'] else 'recipe'})",
        "chunk  ID median  ID max  displaced median  displaced min  AUROC",
    ]
    for r in rep["chunks"]:
        lines.append(f"{r['chunk']:>5}  {num(r['id_median']):>9}  {num(r['id_max']):>6}  {num(r['ood_median']):>16}  "
                     f"{num(r['ood_min']):>13}  {num(r['auroc'], '{:.2f}'):>5}")
    det = [d for d in rep["detection_chunk"] if d is not None]
    fa = [d for d in rep["false_alarm_chunk"] if d is not None]
    lines.append(f"displaced episodes above tau: {len(det)}/{len(rep['detection_chunk'])}, first at chunks "
                 f"{rep['detection_chunk']}")
    lines.append(f"ID episodes above tau (false alarms): {len(fa)}/{len(rep['false_alarm_chunk'])}")
    if rep.get("tau_per_chunk") is not None:
        det = [d for d in rep["detection_chunk_per_chunk"] if d is not None]
        fa = [d for d in rep["false_alarm_chunk_per_chunk"] if d is not None]
        lines.append(f"per-chunk thresholds (controller.detector.per_chunk: true): displaced above {len(det)}/"
                     f"{len(rep['detection_chunk_per_chunk'])}, first at chunks {rep['detection_chunk_per_chunk']}; "
                     f"false alarms {len(fa)}/{len(rep['false_alarm_chunk_per_chunk'])}")
    return "\n".join(lines)


def plot_separability(rep: dict, path) -> None:
    """ID D_R-I as a min-max band with its median, displaced episodes as lines, tau dashed."""
    from ddp.plots import _pyplot

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.5))
    id_chunks = _per_chunk([{"discrepancy": d} for d in rep["discrepancy"]["id"]])
    xs, lo, hi, med = [], [], [], []
    for c, vals in enumerate(id_chunks):
        v = np.asarray(vals, dtype=np.float64)
        v = v[~np.isnan(v)]
        if v.size:
            xs.append(c), lo.append(v.min()), hi.append(v.max()), med.append(np.median(v))
    ax.fill_between(xs, lo, hi, color="tab:green", alpha=0.25, label="ID (min-max)")
    ax.plot(xs, med, color="tab:green", lw=1.5, label="ID median")
    for i, d in enumerate(rep["discrepancy"]["ood_base"]):
        ax.plot(range(len(d)), d, color="tab:red", lw=0.8, alpha=0.7, label="displaced" if i == 0 else None)
    ax.axhline(rep["tau"], color="black", ls="--", lw=1, label="tau")
    if rep.get("tau_per_chunk"):
        taus = rep["tau_per_chunk"]
        ax.step(range(len(taus)), taus, where="mid", color="tab:purple", ls=":", lw=1.2, label="tau per chunk")
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("chunk")
    ax.set_ylabel("D_R-I")
    ax.set_yscale("log")
    ax.set_title(f"{rep['recipe']}: D_R-I, ID against displaced")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
