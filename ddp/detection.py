"""How well OOD detection works: delays, misses, false alarms and AUROC, in evaluations and in ``ddp detect``.

Every evaluated episode records, per chunk, the controller's ``mode`` (0 ID,
1 OOD), the detector's statistic (``score``; D_R-I by default) and whether
the observation the controller saw was ``disturbed`` (an object displaced, or
the camera blind; read from the env's privileged keys, never shown to the
controller). From these :func:`detection_metrics` counts, per protocol:

* ``first_visible``: the first disturbed chunk of an episode (the first chunk
  at which a detector could see the disturbance);
* detections: the first ID->OOD switch at or after it, its ``delay`` in
  chunks; ``alarm_before_visible`` episodes (no such switch, but OOD already on
  at the first visible chunk: an earlier alarm, which the controller acts on)
  and ``missed`` ones (neither: ID at the first visible chunk and after);
* false alarms: ID->OOD switches before the first visible chunk of a
  disturbed episode, or anywhere in an undisturbed one (per episode and per
  undisturbed chunk);
* AUROC of the statistic at the first visible chunk and the chunks after it,
  against the ID statistic at the same chunk index (the detector's held-out
  calibration episodes), over the chunks whose forecast was made from real
  latents (after an alarm the controller forecasts from its own imagination,
  several steps open loop, which no 1-step ID forecast compares with).

:func:`detect` is the offline comparison behind ``ddp detect``: one set of ID
calibration rollouts, ID test rollouts and disturbed rollouts of the base
policy with the world model forecasting every cycle, on which every score
variant is calibrated to the same false-alarm rate and then scored (its tau set on
the successful held-out ID episodes unless the variant says ``threshold_on: all``;
more ID episodes are rolled out while too few succeeded, as ``ddp eval`` does). Until its
first alarm a sticky detector leaves the base policy's behaviour unchanged, so
the first alarm found here is the one the closed-loop controller raises.
"""

from __future__ import annotations

import math

import numpy as np

from ddp.atomic_file import atomic_write

__all__ = ["auroc", "first_above", "first_visible", "alarmed_before_visible", "detection_metrics", "detect",
           "SCORE_VARIANTS", "format_detect"]


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


def first_above(values, tau: float, start: int = 0) -> int | None:
    """Index of the first value at or after ``start`` above ``tau`` (NaNs never are), or None."""
    for i in range(start, len(values)):
        v = values[i]
        if not math.isnan(v) and v > tau:
            return i
    return None


def first_visible(ep: dict) -> int | None:
    """The first chunk whose observation showed the disturbance (its ``disturbed`` flags), or None."""
    flags = ep.get("disturbed") or []
    return next((c for c, f in enumerate(flags) if f), None)


def alarmed_before_visible(ep: dict) -> bool:
    """A disturbed episode with no ID->OOD switch at or after its first visible chunk whose mode was already
    OOD there: an alarm raised before the disturbance showed was still on (not a miss; a false alarm too).
    ``ep`` is an evaluated episode, or a suite result's trace (``first_visible``, ``mode`` as a 0/1 string)."""
    visible = ep["first_visible"] if "first_visible" in ep else first_visible(ep)
    mode = [float(m) for m in ep.get("mode") or []]
    if visible is None or visible >= len(mode) or mode[visible] < 0.5:
        return False
    return not any(a >= visible for a in _alarms(mode))


def _alarms(mode: list[float]) -> list[int]:
    """Chunks at which the mode switched from ID to OOD."""
    out, prev = [], 0.0
    for c, m in enumerate(mode):
        if m >= 0.5 and prev < 0.5:
            out.append(c)
        prev = m
    return out


def _auroc_after_visible(episodes: list[dict], reference: list[list[float]] | None, key: str,
                         horizon: int) -> list[float] | None:
    if not reference:
        return None
    out = []
    for k in range(horizon):
        by_chunk: dict[int, list[float]] = {}  # chunk index -> the disturbed episodes' statistic there
        for ep in episodes:
            v = first_visible(ep)
            trace = ep.get(key)
            if v is None or trace is None or v + k >= len(trace):
                continue
            imagined = ep.get("imagined")
            if imagined is not None and v + k >= 1 and imagined[v + k - 1]:
                continue  # its forecast came from imagined latents (after an alarm): no 1-step ID forecast's peer
            by_chunk.setdefault(v + k, []).append(trace[v + k])
        # every (disturbed, ID) pair at the same chunk index, each pair once
        pairs = [(auroc(neg, pos), sum(1 for x in pos if x == x) * sum(1 for x in neg if x == x))
                 for c, pos in by_chunk.items() for neg in [[r[c] for r in reference if c < len(r)]]]
        total = sum(n for _, n in pairs)
        out.append(sum(a * n for a, n in pairs if n) / total if total else float("nan"))
    return out


