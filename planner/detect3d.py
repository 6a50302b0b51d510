"""Detectability over an area before any probe: which spherical stones (diameter, depth, position) can a planned 3D
raster find with a given sensor?

The 2D analysis (planner.detectability) over a surface: the surrogate (planner.surrogate3d) gives the contrast c_i a
stone adds at each planned probe; the sensor gives each probe's standard error sigma_i; the localizer's nuisance
(planner.localize3d: the drift offset, tau_i, with the localizer's prior on the drift rate, the stiffness scale,
the prior's force F_i, and the thickness change, dF_i/d eta with the localizer's prior on it) is projected out, and
the expected likelihood ratio is the noncentrality lambda of what remains. The detection probability is P(LR >=
threshold) with LR ~ noncentral chi2(4 dof, lambda): four fitted stone parameters (x, y, depth, diameter), the
localizer's own threshold (LR_THRESHOLD3D). A stone counts as detectable when that probability is at least 0.9.
The surface offset and tilts are pinned by the contact onsets and left out, as in 2D.
"""
from __future__ import annotations

import numpy as np

from planner.detectability import (
    P_DETECT,
    ncx2_sf,
    noncentrality,
    probe_sigma_n,
    probe_tau_s,
    sensor_usable,
    smallest_detectable,
)
from planner.localize import DRIFT_SIGMA_N_PER_S, FLOOR_GAP_M, MODEL_ABS_ERR_N, THICKNESS_SIGMA
from planner.localize3d import LR_THRESHOLD3D

STONE_DOF = 4


def weights3d(sigma_n, contrast_n, surrogate) -> np.ndarray:
    """1 / sigma^2 per probe as localize3d weighs it: the sensor noise plus the surrogate's error allowance."""
    c = np.asarray(contrast_n, float)
    rel = float(getattr(surrogate, "rel_err", 0.02))
    ab = float(getattr(surrogate, "abs_err_n", MODEL_ABS_ERR_N))
    return 1.0 / (np.asarray(sigma_n, float) ** 2 + ab ** 2 + (rel * np.maximum(c, 0.0)) ** 2)


def p_detect3d(stone, *, x_m, y_m, depth_m, sigma_n, surrogate, prior_force_n, tau_s, thickness_slope_n=None,
               thickness_sigma: float = THICKNESS_SIGMA, lr_threshold: float = LR_THRESHOLD3D) -> float:
    """Predicted detection probability of one stone (xs_m, ys_m, depth_m, diameter_m) by probes at (x_m, y_m)
    pressed ``depth_m`` deep, the stiffness scale and the drift unknown, and the thickness when
    ``thickness_slope_n`` (the prior's dF/d eta at each probe: planner.tissue_response3d) is given, with the prior
    ``thickness_sigma`` on eta (0: known)."""
    x, y, d = (np.asarray(v, float) for v in (x_m, y_m, depth_m))
    dc = np.clip(d, surrogate.levels[0], surrogate.levels[-1])
    c = np.asarray(surrogate.contrast(x, y, dc, *stone), float)
    w = weights3d(sigma_n, c, surrogate)
    cols = [np.broadcast_to(np.asarray(tau_s, float), x.shape), np.broadcast_to(prior_force_n, x.shape)]
    prec = [1.0 / DRIFT_SIGMA_N_PER_S ** 2, 0.0]
    if thickness_slope_n is not None and thickness_sigma > 0:
        cols.append(np.broadcast_to(np.asarray(thickness_slope_n, float), x.shape))
        prec.append(1.0 / thickness_sigma ** 2)
    lam = noncentrality(c, w, np.array(cols).T, np.array(prec))
    return ncx2_sf(lr_threshold, STONE_DOF, max(lam, 1e-12))


def detectability3d(plan, surrogate, prior_force_n, *, sensor_spec, stones=None, thickness_slope_n=None,
                    thickness_sigma: float = THICKNESS_SIGMA) -> dict:
    """Predicted detection of stones (``stones``: (diameter_m, depth_m) pairs; default a grid) centred under the
    middle of a 3D ``plan``'s raster, by that raster. ``prior_force_n``: the prior's force at each planned probe (or
    one for all: the median planned force); ``thickness_slope_n``: its derivative with respect to the thickness change
    at each probe, with the prior ``thickness_sigma`` (None or 0: the thickness taken as known). Returns {"usable",
    "reason", "sigma_n", "rows": [{diameter_m, depth_m, p_detect, detectable}],
    "smallest_detectable": [{depth_m, diameter_m}]}."""
    x = np.array([p.x_m for p in plan.probes])
    y = np.array([p.y_m for p in plan.probes])
    d = np.array([p.depth_m for p in plan.probes])
    usable, reason = sensor_usable(sensor_spec, plan.limits.force_limit_n)
    sig = probe_sigma_n(sensor_spec, plan.motion)
    tau = probe_tau_s(plan.motion, d)
    b = surrogate.bounds() if callable(surrogate.bounds) else surrogate.bounds
    if stones is None:
        stones = [(D, dep) for D in (6e-3, 8e-3, 10e-3, 12e-3, 15e-3) for dep in (10e-3, 15e-3, 20e-3, 25e-3, 30e-3)]
    xc, yc = 0.5 * (x.min() + x.max()), 0.5 * (y.min() + y.max())
    rows = []
    for D, dep in stones:
        s = dep - D / 2
        if "height_m" in b and dep + D / 2 > b["height_m"] - FLOOR_GAP_M:
            rows.append({"diameter_m": D, "depth_m": dep, "p_detect": None, "detectable": None,
                         "note": "does not fit in the block"})
            continue
        if not (b["s_m"][0] <= s <= b["s_m"][1] + 1e-12 and b["diam_m"][0] <= D <= b["diam_m"][1] + 1e-12):
            rows.append({"diameter_m": D, "depth_m": dep, "p_detect": None, "detectable": None,
                         "note": "outside the surrogate's range"})
            continue
        p = p_detect3d((xc, yc, dep, D), x_m=x, y_m=y, depth_m=d, sigma_n=sig, surrogate=surrogate,
                       prior_force_n=prior_force_n, tau_s=tau, thickness_slope_n=thickness_slope_n,
                       thickness_sigma=thickness_sigma) if usable else 0.0
        ok = bool(usable and p >= P_DETECT)
        rows.append({"diameter_m": D, "depth_m": dep, "p_detect": p, "detectable": ok})
    return {"usable": usable, "reason": reason, "sigma_n": sig, "rows": rows,
            "smallest_detectable": smallest_detectable(rows)}
