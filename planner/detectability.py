"""Detectability before any probe: which stones (diameter, depth) can a raster find with a given sensor and force limit?

For a candidate stone the surrogate gives the contrast c_i it adds at each planned probe (same positions and
force-chosen depths the planner would use). The sensor gives each probe's standard error sigma_i (white noise of the
dwell mean and of the zeroing; drift is a common offset, which the localizer fits and which is projected out here).
The expected likelihood ratio of "stone" over "no stone" is then the noncentrality

    lambda = sum (c_i / sigma_i)^2 - (sum c_i tau_i / sigma_i^2)^2 / sum (tau_i / sigma_i)^2

and the detection probability P(LR >= threshold) with LR ~ noncentral chi2(3 dof, lambda) (three fitted stone
parameters). The localizer also fits the tissue's unknowns (planner.localize: stiffness scale, thickness, surface);
with ``nuisance`` (default) the part of the contrast they can explain is projected out too: the columns are the
drift offset (tau_i), the scale (the prior's force F_i) and the thickness change (dF_i/d eta, with the localizer's
prior 1/THICKNESS_SIGMA^2 on it); the surface height is pinned by the contact onsets and left out. This is the
"widening" of detectability: a broad, deep stone looks like a thicker or stiffer tissue. A stone counts as detectable when that probability is at least 0.9. The same threshold as the localizer
(planner.localize.LR_THRESHOLD) is used, so the prediction and the accuracy study speak of the same decision.

The sensor must also pass the driver's own check: its filtered free-air noise, times 5, below half the force limit
(robot.driver refuses to probe otherwise: a force limit it cannot see is no limit).
"""
from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np
from scipy.special import chndtr

from core.contracts import (
    BASELINE_CLEARANCE_M,
    BASELINE_SETTLE_S,
    FILTER_WINDOW,
    MIN_BASELINE_SAMPLES,
    N_ZERO_AVERAGE,
    NOISE_SIGMA_FACTOR,
    Motion,
    sensor_spec,
)
from fem.contact import surface_model
from fem.scene import load
from planner.localize import FLOOR_GAP_M, LR_THRESHOLD, MODEL_ABS_ERR_N, MODEL_REL_ERR, THICKNESS_SIGMA
from planner.raster import choose_depths, raster_positions
from planner.surrogate import load_surrogate
from planner.tissue_response import prior_and_thickness_slope

P_DETECT = 0.9


def baseline_samples(motion, period_s: float = 0.002) -> int:
    """Free-air samples of one descent the driver's records average as the force baseline (robot.records)."""
    base_s = (motion.approach_height_m - BASELINE_CLEARANCE_M) / motion.probe_speed_m_s - BASELINE_SETTLE_S
    return max(0, int(base_s / period_s))


def probe_sigma_n(sensor_spec, motion=None, period_s: float = 0.002) -> float:
    """Standard error of one probe's force: noise of the dwell mean and of the free-air baseline it is taken
    relative to (robot.records; the sensor's 50-sample zeroing if the descent is too short for a baseline)."""
    motion = motion or Motion()
    n = max(1, int(round(motion.dwell_s / period_s)))
    nb = baseline_samples(motion, period_s)
    return float(sensor_spec.noise_std_n * math.sqrt(1.0 / n + 1.0 / (nb if nb >= MIN_BASELINE_SAMPLES
                                                                        else N_ZERO_AVERAGE)))


def fit_weights(sigma_n, contrast_n) -> np.ndarray:
    """1 / sigma^2 per probe as the localizer weighs it: sensor noise plus the forward model's error allowance."""
    c = np.asarray(contrast_n, float)
    return 1.0 / (np.asarray(sigma_n, float) ** 2 + MODEL_ABS_ERR_N ** 2 + (MODEL_REL_ERR * np.maximum(c, 0.0)) ** 2)


def probe_tau_s(motion, depth_m):
    """Time from the middle of the free-air baseline to the middle of the dwell (the drift offset grows with it)."""
    base_s = (motion.approach_height_m - BASELINE_CLEARANCE_M) / motion.probe_speed_m_s - BASELINE_SETTLE_S
    return 0.5 * base_s + (BASELINE_CLEARANCE_M + np.asarray(depth_m)) / motion.probe_speed_m_s + 0.5 * motion.dwell_s


def noncentrality(c, w, cols, prior_precision=None) -> float:
    """Expected LR of a stone whose contrast is ``c``: the weighted norm of the part of ``c`` that the nuisance
    ``cols`` (n x k) cannot explain (Gaussian priors of precision ``prior_precision`` (k) on their coefficients)."""
    c, w = np.asarray(c, float), np.asarray(w, float)
    N = np.asarray(cols, float).reshape(len(c), -1)
    A = N.T @ (w[:, None] * N)
    if prior_precision is not None:
        A = A + np.diag(prior_precision)
    b = N.T @ (w * c)
    return float(np.sum(w * c * c) - b @ np.linalg.solve(A + 1e-30 * np.eye(len(b)), b))