def detection_metrics(episodes: list[dict], reference: list[list[float]] | None = None, *, key: str = "score",
                      horizon: int = 4) -> dict:
    """Detection summary of one protocol's episodes (see the module docstring); per-episode entries too."""
    per_ep, delays = [], []
    disturbed = [ep for ep in episodes if first_visible(ep) is not None]
    clean = [ep for ep in episodes if first_visible(ep) is None]
    for ep in episodes:
        visible = first_visible(ep)
        alarms = _alarms(ep.get("mode") or [])
        if visible is None:
            per_ep.append({"seed": ep["seed"], "first_visible": None, "detected": None, "delay": None,
                           "false_alarms": len(alarms)})
            continue
        early = [a for a in alarms if a < visible]
        hit = next((a for a in alarms if a >= visible), None)
        # an alarm raised before the disturbance and still on when it becomes visible counts as no detection
        per_ep.append({"seed": ep["seed"], "first_visible": visible, "detected": hit,
                       "delay": None if hit is None else hit - visible, "false_alarms": len(early)})
        if hit is not None:
            delays.append(hit - visible)
    id_chunks = sum(len(ep.get("mode") or []) for ep in clean) + sum(
        e["first_visible"] for e in per_ep if e["first_visible"] is not None)
    fa_total = sum(e["false_alarms"] for e in per_ep)
    early = sum(alarmed_before_visible(ep) for ep in disturbed)
    out = {
        "disturbed_episodes": len(disturbed),
        "clean_episodes": len(clean),
        "detected": len(delays),
        "alarm_before_visible": early,
        "missed": len(disturbed) - len(delays) - early,
        "detected_within_1": sum(d <= 1 for d in delays),
        "median_delay": float(np.median(delays)) if delays else None,
        "mean_delay": float(np.mean(delays)) if delays else None,
        "episodes_with_false_alarm": sum(e["false_alarms"] > 0 for e in per_ep),
        "false_alarms_per_id_chunk": fa_total / id_chunks if id_chunks else None,
        "auroc_after_visible": _auroc_after_visible(disturbed, reference, key, horizon),
        "per_episode": per_ep,
    }
    return out


def format_detection(m: dict) -> str:
    """One line: detections, delay, false alarms."""
    parts = []
    if m["disturbed_episodes"]:
        parts.append(f"detected {m['detected']}/{m['disturbed_episodes']} (within 1 chunk {m['detected_within_1']}), "
                     f"median delay {fmt_num(m['median_delay'], '{:.1f}')} chunks")
    n = m["disturbed_episodes"] + m["clean_episodes"]
    parts.append(f"false alarms in {m['episodes_with_false_alarm']}/{n} episodes")
    if m.get("auroc_after_visible"):
        parts.append("AUROC at visibility+k " + "/".join(fmt_num(a, "{:.2f}") for a in m["auroc_after_visible"]))
    return "; ".join(parts)


def fmt_num(v, fmt="{:.3g}") -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else fmt.format(v)


# ----------------------------------------------------------------------------- ddp detect
#: the statistics ``ddp detect`` compares (name -> detector options)
SCORE_VARIANTS: dict[str, dict] = {
    "paper": {},
    "newest_frame": {"frames": "newest"},
    "max_frame": {"frames": "max"},
    "point_dims": {"dims": "point"},
    "point_newest": {"dims": "point", "frames": "newest"},
    "point_newest_per_chunk": {"dims": "point", "frames": "newest", "per_chunk": True},
    # tau set on every held-out ID episode, failing ones too (every other variant: the successful ones)
    "point_newest_per_chunk_tau_all": {"dims": "point", "frames": "newest", "per_chunk": True, "threshold_on": "all"},
    "point_newest_per_chunk_q90": {"dims": "point", "frames": "newest", "per_chunk": True, "chunk_quantile": 0.9},
    "point_newest_per_chunk_w2_q90": {"dims": "point", "frames": "newest", "per_chunk": True, "window": 2,
                                      "chunk_quantile": 0.9},
    # each chunk scaled by its own ID 90 % quantile, no neighbours pooled (an ID peak at the grasp does not
    # raise the scale of the chunk before it; coffee-pull: 9/20 on time where the default flags 0)
    "point_newest_per_chunk_w0_q90": {"dims": "point", "frames": "newest", "per_chunk": True, "window": 0,
                                      "chunk_quantile": 0.9},
    # the same, each phase's scale fitted on the successful fitting episodes only (fit_on: successful)
    "point_newest_per_chunk_w0_q90_fit_ok": {"dims": "point", "frames": "newest", "per_chunk": True, "window": 0,
                                             "chunk_quantile": 0.9, "fit_on": "successful"},
    "whitened": {"whiten": True},
    "per_chunk": {"per_chunk": True},
    "whitened_per_chunk": {"whiten": True, "per_chunk": True},
    "per_chunk_cusum": {"per_chunk": True, "cusum": True},
    "point_per_chunk_cusum": {"dims": "point", "per_chunk": True, "cusum": True},
    # need rollouts with controller.forecast_samples > 1 (ddp detect --samples K)
    "spread": {"spread": True},
    "point_spread": {"dims": "point", "spread": True},
}


