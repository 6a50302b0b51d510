"""Mismatch study: the truth is not the belief (issue 14). A script, not a test.

    python bench/mismatch_study.py [--quick] [--stones N] [--healthy N] [--budget 25] [--seed 1] [--out bench-out]

Every trial is a whole ``palpate run TRUTH --plan plan.json --sim`` (planner, driver on the in-memory simulated arm,
localizer, refinement) where the planner and the localizer know only the ``paper`` prior (E = 2500 Pa, nu = 0.4,
50 mm thick, surface on the nominal tissue pose) and the simulated truth is drawn from these ranges:

    tissue modulus       x 0.5 - x 2 of the prior (log-uniform)
    Poisson ratio        0.35 - 0.49 (uniform)
    thickness            prior +- 10 % (uniform)
    surface offset       +- 2 mm against the nominal tissue pose (uniform; positive: above it)
    surface tilt         +- 3 deg about the tissue's y axis (uniform)
    viscoelastic         on in half the trials: relaxation 20-30 %, tau 1-4 s (standard linear solid)
    stone                random rigid stone inside the true tissue (planner.surrogate.random_stones), or none

and the sensor is the nano17 preset (its own random bias and drift). The plan (made once, on the prior) indents
3 mm (not the default 4 mm: with a surface up to 2 mm above the nominal one the true indentation reaches 5 mm, the
tip radius, where fem's contact model ends) with a contact threshold of 8 mN (the default 20 mN is not reached at
all when the surface lies 2 mm below the nominal one). Everything else is palpate run's default.

Per trial the same probe records are also localized with the tissue taken as known (``nuisance=False``: the
localizer before issue 14) for comparison. Detectability envelope: a stone counts as inside when
planner.detectability.p_detect (nuisance projected out, the coarse raster) is at least 0.9.

Outputs in OUT: mismatch.csv (one row per trial), mismatch.md (the tables), mismatch.png (error against each
mismatch), mismatch_runs/<trial>/ (every run's files: nothing is deleted).
"""
from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import io
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from app.cli import main as palpate  # noqa: E402
from core.contracts import Limits, Motion, sensor_spec  # noqa: E402
from fem import contact  # noqa: E402
from fem.scene import Stone, dump_toml, load  # noqa: E402
from planner.detectability import p_detect, probe_sigma_n, probe_tau_s  # noqa: E402
from planner.localize import Measurements, localize  # noqa: E402
from planner.plan import plan_raster  # noqa: E402
from planner.surrogate import load_surrogate, random_stones  # noqa: E402
from planner.tissue_response import PriorResponse, prior_and_thickness_slope  # noqa: E402
from robot.records import read_records  # noqa: E402

PLAN_DEPTH_M = 0.003
CONTACT_THRESHOLD_N = 0.008
RANGES = {"youngs_scale": (0.5, 2.0), "poisson": (0.35, 0.49), "thickness_scale": (0.9, 1.1),
          "surface_offset_m": (-0.002, 0.002), "surface_tilt_deg": (-3.0, 3.0), "relaxation_fraction": (0.2, 0.3),
          "relaxation_tau_s": (1.0, 4.0)}


def draw_mismatch(rng) -> dict:
    r = RANGES
    return {"youngs_scale": float(math.exp(rng.uniform(math.log(r["youngs_scale"][0]), math.log(r["youngs_scale"][1])))),
            "poisson": float(rng.uniform(*r["poisson"])), "thickness_scale": float(rng.uniform(*r["thickness_scale"])),
            "surface_offset_m": float(rng.uniform(*r["surface_offset_m"])),
            "surface_tilt_deg": float(rng.uniform(*r["surface_tilt_deg"])),
            "viscoelastic": bool(rng.uniform() < 0.5),
            "relaxation_fraction": float(rng.uniform(*r["relaxation_fraction"])),
            "relaxation_tau_s": float(rng.uniform(*r["relaxation_tau_s"]))}


def truth_toml(prior, mm: dict, stone) -> str:
    t = prior.tissue
    sc = dataclasses.replace(prior, name="truth", stones=(stone,) if stone is not None else (),
                             tissue=dataclasses.replace(t, youngs_pa=t.youngs_pa * mm["youngs_scale"],
                                                        poisson=mm["poisson"],
                                                        height_m=t.height_m * mm["thickness_scale"]))
    truth = {"surface_offset_m": mm["surface_offset_m"], "surface_tilt_rad": math.radians(mm["surface_tilt_deg"]),
             "relaxation_fraction": mm["relaxation_fraction"] if mm["viscoelastic"] else 0.0,
             "relaxation_tau_s": mm["relaxation_tau_s"]}
    return dump_toml(sc) + "\n[truth]\n" + "".join(f"{k} = {v!r}\n" for k, v in truth.items())


def keep_only(cache_keys) -> None:
    """Drop the simulator's one-off truth models from fem's in-memory cache (hundreds of MB otherwise)."""
    for k in list(contact._CACHE):
        if k not in cache_keys:
            del contact._CACHE[k]


