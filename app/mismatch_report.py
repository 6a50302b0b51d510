"""The mismatch study's report: summary numbers, the markdown table, the figure of error against each mismatch."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np


def _pct(v) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{100 * v:.0f} %"


def _num(v, digits: int = 2) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"


def summarize(rows) -> dict:
    ok = [r for r in rows if r["rc"] == 0]
    st = [r for r in ok if r["stone"]]
    he = [r for r in ok if not r["stone"]]
    det = [r for r in st if r["detected"]]
    env = [r for r in st if r.get("p_detect", 0) >= 0.9]
    env_t = [r for r in st if r.get("p_detect_truth", 0) >= 0.9]

    def med(key, rs, q=50):
        v = [abs(r[key]) * 1e3 for r in rs if key in r]
        return float(np.percentile(v, q)) if v else float("nan")

    def rate(rs, key):
        rs = [r for r in rs if r.get(key) not in (None, "")]      # (older rows lack the newer comparisons)
        return float(np.mean([r[key] in (True, "True") for r in rs])) if rs else float("nan")

    def top(rs, key):
        return float(max([float(r[key]) for r in rs if r.get(key) not in (None, "")] or [np.nan]))
    return {"trials": len(rows), "failed_runs": len(rows) - len(ok), "stones": len(st), "healthy": len(he),
            "in_envelope": len(env), "detection_rate": rate(st, "detected"),
            "detection_rate_in_envelope": rate(env, "detected"), "false_alarm_rate": rate(he, "detected"),
            "in_envelope_truth": len(env_t), "detection_rate_in_envelope_truth": rate(env_t, "detected"),
            "detection_rate_known_tissue": rate(st, "detected_known_tissue"),
            "false_alarm_rate_known_tissue": rate(he, "detected_known_tissue"),
            "lateral_err_median_mm": med("err_x_m", det), "lateral_err_p90_mm": med("err_x_m", det, 90),
            "depth_err_median_mm": med("err_depth_m", det), "depth_err_p90_mm": med("err_depth_m", det, 90),
            "lateral_err_median_known_tissue_mm": med("err_x_known_tissue_m", st),
            "depth_err_median_known_tissue_mm": med("err_depth_known_tissue_m", st),
            "depth_sigma_median_mm": med("sigma_depth_m", det),
            "coverage_depth_68": rate(det, "in68"), "coverage_depth_95": rate(det, "in95"),
            "coverage_x_1sigma": rate(det, "x_in1s"), "coverage_x_2sigma": rate(det, "x_in2s"),
            "offset_err_median_mm": float(np.median([abs(r["offset_est_m"] - r["surface_offset_m"]) * 1e3
                                                     for r in ok if r.get("onsets", 0) > 0] or [np.nan])),
            "max_lr_healthy": float(max([r["lr"] for r in he] or [np.nan])),
            "max_lr_healthy_known_tissue": float(max([r["lr_known_tissue"] for r in he] or [np.nan])),
            "detection_rate_no_finite_strain": rate(st, "detected_no_finite_strain"),
            "false_alarm_rate_no_finite_strain": rate(he, "detected_no_finite_strain"),
            "lateral_err_median_no_finite_strain_mm": med("err_x_no_finite_strain_m", st),
            "depth_err_median_no_finite_strain_mm": med("err_depth_no_finite_strain_m", st),
            "max_lr_healthy_no_finite_strain": top(he, "lr_no_finite_strain"),
            "wall_s_mean": float(np.mean([r["wall_s"] for r in rows]))}


def table(s: dict, cmd: str) -> str:
    return "\n".join([
        f"Mismatch study (`{cmd}`): {s['stones']} random stones, {s['healthy']} healthy scenes "
        f"({s['failed_runs']} runs failed), mean {s['wall_s_mean']:.0f} s per run.", "",
        "| localizer | detected (all stones) | detected (inside envelope: the prior's, n / the truth's, n) | false "
        "alarms | lateral err median / p90 (mm) | depth err median / p90 (mm) | depth 68 % / 95 % interval coverage | "
        "x within 1 / 2 sigma |",
        "|---|---:|---:|---:|---|---|---|---|",
        f"| tissue unknowns fitted (issue 14) | {_pct(s['detection_rate'])} | {_pct(s['detection_rate_in_envelope'])} "
        f"({s['in_envelope']}) / {_pct(s.get('detection_rate_in_envelope_truth'))} ({s.get('in_envelope_truth', 0)}) "
        f"| {_pct(s['false_alarm_rate'])} | {s['lateral_err_median_mm']:.2f} / "
        f"{s['lateral_err_p90_mm']:.2f} | {s['depth_err_median_mm']:.2f} / {s['depth_err_p90_mm']:.2f} | "
        f"{_pct(s['coverage_depth_68'])} / {_pct(s['coverage_depth_95'])} | {_pct(s['coverage_x_1sigma'])} / "
        f"{_pct(s['coverage_x_2sigma'])} |",
        f"| tissue taken as the prior (before), same probes | {_pct(s['detection_rate_known_tissue'])} | | "
        f"{_pct(s['false_alarm_rate_known_tissue'])} | {s['lateral_err_median_known_tissue_mm']:.2f} median | "
        f"{s['depth_err_median_known_tissue_mm']:.2f} median | | |",
        f"| without the finite-strain term (a linear tissue assumed), same probes | "
        f"{_pct(s.get('detection_rate_no_finite_strain'))} | | {_pct(s.get('false_alarm_rate_no_finite_strain'))} | "
        f"{_num(s.get('lateral_err_median_no_finite_strain_mm'))} median | "
        f"{_num(s.get('depth_err_median_no_finite_strain_mm'))} median | | |", "",
        f"Largest LR on healthy tissue: {s['max_lr_healthy']:.1f} (threshold 20); with the tissue taken as the prior "
        f"{s['max_lr_healthy_known_tissue']:.1f}, without the finite-strain term "
        f"{_num(s.get('max_lr_healthy_no_finite_strain'), 1)}. Surface offset from the contact onsets: median error "
        f"{s['offset_err_median_mm']:.3f} mm. Median depth sigma reported: {s['depth_sigma_median_mm']:.2f} mm."])


def by_hyperelastic(rows) -> str:
    """A line per truth model (linear, neo-Hookean) when the study drew neo-Hookean truths; else nothing."""
    if not any(r.get("hyperelastic") in (True, "True") for r in rows):
        return ""
    out = ["", "", "| truth | stones | detected | false alarms (healthy) | largest healthy LR | lateral err median (mm) | "
           "depth err median (mm) | finite-strain amplitude a, median (range) | without the term, same probes: "
           "detected / false alarms / largest healthy LR / lateral, depth err median (mm) |",
           "|---|---:|---:|---:|---:|---|---|---|---|"]
    for name, on in (("linear elastic", False), ("neo-Hookean", True)):
        group = [r for r in rows if (r.get("hyperelastic") in (True, "True")) == on]
        if not group:
            continue
        s = summarize(group)
        mm = [("-" if not np.isfinite(s[k]) else f"{s[k]:.2f}") for k in ("lateral_err_median_mm",
                                                                           "depth_err_median_mm")]
        a = [float(r["finite_strain_est"]) for r in group if r.get("finite_strain_est") not in (None, "")]
        a_txt = f"{np.median(a):.2f} ({min(a):.2f}-{max(a):.2f})" if a else "-"
        lr = "-" if not np.isfinite(s["max_lr_healthy"]) else f"{s['max_lr_healthy']:.1f}"
        f2 = [("-" if not np.isfinite(s[k]) else f"{s[k]:.{n}f}") for k, n in (
            ("max_lr_healthy_no_finite_strain", 1), ("lateral_err_median_no_finite_strain_mm", 2),
            ("depth_err_median_no_finite_strain_mm", 2))]
        out.append(f"| {name} | {s['stones']} | {_pct(s['detection_rate'])} | {_pct(s['false_alarm_rate'])} "
                   f"({s['healthy']}) | {lr} | {mm[0]} | {mm[1]} | {a_txt} | "
                   f"{_pct(s['detection_rate_no_finite_strain'])} / {_pct(s['false_alarm_rate_no_finite_strain'])} / "
                   f"{f2[0]} / {f2[1]}, {f2[2]} |")
    return "\n".join(out)


def figure(rows, path: Path) -> None:
    """|error| of each detected stone against each mismatch; neo-Hookean truths (when the study drew them) in their
    own colour, with a panel of their own."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    det = [r for r in rows if r["rc"] == 0 and r["stone"] and r["detected"]]
    keys = [("youngs_scale", "modulus / prior"), ("poisson", "Poisson ratio"), ("thickness_scale", "thickness / prior"),
            ("surface_offset_m", "surface offset (mm)"), ("surface_tilt_deg", "tilt (deg)"),
            ("viscoelastic", "viscoelastic (0/1)")]
    hyper = np.array([r.get("hyperelastic") in (True, "True") for r in det], bool)
    if hyper.any():
        keys.append(("hyperelastic", "neo-Hookean (0/1)"))
    fig, axes = plt.subplots(2, (len(keys) + 1) // 2, figsize=(4 * ((len(keys) + 1) // 2), 6.5), sharey=True)
    groups = [("linear", ~hyper, "C0", "C1"), ("neo-Hookean", hyper, "C2", "C3")] if hyper.any() else \
        [("", ~hyper, "C0", "C1")]
    for ax, (k, lab) in zip(axes.flat, keys):
        v = np.array([float(r[k] in (True, "True")) if k == "hyperelastic" else
                      float(r[k]) * (1e3 if k == "surface_offset_m" else 1) for r in det])
        for name, sel, c_depth, c_lat in groups:
            dep = np.array([abs(r["err_depth_m"]) * 1e3 for r in det])
            lat = np.array([abs(r["err_x_m"]) * 1e3 for r in det])
            tag = f" ({name})" if name else ""
            ax.scatter(v[sel], dep[sel], s=14, color=c_depth, label="depth" + tag)
            ax.scatter(v[sel], lat[sel], s=14, marker="x", color=c_lat, label="lateral" + tag)
        ax.set_xlabel(lab)
        ax.set_yscale("log")
    for ax in axes.flat[len(keys):]:
        ax.axis("off")
    axes[0, 0].set_ylabel("|error| (mm)")
    axes[1, 0].set_ylabel("|error| (mm)")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("palpate: stone error against each mismatch (truth drawn from the documented ranges)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(out: Path, rows: list[dict], cmd: str) -> str:
    """mismatch.csv (one row per trial), mismatch.json (the summary), mismatch.md and mismatch.png in ``out``;
    returns the markdown."""
    keys = sorted({k for r in rows for k in r})
    with open(out / "mismatch.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    s = summarize(rows)
    (out / "mismatch.json").write_text(json.dumps(s, indent=1) + "\n")
    md = table(s, cmd) + by_hyperelastic(rows)
    (out / "mismatch.md").write_text(md + "\n")
    if any(r["rc"] == 0 and r["stone"] and r.get("detected") for r in rows):
        figure(rows, out / "mismatch.png")
    return md