def _check_env(exp, env: dict, protocols) -> None:
    """``--env`` overrides checked before any rollout, on top of each disturbance protocol's own overrides
    (``displacement_chunk`` needs the displacement that ``ood_base`` turns on): one line for an unknown key
    (with the closest name) or a value the config refuses."""
    from ddp.eval_runner import env_overrides
    from ddp.protocols.base import get_protocol

    for name in protocols:
        env_overrides(exp, get_protocol(name), exp.recipe.eval.max_steps, extra=env)


def _rollouts(exp, protocol: str, *, episodes: int, seed: int, env: dict, progress: bool, num_envs: int,
              parallel: bool) -> list[dict]:
    from ddp.eval_runner import env_overrides, evaluation_blocks, rollout_episodes
    from ddp.protocols.base import get_protocol

    ctrl = exp.make_controller(detector={"name": "never"}, tracker=False, forecast_every_cycle=True)
    over = env_overrides(exp, get_protocol(protocol), exp.recipe.eval.max_steps, extra=env)
    out = []
    # past one draw of the env's initial states (MetaWorld: 50), the next draw, as ddp eval does: seeds 50
    # apart started from one state, so the ID and disturbed sets held the same layouts twice
    for block, first, n in evaluation_blocks(exp, over, seed, episodes):
        out += rollout_episodes(exp, ctrl, episodes=n, seed=first, overrides=block, desc=f"{protocol} rollouts",
                                progress=progress, num_envs=num_envs, parallel=parallel, record_latents=True)
    return out


def _statistics(episodes: list[dict], spec, cal, point_dims: int) -> list[list[float]]:
    """Each episode's thresholded statistic per chunk, as the online detector computes it."""
    from ddp.detectors.scores import episode_scores, episode_statistic

    return [[float(v) for v in episode_statistic(episode_scores(ep, spec, cal, point_dims), spec, cal)]
            for ep in episodes]


def detect(exp, *, episodes: int = 10, calibration_episodes: int | None = None, alpha: float = 0.05,
           seed: int | None = None, disturbances: tuple[str, ...] = ("ood_base",), env: dict | None = None,
           variants: dict[str, dict] | None = None, progress: bool = True, num_envs: int = 1,
           parallel: bool = False, samples: int | None = None, rollouts: dict | None = None,
           threshold_on: str | None = None) -> dict:
    """Compare detection statistics on ``exp``'s checkpoint (see the module docstring).

    ``disturbances``: protocols whose env disturbs the episodes (``ood_base``: the displacement,
    ``occlusion``: the blind camera), run with the base policy; ``env``: extra env overrides for
    them (e.g. ``displacement_delta``, ``displacement_chunk`` off the paper's table); ``samples``: world-model
    samples per forecast (default the recipe's ``controller.forecast_samples``; the ``spread`` statistics
    need more than one, and every statistic then compares against their mean). ``rollouts``: the
    ``"rollouts"`` of an earlier report (see :func:`save_rollouts` / :func:`load_rollouts`) to score
    new statistics on without rolling out again. ``threshold_on`` (``successful`` / ``all``): which held-out
    ID episodes set every variant's tau (default: each variant's own, ``successful`` unless it says).
    ``exp`` is left as it was (``samples`` applies to this call only).
    """
    before = exp.recipe.controller.forecast_samples
    try:
        return _detect(exp, episodes=episodes, calibration_episodes=calibration_episodes, alpha=alpha, seed=seed,
                       disturbances=disturbances, env=env, variants=variants, progress=progress, num_envs=num_envs,
                       parallel=parallel, samples=samples, rollouts=rollouts, threshold_on=threshold_on)
    finally:
        exp.recipe.controller.forecast_samples = before