def trial(i, prior, sur, plan_path, mm, stone, seed, budget, runs: Path, coarse_x) -> dict:
    d = runs / f"trial{i:03d}"
    d.mkdir(parents=True, exist_ok=True)
    (d / "truth.toml").write_text(truth_toml(prior, mm, stone))
    t0 = time.perf_counter()
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = palpate(["run", str(d / "truth.toml"), "--plan", str(plan_path), "--sim", "--seed", str(seed),
                      "--budget-probes", str(budget), "--no-figure", "--out", str(d / "run")])
    row = {"trial": i, "seed": seed, "rc": rc, "wall_s": time.perf_counter() - t0, **mm,
           "stone": stone is not None}
    if rc != 0:
        row["error"] = err.getvalue().strip().splitlines()[-1:]
        return row
    r = json.loads((d / "run" / "result.json").read_text())
    est, nu = r["estimate"], r["nuisance"]
    row.update(detected=r["detected"], lr=r["evidence"]["likelihood_ratio"], probes=r["probes_used"],
               stiffness_scale=nu["stiffness_scale"]["value"], thickness_est=nu["thickness_scale"]["value"],
               offset_est_m=nu["surface_offset_m"]["value"], tilt_est_rad=nu["surface_tilt_rad"]["value"],
               relax_est=nu["dwell_relaxation_fraction"]["value"], onsets=nu["contact_onsets_used"])
    meas = Measurements.from_records(read_records(d / "run"), statuses=("ok", "force_limit"))
    old = localize(prior, meas, sur, nuisance=False)
    row.update(detected_known_tissue=old.detected, lr_known_tissue=old.lr)
    if stone is not None:
        row.update(x_m=stone.x_m, depth_m=stone.depth_m, diameter_m=stone.diameter_m)
        dep = np.full(len(coarse_x), PLAN_DEPTH_M)
        row["p_detect"] = p_detect(prior, (stone.x_m, stone.depth_m, stone.diameter_m), x_m=coarse_x, depth_m=dep,
                                   sigma_n=probe_sigma_n(sensor_spec("nano17")), surrogate=sur,
                                   tau_s=probe_tau_s(Motion(), dep))
        if r["detected"]:
            iv = est["depth_interval_m"]
            row.update(err_x_m=est["x_m"]["value"] - stone.x_m, err_depth_m=est["depth_m"]["value"] - stone.depth_m,
                       err_diam_m=est["diameter_m"]["value"] - stone.diameter_m, sigma_x_m=est["x_m"]["sigma"],
                       sigma_depth_m=est["depth_m"]["sigma"],
                       in68=bool(iv["68"][0] <= stone.depth_m <= iv["68"][1]),
                       in95=bool(iv["95"][0] <= stone.depth_m <= iv["95"][1]),
                       x_in1s=bool(abs(est["x_m"]["value"] - stone.x_m) <= est["x_m"]["sigma"]),
                       x_in2s=bool(abs(est["x_m"]["value"] - stone.x_m) <= 2 * est["x_m"]["sigma"]))
        if old.detected:
            row.update(err_x_known_tissue_m=old.x_m - stone.x_m, err_depth_known_tissue_m=old.depth_m - stone.depth_m)
    return row


def _pct(v) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{100 * v:.0f} %"


def summarize(rows) -> dict:
    ok = [r for r in rows if r["rc"] == 0]
    st = [r for r in ok if r["stone"]]
    he = [r for r in ok if not r["stone"]]
    det = [r for r in st if r["detected"]]
    env = [r for r in st if r.get("p_detect", 0) >= 0.9]

    def med(key, rs, q=50):
        v = [abs(r[key]) * 1e3 for r in rs if key in r]
        return float(np.percentile(v, q)) if v else float("nan")

    def rate(rs, key):
        return float(np.mean([bool(r[key]) for r in rs])) if rs else float("nan")
    return {"trials": len(rows), "failed_runs": len(rows) - len(ok), "stones": len(st), "healthy": len(he),
            "in_envelope": len(env), "detection_rate": rate(st, "detected"),
            "detection_rate_in_envelope": rate(env, "detected"), "false_alarm_rate": rate(he, "detected"),
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
            "wall_s_mean": float(np.mean([r["wall_s"] for r in rows]))}


