"""The figure of a run: measured against predicted force along the surface, and the estimate on the section.

``run_figure`` computes what it shows (fem's prior curve, the fitted stone's contrast): planner.draw_run's
``RunFigure``, which ``planner.draw_run.draw_run`` draws, in the run's process or in a child (``app.figchild``).
"""
from __future__ import annotations

import numpy as np

from fem import recall
from planner.draw_run import RunFigure
from planner.tissue_response import fem_deepest_m

MAX_CURVES = 4


def curve_depths(prior, depth_m) -> np.ndarray:
    """The probed depths (to 10 um) to draw fem's prior curve at: the MAX_CURVES most common (among as common ones,
    those nearest the median), inside fem's range (a surface higher than registered stops probes at the depth
    limit, each at its own nominal depth, some at 0 or above the nominal surface: fem has no force there)."""
    vals, cnt = np.unique(np.round(np.asarray(depth_m, float), 5), return_counts=True)
    ok = (vals > 0) & (vals < fem_deepest_m(prior))
    vals, cnt = vals[ok], cnt[ok]
    if not len(vals):
        return vals
    order = np.lexsort((np.abs(vals - np.median(vals)), -cnt))     # the most common; among equals the most central
    return np.sort(vals[order[:MAX_CURVES]])


def run_figure(prior, loc, meas, *, surrogate=None, truth_stones=(), rounds=None, title: str = "") -> RunFigure:
    """The figure's numbers: ``meas`` and ``loc`` (planner.localize), fem's prior force along the probed stretch at
    each probed depth (the true one the fit found, with its stiffness scale) and, with a stone detected, the ``surrogate``'s contrast of the fitted stone; ``rounds``
    (planner.refine) colour the probes by round; ``truth_stones`` (simulation only) are drawn dashed."""
    W = prior.tissue.width_m * 1e3
    x = meas.x_m * 1e3
    rnd = np.zeros(len(x), int)
    if rounds:
        bounds = np.cumsum([r.n_probes for r in rounds])
        rnd = np.searchsorted(bounds, meas.index - meas.index.min(), side="right")
    xx = np.linspace(max(0.0, x.min() - 1), min(W, x.max() + 1), 200)
    depths, prior_n, fitted_n, contrast_n = [], [], [], []
    # at the true indentations and stiffness the fit found: the nominal depth moved by the fitted surface (a surface
    # 5 mm higher than registered: probes stopped near nominal depth 0 read 150 mN), times the stiffness scale
    nu = loc.nuisance or {}
    off, tilt = (float((nu.get(k) or (0.0,))[0] or 0.0) for k in ("surface_offset_m", "surface_tilt_rad"))
    scale = float((nu.get("stiffness_scale") or (1.0,))[0] or 1.0)
    deepest = 0.99 * fem_deepest_m(prior)
    for dep in curve_depths(prior, meas.depth_m):
        if round(float(np.clip(dep + off, 1e-6, deepest)), 5) in [round(v, 5) for v in depths]:
            continue            # (depth-limited probes beyond fem's deepest: one curve there)
        d = np.clip(dep + off + tilt * (xx * 1e-3 - 0.5 * prior.tissue.width_m), 1e-6, deepest)
        f0 = scale * np.array([recall.force_n(prior, v * 1e-3, float(di)) for v, di in zip(xx, d)])
        c = None
        if surrogate is not None and loc.detected:
            c = scale * np.asarray(surrogate.contrast(xx * 1e-3, d, loc.x_m, loc.depth_m, loc.diameter_m), float)
        depths.append(float(np.clip(dep + off, 1e-6, deepest)))
        prior_n.append(f0)
        fitted_n.append(None if c is None else f0 + c)
        contrast_n.append(c)
    iv = loc.depth_interval_m.get("95") if loc.detected else None
    return RunFigure(
        width_m=prior.tissue.width_m, height_m=prior.tissue.height_m, x_m=np.asarray(meas.x_m),
        force_n=np.asarray(meas.force_n), sigma_n=np.asarray(meas.sigma_n), contrast_n=np.asarray(loc.contrast_n),
        round_of=np.asarray(rnd), curve_x_mm=xx, depths_m=depths, prior_n=prior_n, fitted_n=fitted_n,
        fit_contrast_n=contrast_n, detected=bool(loc.detected), lr=float(loc.lr),
        lr_threshold=float(loc.lr_threshold), peak_x_m=float(loc.peak_x_m), x_est_m=float(loc.x_m),
        depth_est_m=float(loc.depth_m), diameter_m=float(loc.diameter_m),
        sigma_diameter_m=float(loc.sigma_diameter_m), sigma_x_m=float(loc.sigma_x_m),
        sigma_depth_m=float(loc.sigma_depth_m), depth95_m=(float(iv[0]), float(iv[1])) if iv else None,
        truth_stones_m=[(float(s.x_m), float(s.depth_m), float(s.radius_m)) for s in truth_stones], title=title)

