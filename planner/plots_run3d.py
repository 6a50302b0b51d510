"""The figure of a 3D run (fig_run.png): ``run_figure3d`` computes what it shows (the fitted stone's contrast along
two sections through the estimate): planner.draw_run3d's ``RunFigure3D``, which ``planner.draw_run3d.draw_run3d``
draws, in the run's process or in a child (``app.figchild``).
"""
from __future__ import annotations

import math

import numpy as np

from planner.draw_run3d import SECTION_HALF_WIDTH_M, RunFigure3D, Section3D


def run_figure3d(prior, loc, meas, *, surrogate, truth_stones=(), region=None, title: str = "") -> RunFigure3D:
    """The figure's numbers: ``meas`` and ``loc`` (planner.localize3d), and along the two sections through the
    estimate (or the contrast's peak) the ``surrogate``'s contrast of the fitted stone (scaled by the fitted
    stiffness) at each indentation level, moved to the true indentation by the fitted surface; ``truth_stones`` (simulation only) are drawn after the fact."""
    c = loc.contrast_n if loc.contrast_n is not None else np.zeros(len(meas))
    cx = loc.x_m if loc.detected else loc.peak_x_m
    cy = loc.y_m if loc.detected else loc.peak_y_m
    nu = loc.nuisance or {}
    k_scale = nu.get("stiffness_scale", (1.0, 0.0))[0]
    # the fitted stone's contrast at the true indentations the fit found (the nominal level moved by the fitted
    # surface: a surface 5 mm higher than registered drew it at 0.5-0.7 mm, 0.2 mN against 3.5 mN measured)
    off, tx, ty = (float((nu.get(k) or (0.0,))[0] or 0.0)
                   for k in ("surface_offset_m", "surface_tilt_x_rad", "surface_tilt_y_rad"))
    sections = []
    for along, fixed in ((0, cy), (1, cx)):
        s = Section3D(along=along, fixed_m=float(fixed))
        pos = meas.x_m if along == 0 else meas.y_m
        other = meas.y_m if along == 0 else meas.x_m
        if math.isfinite(fixed):
            near = np.abs(other - fixed) <= SECTION_HALF_WIDTH_M
            levels = np.unique(np.round(meas.depth_m[near], 4))
            for lev in levels[::-1]:       # one colour per indentation (the coarse grid has two)
                s.levels_m.append(float(lev))
                s.selected.append(near & (np.abs(meas.depth_m - lev) <= 5e-5))
                sx = model = None
                if loc.detected:
                    if region is not None:
                        lo, hi = (region[0], region[1]) if along == 0 else (region[2], region[3])
                    else:
                        lo, hi = pos.min(), pos.max()
                    sx = np.linspace(lo, hi, 200)
                    xs = sx if along == 0 else np.full(len(sx), fixed)
                    ys = np.full(len(sx), fixed) if along == 0 else sx
                    dd = np.clip(lev + off + tx * (xs - 0.5 * prior.tissue.width_m)
                                 + ty * (ys - 0.5 * prior.tissue.length_m), surrogate.levels[0], surrogate.levels[-1])
                    model = k_scale * surrogate.contrast(xs, ys, dd, loc.x_m, loc.y_m, loc.depth_m, loc.diameter_m)
                s.curve_m.append(sx)
                s.curve_n.append(model)
        sections.append(s)
    return RunFigure3D(
        x_m=np.asarray(meas.x_m), y_m=np.asarray(meas.y_m), sigma_n=np.asarray(meas.sigma_n),
        contrast_n=np.asarray(c), sections=sections, detected=bool(loc.detected), x_est_m=float(loc.x_m),
        y_est_m=float(loc.y_m), diameter_m=float(loc.diameter_m), cov_xy_m2=np.asarray(loc.cov_xy_m2()),
        region_m=tuple(float(v) for v in region) if region is not None else None,
        truth_stones_m=[(float(s.x_m), float(s.y_m), float(s.radius_m)) for s in truth_stones], title=title)