def table(s: dict, cmd: str) -> str:
    return "\n".join([
        f"Mismatch study (`{cmd}`): {s['stones']} random stones, {s['healthy']} healthy scenes "
        f"({s['failed_runs']} runs failed), mean {s['wall_s_mean']:.0f} s per run.", "",
        "| localizer | detected (all stones) | detected (inside envelope, n) | false alarms | lateral err median / p90 "
        "(mm) | depth err median / p90 (mm) | depth 68 % / 95 % interval coverage | x within 1 / 2 sigma |",
        "|---|---:|---:|---:|---|---|---|---|",
        f"| tissue unknowns fitted (issue 14) | {_pct(s['detection_rate'])} | {_pct(s['detection_rate_in_envelope'])} "
        f"({s['in_envelope']}) | {_pct(s['false_alarm_rate'])} | {s['lateral_err_median_mm']:.2f} / "
        f"{s['lateral_err_p90_mm']:.2f} | {s['depth_err_median_mm']:.2f} / {s['depth_err_p90_mm']:.2f} | "
        f"{_pct(s['coverage_depth_68'])} / {_pct(s['coverage_depth_95'])} | {_pct(s['coverage_x_1sigma'])} / "
        f"{_pct(s['coverage_x_2sigma'])} |",
        f"| tissue taken as the prior (before), same probes | {_pct(s['detection_rate_known_tissue'])} | | "
        f"{_pct(s['false_alarm_rate_known_tissue'])} | {s['lateral_err_median_known_tissue_mm']:.2f} median | "
        f"{s['depth_err_median_known_tissue_mm']:.2f} median | | |", "",
        f"Largest LR on healthy tissue: {s['max_lr_healthy']:.1f} (threshold 20); with the tissue taken as the prior "
        f"{s['max_lr_healthy_known_tissue']:.1f}. Surface offset from the contact onsets: median error "
        f"{s['offset_err_median_mm']:.3f} mm. Median depth sigma reported: {s['depth_sigma_median_mm']:.2f} mm."])


def figure(rows, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    det = [r for r in rows if r["rc"] == 0 and r["stone"] and r["detected"]]
    keys = [("youngs_scale", "modulus / prior"), ("poisson", "Poisson ratio"), ("thickness_scale", "thickness / prior"),
            ("surface_offset_m", "surface offset (mm)"), ("surface_tilt_deg", "tilt (deg)"),
            ("viscoelastic", "viscoelastic (0/1)")]
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5), sharey=True)
    for ax, (k, lab) in zip(axes.flat, keys):
        v = np.array([float(r[k]) * (1e3 if k == "surface_offset_m" else 1) for r in det])
        ax.scatter(v, [abs(r["err_depth_m"]) * 1e3 for r in det], s=14, label="depth")
        ax.scatter(v, [abs(r["err_x_m"]) * 1e3 for r in det], s=14, marker="x", label="lateral")
        ax.set_xlabel(lab)
        ax.set_yscale("log")
    axes[0, 0].set_ylabel("|error| (mm)")
    axes[1, 0].set_ylabel("|error| (mm)")
    axes[0, 0].legend()
    fig.suptitle("palpate: stone error against each mismatch (truth drawn from the documented ranges)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="20 stones and 10 healthy scenes")
    p.add_argument("--stones", type=int, default=100)
    p.add_argument("--healthy", type=int, default=40)
    p.add_argument("--budget", type=int, default=25, help="probe budget per run (default 25)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", default="bench-out")
    a = p.parse_args(argv)
    if a.quick:
        a.stones, a.healthy = 20, 10
    out = Path(a.out)
    runs = out / "mismatch_runs"
    if runs.exists() and any(runs.iterdir()):
        print(f"{runs} holds runs of an earlier study: choose another --out (nothing is overwritten)", file=sys.stderr)
        return 2
    runs.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("PALPATE_CACHE_DIR", str(out / "cache"))     # the truths' one-off meshes stay out of ~
    prior = load("paper").prior()
    sur = load_surrogate(prior)
    plan = plan_raster(prior, n_waypoints=15, limits=Limits(depth_limit_m=PLAN_DEPTH_M),
                       motion=Motion(contact_threshold_n=CONTACT_THRESHOLD_N))
    plan_path = out / "mismatch_plan.json"
    plan.save(plan_path)
    coarse_x = np.array([q.x_m for q in plan.probes])
    PriorResponse(prior, coarse_x)
    prior_and_thickness_slope(prior, coarse_x, PLAN_DEPTH_M)
    keep = set(contact._CACHE)
    rng = np.random.default_rng(a.seed)
    rows, t0 = [], time.perf_counter()
    n = a.stones + a.healthy
    for i in range(n):
        mm = draw_mismatch(rng)
        stone = None
        if i < a.stones:
            H = prior.tissue.height_m * mm["thickness_scale"]
            xs, s, D = random_stones(sur.bounds, prior.tissue.width_m, H, 1, rng)[0]
            stone = Stone(x_m=xs, depth_m=s + D / 2, diameter_m=D)
        rows.append(trial(i, prior, sur, plan_path, mm, stone, a.seed * 100000 + i, a.budget, runs, coarse_x))
        keep_only(keep)
        r = rows[-1]
        print(f"  {i + 1}/{n} ({time.perf_counter() - t0:.0f} s): stone {r['stone']}, detected {r.get('detected')}, "
              f"LR {r.get('lr', float('nan')):.0f}, err x/depth "
              f"{r.get('err_x_m', float('nan')) * 1e3:.2f}/{r.get('err_depth_m', float('nan')) * 1e3:.2f} mm",
              file=sys.stderr, flush=True)
    keys = sorted({k for r in rows for k in r})
    with open(out / "mismatch.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    s = summarize(rows)
    (out / "mismatch.json").write_text(json.dumps(s, indent=1))
    cmd = "python bench/mismatch_study.py " + " ".join(argv if argv is not None else sys.argv[1:])
    md = table(s, cmd.strip())
    (out / "mismatch.md").write_text(md + "\n")
    print(md)
    figure(rows, out / "mismatch.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
