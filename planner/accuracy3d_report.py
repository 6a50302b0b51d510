"""The 3D accuracy study's report: accuracy3d.csv (one row per trial and method), accuracy3d.json (the summary),
accuracy3d.md (the tables) and accuracy3d.png (errors against the stone's depth, and against probes used).

Per method over the stones: the fraction detected, the median lateral (in-plane) and depth errors of the detected,
their 68 % / 95 % interval coverage (x, y and depth), the median probes (over the stones; the healthy blocks'
apart); detection inside the detectability envelope (stones the
coarse grid's analysis gives p_detect >= 0.9: planner.detect3d) against the 95 % target; false alarms over the
healthy blocks. The probes an even grid needs for the adaptive run's medians: the smallest grid whose median lateral
and depth errors are both at most the adaptive run's, as a ratio to the adaptive run's median probes; and the
Cramer-Rao comparison of the best placement against an even grid (planner.accuracy3d.oracle_gain).
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from core.jsonsafe import csv_row, nulled

from .accuracy3d import FAILED

P_ENVELOPE = 0.9
TARGETS = {"lateral_m": 1e-3, "depth_m": 1.5e-3, "detect_in_envelope": 0.95, "false_alarm": 0.05}


def _median(v) -> float:
    v = [a for a in v if a is not None and math.isfinite(a)]
    return float(np.median(v)) if v else float("nan")


def _coverage(rows, err, sig, k) -> float:
    ok = [r for r in rows if math.isfinite(r.get(err, math.nan)) and math.isfinite(r.get(sig, math.nan))]
    return float(np.mean([abs(r[err]) <= k * r[sig] for r in ok])) if ok else float("nan")


def summarise(rows: list[dict]) -> dict:
    failed = [r for r in rows if r["method"] == FAILED]
    rows = [r for r in rows if r["method"] != FAILED]
    methods = sorted({r["method"] for r in rows}, key=lambda m: (m != "adaptive", m))
    out = {"methods": {}, "failed_trials": len(failed), "failures": [r["error"] for r in failed]}
    for m in methods:
        st = [r for r in rows if r["method"] == m and "x_m" in r]
        he = [r for r in rows if r["method"] == m and "x_m" not in r]
        det = [r for r in st if r["detected"]]
        env = [r for r in st if (r.get("p_detect_pred") or 0.0) >= P_ENVELOPE]
        out["methods"][m] = {
            "stones": len(st), "healthy": len(he), "detected": len(det),
            "detected_fraction": len(det) / len(st) if st else float("nan"),
            "median_lateral_error_m": _median([r["err_lateral_m"] for r in det]),
            "median_depth_error_m": _median([abs(r["err_depth_m"]) for r in det]),
            "median_diameter_error_m": _median([abs(r["err_diam_m"]) for r in det]),
            "coverage_x_68": _coverage(det, "err_x_m", "sigma_x_m", 1), "coverage_x_95": _coverage(det, "err_x_m", "sigma_x_m", 2),
            "coverage_y_68": _coverage(det, "err_y_m", "sigma_y_m", 1), "coverage_y_95": _coverage(det, "err_y_m", "sigma_y_m", 2),
            "coverage_depth_68": _coverage(det, "err_depth_m", "sigma_depth_m", 1),
            "coverage_depth_95": _coverage(det, "err_depth_m", "sigma_depth_m", 2),
            "in_envelope": len(env), "detected_in_envelope": sum(r["detected"] for r in env),
            "detect_in_envelope_fraction": (sum(r["detected"] for r in env) / len(env)) if env else float("nan"),
            "false_alarms": sum(r["detected"] for r in he),
            "false_alarm_fraction": (sum(r["detected"] for r in he) / len(he)) if he else float("nan"),
            "median_probes": _median([r["n_probes"] for r in st]),
            "median_probes_healthy": _median([r["n_probes"] for r in he])}
    a = out["methods"].get("adaptive")
    if a:
        need = None
        for m, s in sorted(out["methods"].items(), key=lambda kv: kv[1]["median_probes"]):
            if m.startswith("grid-") and s["median_lateral_error_m"] <= a["median_lateral_error_m"] \
                    and s["median_depth_error_m"] <= a["median_depth_error_m"]:
                need = (m, s["median_probes"])
                break
        largest = max((s["median_probes"] for m, s in out["methods"].items() if m.startswith("grid-")), default=0)
        out["even_grid_for_adaptive_medians"] = (
            {"method": need[0], "probes": need[1], "ratio_to_adaptive": need[1] / a["median_probes"]} if need else
            {"method": None, "probes_more_than": largest, "ratio_to_adaptive_more_than": largest / a["median_probes"]})
        out["oracle_gain_median"] = _median([r.get("oracle_gain") for r in rows if r["method"] == "adaptive"])
        out["targets"] = TARGETS
        out["met"] = {"lateral": a["median_lateral_error_m"] < TARGETS["lateral_m"],
                      "depth": a["median_depth_error_m"] < TARGETS["depth_m"],
                      "detect_in_envelope": a["detect_in_envelope_fraction"] >= TARGETS["detect_in_envelope"],
                      "false_alarm": a["false_alarm_fraction"] <= TARGETS["false_alarm"]}
    return out


def _fmt(v, scale=1.0, nd=2) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v * scale:.{nd}f}"


def write_report(out: Path, rows: list[dict], command: str, elapsed_s: float, where: str) -> list[str]:
    out.mkdir(parents=True, exist_ok=True)
    keys = sorted({k for r in rows for k in r})
    with open(out / "accuracy3d.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows([csv_row(r) for r in rows])
    s = summarise(rows)
    s.update({"command": command, "elapsed_s": elapsed_s, "where": where})
    (out / "accuracy3d.json").write_text(json.dumps(nulled(s), indent=1, default=lambda v: None, allow_nan=False))
    lines = [f"3D accuracy study: `{command}` ({elapsed_s:.0f} s, {where})", "",
             "| method | probes (median) | detected | lateral error (mm, median) | depth error (mm, median) | "
             "diameter error (mm) | x in 1/2 sigma | y in 1/2 sigma | depth in 1/2 sigma | detected in envelope | "
             "false alarms | probes on healthy blocks (median) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for m, v in s["methods"].items():
        lines.append(
            f"| {m} | {_fmt(v['median_probes'], 1, 0)} | {v['detected']}/{v['stones']} | "
            f"{_fmt(v['median_lateral_error_m'], 1e3)} | {_fmt(v['median_depth_error_m'], 1e3)} | "
            f"{_fmt(v['median_diameter_error_m'], 1e3)} | {_fmt(v['coverage_x_68'], 100, 0)} / "
            f"{_fmt(v['coverage_x_95'], 100, 0)} % | {_fmt(v['coverage_y_68'], 100, 0)} / "
            f"{_fmt(v['coverage_y_95'], 100, 0)} % | {_fmt(v['coverage_depth_68'], 100, 0)} / "
            f"{_fmt(v['coverage_depth_95'], 100, 0)} % | {v['detected_in_envelope']}/{v['in_envelope']} | "
            f"{v['false_alarms']}/{v['healthy']} | {_fmt(v['median_probes_healthy'], 1, 0)} |")
    e = s.get("even_grid_for_adaptive_medians")
    if e:
        lines += ["", ("even grid reaching the adaptive run's medians: "
                       + (f"{e['method']} ({e['probes']:.0f} probes, {e['ratio_to_adaptive']:.2f}x the adaptive run's)"
                          if e.get("method") else
                          f"none of the grids (more than {e['probes_more_than']:.0f} probes, "
                          f"> {e['ratio_to_adaptive_more_than']:.2f}x)"))]
    if "oracle_gain_median" in s:
        lines += ["", f"Cramer-Rao: the best placement (greedy A-optimal at the TRUE stone, the adaptive run's probe "
                      f"count) needs {_fmt(s['oracle_gain_median'], 1, 2)}x fewer probes than an even grid for the same "
                      f"var(x) + var(y) + var(depth) (median over the stones; planner.accuracy3d.oracle_gain)"]
    if s["failed_trials"]:
        lines += ["", f"{s['failed_trials']} trial(s) failed and are not counted above: " + "; ".join(s["failures"])]
    if "met" in s:
        lines += ["", "targets (adaptive): " + ", ".join(f"{k} {'met' if v else 'NOT met'}" for k, v in s["met"].items())]
    (out / "accuracy3d.md").write_text("\n".join(lines) + "\n")
    _figure(out / "accuracy3d.png", rows, s)
    return lines


def _figure(path: Path, rows: list[dict], s: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.5))
    ad = [r for r in rows if r["method"] == "adaptive" and "x_m" in r]
    det = [r for r in ad if r["detected"]]
    miss = [r for r in ad if not r["detected"]]
    for a, key, name in ((ax[0], "err_lateral_m", "lateral error (mm)"), (ax[1], "err_depth_m", "depth error (mm)")):
        sc = a.scatter([r["depth_m"] * 1e3 for r in det], [abs(r[key]) * 1e3 for r in det],
                       c=[r["diam_m"] * 1e3 for r in det], cmap="viridis", s=25, label="detected")
        a.scatter([r["depth_m"] * 1e3 for r in miss], [0.0] * len(miss), marker="x", c="r", label="missed")
        a.set_xlabel("true centre depth (mm)")
        a.set_ylabel(name)
        a.set_yscale("symlog", linthresh=0.1)
        a.legend(fontsize=7)
        fig.colorbar(sc, ax=a, label="diameter (mm)")
    for m, v in s["methods"].items():
        ax[2].plot(v["median_probes"], v["median_lateral_error_m"] * 1e3, "o" if m == "adaptive" else "s",
                   label=f"{m}: lateral")
        ax[2].plot(v["median_probes"], v["median_depth_error_m"] * 1e3, "^" if m == "adaptive" else "v",
                   label=f"{m}: depth")
    ax[2].set_xlabel("probes (median)")
    ax[2].set_ylabel("median error (mm)")
    ax[2].legend(fontsize=6, ncol=2)
    ax[2].set_title("adaptive against even grids")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