def sensor_usable(sensor_spec, force_limit_n: float) -> tuple[bool, str]:
    thr = NOISE_SIGMA_FACTOR * sensor_spec.noise_std_n / math.sqrt(FILTER_WINDOW)
    if thr >= 0.5 * force_limit_n:
        return False, (f"sensor {sensor_spec.name}: filtered noise x {NOISE_SIGMA_FACTOR:g} = {thr:.2f} N is "
                       f"above half the force limit {force_limit_n:g} N; the driver refuses to probe")
    return True, ""


def detectability(prior, *, sensor="nano17", force_limit_n: float = 2.0, depth_limit_m: float = 0.004,
                  x_positions_m=None, n_waypoints: int = 15, margin_m: float = 0.005, stones=None, xs_m=None,
                  surrogate=None, lr_threshold: float = LR_THRESHOLD, motion=None, nuisance: bool = True,
                  force_fraction: float = 0.5, min_depth_m: float = 0.001) -> dict:
    """Predicted detection of stones (``stones``: (diameter_m, depth_m) pairs; default a grid) by a raster whose
    depths are chosen as the planner chooses them (``force_fraction``, ``min_depth_m``: a plan's own options).

    Returns {"sensor", "usable", "reason", "sigma_n", "depths_m", "rows": [{diameter_m, depth_m, peak_contrast_n,
    snr, p_detect, detectable}]}. Stones are placed at ``xs_m`` (default: the middle of the section)."""
    if prior.stones:
        raise ValueError("detectability() takes the prior scene (no stones)")
    sp = sensor_spec(sensor)
    motion = motion or Motion()
    W = prior.tissue.width_m
    x = (np.asarray(x_positions_m, float) if x_positions_m is not None
         else raster_positions(W, n=n_waypoints, margin_m=margin_m))
    dc = choose_depths(surface_model(prior).force_n, x, force_limit_n=force_limit_n, depth_limit_m=depth_limit_m,
                       force_fraction=force_fraction, min_depth_m=min_depth_m)
    d = dc.depth_m
    usable, reason = sensor_usable(sp, force_limit_n)
    sig = probe_sigma_n(sp, motion)
    tau = probe_tau_s(motion, d)
    sur = surrogate or load_surrogate(prior)
    b = sur.bounds
    if stones is None:
        stones = [(D, dep) for D in (4e-3, 6e-3, 8e-3, 10e-3, 12e-3, 15e-3)
                  for dep in (5e-3, 10e-3, 15e-3, 20e-3, 25e-3, 30e-3, 35e-3, 40e-3)]
    xs = 0.5 * W if xs_m is None else float(xs_m)
    cols, prec = [tau], [0.0]
    if nuisance:
        P, dP = prior_and_thickness_slope(prior, x, d)
        cols, prec = [tau, P, dP], [0.0, 0.0, 1.0 / THICKNESS_SIGMA ** 2]
    cols = np.array(cols).T
    rows = []
    for D, dep in stones:
        s = dep - D / 2
        if s + D > prior.tissue.height_m - FLOOR_GAP_M:      # below the tissue (or within the localizer's gap)
            rows.append({"diameter_m": D, "depth_m": dep, "peak_contrast_n": None, "snr": None, "p_detect": None,
                         "detectable": None, "note": "does not fit in the tissue"})
            continue
        inside = b["s_m"][0] <= s <= b["s_m"][1] + 1e-12 and b["diam_m"][0] <= D <= b["diam_m"][1] + 1e-12
        if not inside:
            rows.append({"diameter_m": D, "depth_m": dep, "peak_contrast_n": None, "snr": None, "p_detect": None,
                         "detectable": None, "note": "outside the surrogate's range"})
            continue
        c = sur.contrast(x, d, xs, dep, D)
        w = fit_weights(sig, c)
        lam = noncentrality(c, w, cols, np.array(prec))
        p = ncx2_sf(lr_threshold, 3, max(lam, 1e-12)) if usable else 0.0
        rows.append({"diameter_m": D, "depth_m": dep, "peak_contrast_n": float(np.max(c)), "snr": math.sqrt(max(lam, 0)),
                     "p_detect": p, "detectable": bool(usable and p >= P_DETECT)})
    return {"sensor": sp.name, "usable": usable, "reason": reason, "sigma_n": sig, "force_limit_n": force_limit_n,
            "depths_m": [float(v) for v in d], "x_m": [float(v) for v in x], "xs_m": xs, "lr_threshold": lr_threshold,
            "nuisance": nuisance, "rows": rows}


