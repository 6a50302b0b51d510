"""The accuracy study's report: summary by method, equal-accuracy ratios with bootstrap intervals, markdown tables,
and the files a study writes (``write_report``: accuracy.csv, accuracy.json, accuracy_ratio.json, accuracy.md,
accuracy.png). The trials are planner.accuracy's."""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from core.jsonsafe import csv_row, nulled
from planner.accuracy import BOOT, DENSE, PEAK_ONLY, STRATEGIES, errors_by_seed


def _stat(v, fn):
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    return float(fn(v)) if len(v) else float("nan")


def summarize(rows, sensor, methods=None, where=lambda r: True):
    out = {}
    methods = methods or ([f"adaptive-{s}" for s in STRATEGIES] + [f"dense-{n}" for n in DENSE]
                          + [f"peak-{n}" for n in PEAK_ONLY])
    for method in methods:
        R = [r for r in rows if r["method"] == method and r["sensor"] == sensor and where(r)]
        st = [r for r in R if "x_m" in r]            # a stone scene (its truth is in the row)
        he = [r for r in R if "x_m" not in r]
        det = [r for r in st if r["detected"]]

        def e(k, q=None):
            v = np.abs([r.get(k, np.nan) for r in det]) * 1e3
            return _stat(v, np.median if q is None else (lambda a: np.percentile(a, q)))
        out[method] = {
            "n_stone": len(st), "n_healthy": len(he),
            "detection_rate": np.mean([r["detected"] for r in st]) if st else np.nan,
            "false_alarm_rate": np.mean([r["detected"] for r in he]) if he else np.nan,
            "median_err_x_mm": e("err_x_m"), "p90_err_x_mm": e("err_x_m", 90),
            "median_err_depth_mm": e("err_depth_m"), "p90_err_depth_mm": e("err_depth_m", 90),
            "median_err_diam_mm": e("err_diam_m"), "median_err_peak_mm": e("err_peak_m"),
            "median_err_peakfit_mm": e("err_peakfit_m"),
            "median_probes": float(np.median([r["n_probes"] for r in st])) if st else np.nan,
            "mean_probes": float(np.mean([r["n_probes"] for r in st])) if st else np.nan,
            "pred_detect_rate": _stat([r.get("p_detect_pred", np.nan) for r in st], np.mean),
        }
    return out


def _crossing(ns, err, target) -> float:
    """The smallest raster size whose median error reaches ``target``: log-log interpolation between the two
    observed sizes around the first crossing; inf if no observed size reaches it."""
    for i, e in enumerate(err):
        if e <= target:
            if i == 0:
                return float(ns[0])
            t = (math.log(target) - math.log(err[i - 1])) / (math.log(e) - math.log(err[i - 1]))
            return float(math.exp(math.log(ns[i - 1]) + t * (math.log(ns[i]) - math.log(ns[i - 1]))))
    return math.inf


def equal_accuracy(rows, sensor, method, n_boot: int = BOOT) -> dict:
    """How many probes an even raster needs for the adaptive method's median errors, and the ratio to the adaptive
    run's mean probe count; 90 % intervals by resampling the stones (bootstrap).

    * ``fit``: the even raster localized with the same fem fit, equal median lateral AND depth error. Its median
      errors over the raster sizes DENSE are fitted with a power law (error ~ N^b, in log-log least squares), which
      is solved for the size that reaches the adaptive run's medians.
    * ``peak``: the even raster localized by its maximum (``peak_fit``, model-free; gives no depth), equal median
      lateral error, from the observed sizes DENSE + PEAK_ONLY (inf: none of them reaches it)."""
    n_ad = {r["seed"]: r["n_probes"] for r in rows if r["method"] == method and r["sensor"] == sensor and "x_m" in r}
    ad = [errors_by_seed(rows, sensor, method, k) for k in ("err_x_m", "err_depth_m")]
    fit = {N: [errors_by_seed(rows, sensor, f"dense-{N}", k) for k in ("err_x_m", "err_depth_m")] for N in DENSE}
    pk_n = DENSE + PEAK_ONLY
    pk = {N: errors_by_seed(rows, sensor, f"dense-{N}" if N in DENSE else f"peak-{N}", "err_peakfit_m") for N in pk_n}
    # paired: the stones every method detected (all of them when detection is 100 %)
    seeds = sorted(set(n_ad).intersection(*ad, *[d for N in DENSE for d in fit[N]], *pk.values()))

    def one(sample):
        def med(d):
            v = [d[s] for s in sample if s in d]
            return float(np.median(v)) if v else float("nan")
        n = float(np.mean([n_ad[s] for s in sample]))      # the adaptive run's probes, spent on these stones
        need, slopes = [], []
        for j in (0, 1):
            b, c = np.polyfit(np.log(DENSE), np.log([med(fit[N][j]) for N in DENSE]), 1)
            slopes.append(float(b))
            need.append(float(np.exp((math.log(med(ad[j])) - c) / b)) if b < 0 else math.inf)
        n_fit = max(need)
        n_pk = _crossing(pk_n, [med(pk[N]) for N in pk_n], med(ad[0]))
        return {"adaptive_probes": n, "adaptive_err_x_mm": med(ad[0]) * 1e3, "adaptive_err_depth_mm": med(ad[1]) * 1e3,
                "fit_probes": n_fit, "fit_ratio": n_fit / n, "fit_slope_x": slopes[0], "fit_slope_depth": slopes[1],
                "fit_limited_by": "lateral" if need[0] >= need[1] else "depth",
                "peak_probes": n_pk, "peak_ratio": n_pk / n}
    out = one(seeds)
    out["n_stones_paired"] = len(seeds)
    rng = np.random.default_rng(0)
    boots = [one(list(rng.choice(seeds, len(seeds)))) for _ in range(n_boot)]
    for k in ("fit_ratio", "peak_ratio"):
        v = np.array([b[k] for b in boots])
        out[k + "_90"] = [float(np.quantile(v, q, method="nearest")) for q in (0.05, 0.95)]
        out[k + "_inf_fraction"] = float(np.mean(~np.isfinite(v)))
    return out