def _detect(exp, *, episodes, calibration_episodes, alpha, seed, disturbances, env, variants, progress, num_envs,
            parallel, samples, rollouts, threshold_on) -> dict:
    from ddp.contracts import NeedMoreEpisodes
    from ddp.detectors.discrepancy import DiscrepancyConfig
    from ddp.detectors.scores import fit_calibration
    from ddp.eval_runner import calibration_episodes as calibration_rollouts, more_calibration_episodes

    if not exp.model.has_world_model:
        raise ValueError(f"{exp.recipe.name}: detection needs a world model (world_model.enabled is false)")
    if env:
        _check_env(exp, dict(env), disturbances)
    cfg = exp.recipe.eval
    seed = cfg.seed if seed is None else seed
    n_cal = calibration_episodes or cfg.calibration_episodes
    if samples is not None:
        exp.recipe.controller.forecast_samples = samples
    variants = SCORE_VARIANTS if variants is None else variants
    runs = dict(progress=progress, num_envs=num_envs, parallel=parallel)
    if rollouts is None:
        cal_eps = calibration_rollouts(exp, episodes=n_cal, seed=seed + 100_000, **runs)  # held-out ID states
        test = {"id": _rollouts(exp, "id", episodes=episodes, seed=seed, env={}, **runs)}
        for name in disturbances:
            test[name] = _rollouts(exp, name, episodes=episodes, seed=seed, env=dict(env or {}), **runs)
    else:
        missing = [n for n in ("calibration", "id", *disturbances) if n not in rollouts]
        if missing:
            raise ValueError(f"the saved rollouts hold no {', '.join(missing)} episodes "
                             f"(they have {', '.join(rollouts)})")
        cal_eps, test = rollouts["calibration"], {n: rollouts[n] for n in ("id", *disturbances)}
        n_cal, episodes = len(cal_eps), len(test["id"])
    pd = exp.model.point_dims

    def calibrate(options: dict):
        cfg = DiscrepancyConfig(alpha=alpha, **{**options, **({"threshold_on": threshold_on} if threshold_on else {})})
        return cfg.spec, fit_calibration(cal_eps, cfg.spec, alpha=alpha, point_dims=pd, fit_fraction=cfg.fit_fraction,
                                         threshold_on=cfg.threshold_on, fit_on=cfg.fit_on)

    def calibrate_all() -> dict:  # label -> (spec, calibration), or the ValueError it raised
        out = {}
        for label, options in variants.items():
            try:
                out[label] = calibrate(options)
            except ValueError as err:  # e.g. point dims on an encoder without a point part, too few successful episodes
                out[label] = err
        return out

    fits = calibrate_all()
    cap = max(n_cal, cfg.max_calibration_episodes)
    while rollouts is None and len(cal_eps) < cap:  # as ddp eval does: more ID episodes while a variant lacks them
        more = max((f.more for f in fits.values() if isinstance(f, NeedMoreEpisodes)  # a variant that could
                    and (f.at_least is None or f.at_least <= cap)), default=0)  # never fit under the cap: none
        if not more:
            break
        cal_eps = more_calibration_episodes(exp, cal_eps, more, cap=cap, **runs)
        fits = calibrate_all()
    n_cal = len(cal_eps)
    rows, traces = [], {}
    for label, options in variants.items():
        if isinstance(fits[label], ValueError):
            rows.append({"score": label, "options": options, "error": str(fits[label])})
            continue
        spec, cal = fits[label]
        row = {"score": label, "options": options, "description": spec.label(), "tau": cal.tau,
               "threshold_on": cal.threshold_on, "fit_on": cal.fit_on,
               "fit_episodes": cal.fit_episodes, "threshold_episodes": cal.threshold_episodes}
        stats = {name: _statistics(eps, spec, cal, pd) for name, eps in test.items()}
        traces[label] = {"tau": cal.tau, "reference": cal.reference, **stats}
        id_alarms = [first_above(s, cal.tau) for s in stats["id"]]
        row["id_false_alarm_episodes"] = sum(a is not None for a in id_alarms)
        row["id_episodes"] = len(id_alarms)
        # the episodes alpha bounds where tau is set on the successful ones: those, apart
        nominal = [a for a, ep in zip(id_alarms, test["id"]) if ep.get("success")]
        row["id_false_alarm_successful"], row["id_successful"] = sum(a is not None for a in nominal), len(nominal)
        for name in disturbances:
            eps = [{**ep, "score": s} for ep, s in zip(test[name], stats[name])]
            delays, early, missed = [], 0, 0
            for ep in eps:
                visible = first_visible(ep)
                first = first_above(ep["score"], cal.tau)
                if visible is None:
                    continue
                if first is not None and first < visible:
                    early += 1  # a sticky detector is already OOD: the disturbance is not what it saw
                    continue
                if first is None:
                    missed += 1
                else:
                    delays.append(first - visible)
            au = _auroc_after_visible(eps, stats["id"], "score", 3)
            row[name] = {
                "episodes": sum(first_visible(ep) is not None for ep in eps),
                "detected": len(delays), "detected_within_1": sum(d <= 1 for d in delays),
                "median_delay": float(np.median(delays)) if delays else None, "missed": missed,
                "alarm_before_visible": early, "auroc_after_visible": au,
            }
        rows.append(row)
    return {
        "recipe": exp.recipe.name, "alpha": alpha, "episodes": episodes, "calibration_episodes": n_cal,
        "forecast_samples": exp.recipe.controller.forecast_samples,
        "seed": seed, "disturbances": list(disturbances), "env": dict(env or {}), "rows": rows,
        "traces": traces,
        "success": {name: [None if ep["success"] is None else bool(ep["success"]) for ep in eps]
                    for name, eps in test.items()},  # None: an env that cannot judge (a real robot)
        "first_visible": {name: [first_visible(ep) for ep in eps] for name, eps in test.items() if name != "id"},
        "rollouts": {"calibration": cal_eps, **test},
    }