def smallest_detectable(rows) -> list[dict]:
    """The smallest detectable stone at each depth of a detectability table's ``rows``: [{"depth_m", "diameter_m"}],
    by depth (depths with none detectable left out)."""
    best: dict[float, float] = {}
    for r in rows:
        if r.get("detectable"):
            best[r["depth_m"]] = min(best.get(r["depth_m"], math.inf), r["diameter_m"])
    return [{"depth_m": dep, "diameter_m": D} for dep, D in sorted(best.items())]


def describe_smallest(smallest: list[dict]) -> str:
    """``smallest_detectable``'s list on one line ("depth 10 mm: >= 6 mm, ..."; empty when there is none)."""
    return ", ".join(f"depth {s['depth_m'] * 1e3:g} mm: >= {s['diameter_m'] * 1e3:g} mm" for s in smallest)


def ncx2_sf(x: float, df: float, nc: float) -> float:
    """The non-central chi-squared survival function: 1 - scipy.special.chndtr, scipy.stats.ncx2.sf's value to
    2e-15 absolute over the range detection asks (tested), without scipy.stats (0.27 s of a command's start-up)."""
    v = 1.0 - float(chndtr(x, df, nc))
    return v if math.isnan(v) else max(0.0, v)          # a NaN stays NaN, as scipy.stats gives it


def p_detect(prior, stone, *, x_m, depth_m, sigma_n, surrogate, lr_threshold: float = LR_THRESHOLD,
             tau_s=None, nuisance: bool = True) -> float:
    """Predicted detection probability of one stone (x_m, depth_m, diameter_m) by probes at x_m/depth_m
    (``nuisance``: with the tissue's stiffness scale and thickness unknown, as the localizer fits them)."""
    c = surrogate.contrast(np.asarray(x_m), np.asarray(depth_m), *stone)
    tau = np.ones(len(c)) if tau_s is None else np.asarray(tau_s)
    w = fit_weights(sigma_n, c)
    cols, prec = [tau], [0.0]
    if nuisance:
        P, dP = prior_and_thickness_slope(prior, x_m, depth_m)
        cols, prec = [tau, P, dP], [0.0, 0.0, 1.0 / THICKNESS_SIGMA ** 2]
    lam = noncentrality(c, w, np.array(cols).T, np.array(prec))
    return ncx2_sf(lr_threshold, 3, max(lam, 1e-12))


def format_table(res: dict) -> str:
    """A depth x diameter table of p_detect (markdown)."""
    rows = res["rows"]
    Ds = sorted({r["diameter_m"] for r in rows})
    deps = sorted({r["depth_m"] for r in rows})
    head = "| depth \\ diameter | " + " | ".join(f"{D * 1e3:g} mm" for D in Ds) + " |"
    lines = [head, "|" + "---|" * (len(Ds) + 1)]
    for dep in deps:
        cells = []
        for D in Ds:
            r = next(r for r in rows if r["diameter_m"] == D and r["depth_m"] == dep)
            if r["p_detect"] is None:
                cells.append("-")
            else:
                cells.append(f"{'**yes**' if r['detectable'] else 'no'} {r['p_detect']:.2f} "
                             f"({r['peak_contrast_n'] * 1e3:.1f} mN)")
        lines.append(f"| {dep * 1e3:g} mm | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    """``python -m planner.detectability [SCENE] [--sensor S] [--force-limit-n F]``: the table, before any probe."""
    p = argparse.ArgumentParser(prog="python -m planner.detectability", description=__doc__.splitlines()[0])
    p.add_argument("scene", nargs="?", default="paper")
    p.add_argument("--sensor", default="nano17")
    p.add_argument("--force-limit-n", type=float, default=2.0)
    p.add_argument("--waypoints", type=int, default=15)
    p.add_argument("--json", metavar="PATH")
    p.add_argument("--known-tissue", action="store_true",
                   help="as if the tissue's stiffness and thickness were known (no nuisance projected out)")
    a = p.parse_args(argv)
    r = detectability(load(a.scene).prior(), sensor=a.sensor, force_limit_n=a.force_limit_n,
                      n_waypoints=a.waypoints, nuisance=not a.known_tissue)
    print(f"{a.waypoints}-probe raster, sensor {r['sensor']} (probe sigma {r['sigma_n'] * 1e3:.2f} mN), force limit "
          f"{a.force_limit_n:g} N, probe depth {min(r['depths_m']) * 1e3:.2f}-{max(r['depths_m']) * 1e3:.2f} mm; "
          f"P(detect) at LR >= {r['lr_threshold']:g} (peak contrast):")
    if not r["usable"]:
        print("NOT USABLE: " + r["reason"])
    print(format_table(r))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(r, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