def equal_accuracy_lines(eq: dict, strategy: str) -> list:
    def r(k):
        lo, hi = eq[k + "_90"]
        return (f"{eq[k]:.1f}x (90 % bootstrap interval {lo:.1f}-{hi:.1f}x)" if math.isfinite(eq[k]) else
                f"not reached by any raster up to {PEAK_ONLY[-1]} probes: > {PEAK_ONLY[-1] / eq['adaptive_probes']:.1f}x")
    return [f"adaptive-{strategy}: {eq['adaptive_probes']:.1f} probes (mean), median error "
            f"{eq['adaptive_err_x_mm']:.2f} mm lateral / {eq['adaptive_err_depth_mm']:.2f} mm depth.",
            f"- even raster, same fem fit, equal lateral and depth error: {eq['fit_probes']:.0f} probes -> ratio "
            f"{r('fit_ratio')}; set by the {eq['fit_limited_by']} error (raster error ~ N^{eq['fit_slope_x']:.2f} "
            f"lateral, N^{eq['fit_slope_depth']:.2f} depth)" + (" (beyond the largest raster: extrapolated)"
                                                                  if eq["fit_probes"] > DENSE[-1] else ""),
            "- even raster localized by its maximum (model-free peak fit, no depth), equal lateral error: "
            + (f"{eq['peak_probes']:.0f} probes -> ratio " if math.isfinite(eq["peak_probes"]) else "")
            + r("peak_ratio"), ""]


def read_rows(path):
    rows = []
    with open(path) as f:
        for r in csv.DictReader(f):
            d = {}
            for k, v in r.items():
                if v == "":
                    continue
                try:
                    d[k] = float(v)
                except ValueError:
                    d[k] = v
            for k in ("seed", "n_probes", "detected"):
                if k in d:
                    d[k] = int(d[k])
            rows.append(d)
    return rows