_EPISODE_ARRAYS = ("latent_real", "latent_pred", "latent_pred_std")


#: the ``.npz`` entry holding what the rollouts were made with (JSON text as bytes: a plain array)
PROVENANCE_KEY = "provenance"


def save_rollouts(rollouts: dict, path, provenance: dict | None = None) -> None:
    """The latent windows, disturbance flags and success of every rollout, as one compressed ``.npz``
    (plain arrays: loading it runs no code); ``provenance`` (plain JSON values: the model's weights digest,
    seed, env overrides, forecast samples) is stored beside them (:func:`rollouts_provenance`)."""
    import json

    arrays = {}
    if provenance is not None:
        arrays[PROVENANCE_KEY] = np.frombuffer(json.dumps(provenance, sort_keys=True).encode(), dtype=np.uint8)
    for name, eps in rollouts.items():
        for i, ep in enumerate(eps):
            for key in _EPISODE_ARRAYS:
                if ep.get(key) is not None:
                    arrays[f"{name}/{i}/{key}"] = np.asarray(ep[key], dtype=np.float32)
            arrays[f"{name}/{i}/disturbed"] = np.asarray(ep.get("disturbed") or [], dtype=bool)
            judged = -1 if ep["success"] is None else int(ep["success"])  # -1: not judged (a real robot)
            arrays[f"{name}/{i}/meta"] = np.asarray([ep["seed"], judged], dtype=np.int64)
    # atomic: a kill mid-write left a truncated file that the next --rollouts refused (the rollouts lost)
    atomic_write(path, lambda f: np.savez_compressed(f, **arrays))


def load_rollouts(path) -> dict:
    """What :func:`save_rollouts` wrote, as ``{condition: [episode dict, ...]}``."""
    return read_rollouts(path)[0]


def read_rollouts(path) -> tuple[dict, dict | None]:
    """The rollouts and their provenance (:func:`load_rollouts`, :func:`rollouts_provenance`), the file opened
    once."""
    out: dict[str, dict[int, dict]] = {}
    with np.load(path, allow_pickle=False) as data:
        made_with = _provenance(data)
        for key in data.files:
            if key == PROVENANCE_KEY:
                continue
            name, i, field = key.rsplit("/", 2)
            ep = out.setdefault(name, {}).setdefault(int(i), {})
            value = data[key]
            if field == "meta":
                ep["seed"], ep["success"] = int(value[0]), (None if int(value[1]) < 0 else bool(value[1]))
            elif field == "disturbed":
                ep["disturbed"] = value.tolist()
            else:
                ep[field] = value.astype(np.float64)
    return {name: [eps[i] for i in sorted(eps)] for name, eps in out.items()}, made_with


def rollouts_provenance(path) -> dict | None:
    """What :func:`save_rollouts` stored about how the rollouts were made; None for a file written without
    (before 2026-12-05)."""
    with np.load(path, allow_pickle=False) as data:
        return _provenance(data)


def _provenance(data) -> dict | None:
    """The provenance entry of an opened rollouts ``.npz`` (JSON text stored as bytes), or None."""
    import json

    return json.loads(data[PROVENANCE_KEY].tobytes().decode()) if PROVENANCE_KEY in data.files else None


def format_detect(rep: dict) -> str:
    """The comparison as a markdown table (one row per score and disturbance)."""
    lines = [
        f"{rep['recipe']}: alpha {rep['alpha']:g} per ID episode (per successful one where tau is set on the "
        f"successful held-out episodes), {rep['calibration_episodes']} ID calibration "
        f"episodes (split: fit / threshold), {rep['episodes']} test episodes per condition, seed {rep['seed']}, "
        f"{rep.get('forecast_samples', 1)} world-model sample(s) per forecast"
        + (f", env overrides {rep['env']}" if rep["env"] else ""),
        "",
        "| score | disturbance | AUROC at visible / +1 / +2 | detected (<= 1 chunk) | median delay | missed | "
        "alarm before visible | ID false alarms | tau |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rep["rows"]:
        if "error" in row:
            lines.append(f"| {row['score']} | - | {row['error']} | | | | | | |")
            continue
        for name in rep["disturbances"]:
            r = row[name]
            au = "/".join(fmt_num(a, "{:.2f}") for a in (r["auroc_after_visible"] or []))
            id_fa = f"{row['id_false_alarm_episodes']}/{row['id_episodes']}"
            if row.get("threshold_on") == "successful" and "id_successful" in row:
                id_fa += f" ({row['id_false_alarm_successful']}/{row['id_successful']} successful)"
            lines.append(
                f"| {row['score']} | {name} | {au} | {r['detected']}/{r['episodes']} ({r['detected_within_1']}) | "
                f"{fmt_num(r['median_delay'], '{:.1f}')} | {r['missed']} | {r['alarm_before_visible']} | "
                f"{id_fa} | {fmt_num(row['tau'])} |"
            )
    return "\n".join(lines) + "\n"


def plot_detect(rep: dict, score: str, path) -> None:
    """The statistic of one score: the ID test band (min-max), disturbed episodes as lines, tau dashed."""
    from matplotlib.ticker import MaxNLocator

    from ddp.plots import _pyplot, save_figure

    plt = _pyplot()
    tr = rep["traces"][score]
    fig, axes = plt.subplots(1, len(rep["disturbances"]), figsize=(6.5 * len(rep["disturbances"]), 3.5),
                             squeeze=False)
    for ax, name in zip(axes[0], rep["disturbances"]):
        ids = tr["id"]
        chunks = max(len(t) for t in ids)
        cols = [np.asarray([t[c] for t in ids if c < len(t)], dtype=np.float64) for c in range(chunks)]
        cols = [c[np.isfinite(c)] for c in cols]
        lo = [c.min() if c.size else np.nan for c in cols]
        hi = [c.max() if c.size else np.nan for c in cols]
        ax.fill_between(range(chunks), lo, hi, color="tab:green", alpha=0.25, label="ID test (min-max)")
        for i, (t, v) in enumerate(zip(tr[name], rep["first_visible"][name])):
            ax.plot(range(len(t)), t, color="tab:red", lw=0.8, alpha=0.7, label=name if i == 0 else None)
            if v is not None:
                ax.axvline(v, color="tab:red", lw=0.5, ls=":", alpha=0.5)
        ax.axhline(tr["tau"], color="black", ls="--", lw=1, label=f"tau (alpha {rep['alpha']:g})")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_xlabel("chunk (dotted: first visible)")
        ax.set_ylabel(f"statistic: {score}")
        positive = [v for t in [*ids, *tr[name]] for v in t if v == v and v > 0]
        if positive and all(v > 0 for t in [*ids, *tr[name]] for v in t if v == v):
            ax.set_yscale("log")
        elif positive:  # a CUSUM statistic is 0 until evidence accumulates
            ax.set_yscale("symlog", linthresh=min(positive))
            ax.set_ylim(bottom=0)
        ax.set_title(f"{rep['recipe']}: {score} under {name}")
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(plt, fig, path, dpi=120)


def summary_json(rep: dict) -> dict:
    """``rep`` without the per-chunk traces and rollouts (what is worth committing)."""
    return {k: v for k, v in rep.items() if k not in ("traces", "rollouts")}