def write_report(out: Path, rows: list[dict], sensor: str, budget: int, target_m: float, elapsed_s: float,
                 where: str = "", write_csv: bool = True, figure: bool = True) -> list[str]:
    """accuracy.csv (one row per trial and method), accuracy.json (summary by method), accuracy_ratio.json,
    accuracy.md (the tables; returned as lines) and accuracy.png in ``out``."""
    trials = len({r["seed"] for r in rows if "err_x_m" in r})
    healthy = len({r["seed"] for r in rows}) - trials
    where = f"; {where}" if where else ""
    out.mkdir(parents=True, exist_ok=True)
    if write_csv:
        keys = sorted({k for r in rows for k in r})
        with open(out / "accuracy.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=keys)
            w.writeheader()
            w.writerows([csv_row(r) for r in rows])
    summ = summarize(rows, sensor)
    (out / "accuracy.json").write_text(json.dumps(nulled(summ), indent=1, allow_nan=False))
    lines = [f"Accuracy study: {trials} random stones + {healthy} healthy scenes, sensor {sensor}, "
             f"budget {budget} probes, target 1-sigma {target_m * 1e3:g} mm ({elapsed_s:.0f} s{where})",
             "", "| method | probes (mean) | detection rate (predicted) | false alarms | lateral err median / p90 "
             "(mm) | depth err median / p90 (mm) | diameter err median (mm) | 3-point peak lateral err (mm) | "
             "peak-fit lateral err (mm) |", "|---|---|---|---|---|---|---|---|---|"]

    def f2(v):
        return "-" if not np.isfinite(v) else f"{v:.2f}"
    for m, s in summ.items():
        lines.append(f"| {m} | {s['mean_probes']:.1f} | {f2(s['detection_rate'])} ({f2(s['pred_detect_rate'])}) "
                     f"| {f2(s['false_alarm_rate'])} | {f2(s['median_err_x_mm'])} / {f2(s['p90_err_x_mm'])} | "
                     f"{f2(s['median_err_depth_mm'])} / {f2(s['p90_err_depth_mm'])} | {f2(s['median_err_diam_mm'])} | "
                     f"{f2(s['median_err_peak_mm'])} | {f2(s['median_err_peakfit_mm'])} |")
    lines.append("")
    ratios = {}
    for strategy in STRATEGIES:
        eq = equal_accuracy(rows, sensor, f"adaptive-{strategy}")
        ratios[strategy] = eq
        ad = summ[f"adaptive-{strategy}"]
        direct = [n for n in DENSE if summ[f"dense-{n}"]["median_err_x_mm"] <= ad["median_err_x_mm"]
                  and summ[f"dense-{n}"]["median_err_depth_mm"] <= ad["median_err_depth_mm"]]
        eq["direct_probes"] = direct[0] if direct else None
        lines += equal_accuracy_lines(eq, strategy)
        lines[-1:-1] = ["- read directly: the smallest even raster (same fit) no worse in both medians: "
                        + (f"{direct[0]} probes -> ratio {direct[0] / ad['mean_probes']:.1f}x" if direct else "none")]
    targets = [n for n in DENSE if summ[f"dense-{n}"]["median_err_x_mm"] < 0.5
               and summ[f"dense-{n}"]["median_err_depth_mm"] < 1.0]
    lines += ["Smallest even raster (same fit) meeting the targets (median lateral < 0.5 mm, depth < 1 mm): "
              + (f"{targets[0]} probes" if targets else "none"), ""]
    (out / "accuracy_ratio.json").write_text(json.dumps(nulled(ratios), indent=1, allow_nan=False))
    # accuracy against probes: the adaptive estimate after each round, and dense rasters
    lines += ["", "Median error against probes used (detected stones with centre <= 30 mm deep; all rounds of the "
              "adaptive runs):", "", "| probes | adaptive-design x / depth (mm) | adaptive-raster x / depth (mm) | "
              "dense raster x / depth (mm) |", "|---|---|---|---|"]
    shallow = lambda r: "depth_m" in r and r["depth_m"] <= 0.030  # noqa: E731
    for n in sorted(set((15, 25, 35, 45) + DENSE)):
        cells = []
        for m in ("round-design", "round-raster", "dense"):
            key = f"dense-{n}" if m == "dense" else f"{m}@{n}"
            sm = summarize(rows, sensor, [key], shallow)[key]
            cells.append("-" if not sm["n_stone"] else
                         f"{sm['median_err_x_mm']:.2f} / {sm['median_err_depth_mm']:.2f} (n={sm['n_stone']})")
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    lines += ["", "By depth of the stone's centre (adaptive-design):", "",
              "| depth (mm) | stones | detected (predicted) | lateral err median (mm) | depth err median (mm) | "
              "reported sigma_depth median (mm) |", "|---|---|---|---|---|---|"]
    for lo, hi in ((0, 15), (15, 25), (25, 35), (35, 50)):
        band = lambda r, lo=lo, hi=hi: "depth_m" in r and lo * 1e-3 < r["depth_m"] <= hi * 1e-3  # noqa: E731
        sm = summarize(rows, sensor, ["adaptive-design"], band)["adaptive-design"]
        sdv = [r["sigma_depth_m"] for r in rows if r["method"] == "adaptive-design" and band(r) and r["detected"]]
        if sm["n_stone"]:
            lines.append(f"| {lo}-{hi} | {sm['n_stone']} | {sm['detection_rate']:.2f} ({sm['pred_detect_rate']:.2f})"
                         f" | {sm['median_err_x_mm']:.2f} | {sm['median_err_depth_mm']:.2f} | "
                         f"{np.median(sdv) * 1e3 if sdv else float('nan'):.2f} |")
    cov = [r for r in rows if r["method"] == "adaptive-design" and "depth_lo95_m" in r and "err_x_m" in r]
    if cov:
        inside = lambda r, k: r[f"depth_lo{k}_m"] <= r["depth_m"] <= r[f"depth_hi{k}_m"]  # noqa: E731
        jac = np.mean([abs(r["err_depth_m"]) <= r["sigma_depth_m"] for r in cov])
        lines += ["", f"Depth uncertainty, adaptive-design ({len(cov)} detected stones): the truth lies in the 68 % / "
                  f"95 % profile-likelihood interval in {np.mean([inside(r, 68) for r in cov]):.0%} / "
                  f"{np.mean([inside(r, 95) for r in cov]):.0%} of runs; within the Jacobian's 1 sigma in {jac:.0%}."]
    (out / "accuracy.md").write_text("\n".join(lines) + "\n")
    if figure:
        from planner.plots_accuracy import figure as draw
        draw(rows, out / "accuracy.png", sensor)
    return lines
