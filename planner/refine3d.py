"""Adaptive refinement over an area: a coarse grid, then probes where they shrink the stone's uncertainty most,
until the fit's 1-sigma uncertainties in x, y and depth are below a target or the probe budget is spent.

As in 2D (planner.refine), every round is planned by the same CasADi planner within the same limits (``plan_round``:
the coarse plan's ``replan`` over the new positions), executed by whatever ``execute(plan, round) -> records`` the
caller hands in, and localized (planner.localize3d) from the prior block and *all* measurements so far; the loop
never sees a true scene.

Where to probe next: the ``n_refine`` positions on a 1 mm grid over the probed region (repeats allowed) that shrink
var(x) + var(y) + var(depth) most, chosen greedily from the Fisher information of (x, y, depth, diameter, stiffness
scale, drift offset, thickness change) at the current estimate (surrogate derivatives by central differences; the
prior's force, the scale's column, taken as its median over the probes so far: the block's prior force varies by
under 2 % over the probed region; the thickness's column, the prior's dF/d eta times the fitted scale, with the
localizer's prior on eta: fem at each measured probe, and over the candidates interpolated from a
``THICKNESS_GRID`` x ``THICKNESS_GRID`` grid at the design's depth, since it varies smoothly over the face).
Without a detected estimate, an even grid around the contrast's peak (a weak candidate, LR above ``WEAK_LR``)
narrows in on it.
"""
from __future__ import annotations

import math
import time

import numpy as np

from core.contracts import MEASURED
from planner.localize import MIN_MEASUREMENTS3D, NEAR_SIDE, SIDE_REACH3D_M, THICKNESS_SIGMA, Measurements
from planner.localize3d import Localization3D, localize3d
from planner.refine import (
    WEAK_LR,
    AdaptiveResult,
    ProbeReach,
    Round,
    caveats,
    no_stone_caveats,
    prior_force,
    probe_reach,
    too_few,
)
from planner.tissue_response3d import prior_and_thickness_slope3d

DESIGN_STEP_M = 1e-3
SHALLOW_FRACTION = 0.6      # every other coarse probe this fraction of the planned depth (coarse_depths)
THICKNESS_GRID = 9          # the design's thickness column over the candidates: from fem on this grid per side


def coarse_depths(depth_m) -> np.ndarray:
    """The coarse raster's depths: the planned ones (deepest within the limits), every other probe (in probing order:
    neighbours differ) pressed only ``SHALLOW_FRACTION`` of it. On a block the planned depth is the same everywhere,
    so with one depth the tissue's stiffness scale and a sensor offset both scale or shift a flat force level and
    cannot be told apart (only the drift's prior separates them: the fitted scale came out 0.80 on healthy tissue,
    a stone's depth 1.2 mm too shallow, on a small test block); two depths give two force levels, whose ratio is the
    prior's, which pins the scale (0.97-0.99 and a 0.5 mm depth error on the same trials)."""
    d = np.asarray(depth_m, float).copy()
    d[1::2] *= SHALLOW_FRACTION
    return d


def grid_around(cx: float, cy: float, half_m: float, n: int, region) -> np.ndarray:
    """About ``n`` positions on an even square grid of half-width ``half_m`` around (cx, cy), inside ``region``
    (x0, x1, y0, y1)."""
    x0, x1, y0, y1 = region
    k = max(int(math.ceil(math.sqrt(n))), 2)
    xs = np.linspace(max(x0, cx - half_m), min(x1, cx + half_m), k)
    ys = np.linspace(max(y0, cy - half_m), min(y1, cy + half_m), k)
    g = np.array([(x, y) for x in xs for y in ys])
    d = np.hypot(g[:, 0] - cx, g[:, 1] - cy)
    return g[np.argsort(d, kind="stable")[:n]]


def _bilinear(gx: np.ndarray, gy: np.ndarray, V: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``V`` (len(gx) x len(gy), on the increasing nodes gx, gy) at (x, y), bilinearly (held at the edges)."""
    def locate(g, v):
        i = np.clip(np.searchsorted(g, v) - 1, 0, len(g) - 2)
        return i, np.clip((v - g[i]) / (g[i + 1] - g[i]), 0.0, 1.0)
    i, tx = locate(gx, np.asarray(x, float))
    j, ty = locate(gy, np.asarray(y, float))
    return ((1 - tx) * (1 - ty) * V[i, j] + tx * (1 - ty) * V[i + 1, j] + (1 - tx) * ty * V[i, j + 1]
            + tx * ty * V[i + 1, j + 1])


def design_positions3d(loc: Localization3D, meas: Measurements, n: int, surrogate, region,
                       depth_m: float | None = None, step_m: float = DESIGN_STEP_M, prior=None,
                       thickness_sigma: float = THICKNESS_SIGMA) -> np.ndarray:
    """``n`` positions (n x 2) chosen one by one to shrink var(x) + var(y) + var(depth) of the estimate most (module
    doc); without a detected, finite estimate an even grid: around a weak candidate's place (the stone fit's x and
    y below the detection threshold) or, without one, the contrast's peak. ``prior``: the prior block, for the
    thickness's column, with the prior ``thickness_sigma`` on it (None or 0: the thickness taken as known)."""
    if not (loc.detected and all(map(math.isfinite, (loc.x_m, loc.y_m, loc.depth_m, loc.diameter_m)))):
        # the candidate rather than the peak: after the no-stone fit (the thickness and the stiffness absorbing a
        # deep stone's broad bump) the contrast's peak can sit in a corner (block3d seed 6 refined one for four
        # rounds and answered NO STONE while round 0's stone fit stood 0.6 mm from the truth)
        cx, cy = ((loc.x_m, loc.y_m) if math.isfinite(loc.x_m) and math.isfinite(loc.y_m) else
                  (loc.peak_x_m, loc.peak_y_m) if math.isfinite(loc.peak_x_m) else
                  (0.5 * (region[0] + region[1]), 0.5 * (region[2] + region[3])))
        cx, cy = min(max(cx, region[0]), region[1]), min(max(cy, region[2]), region[3])    # (the table's patch is
        return grid_around(cx, cy, 8e-3, n, region)                                     # the region today)
    d = float(np.median(meas.depth_m)) if depth_m is None else depth_m
    d = max(d, float(surrogate.levels[0]))           # (most probes stopped above the nominal surface)
    sig = float(np.median(meas.sigma_n))
    th = np.array([loc.x_m, loc.y_m, loc.depth_m, loc.diameter_m])
    P = float(np.median(loc.prior_n)) if loc.prior_n is not None else 0.0
    k_scale = float((loc.nuisance or {}).get("stiffness_scale", (1.0,))[0])

    def jac(x, y, dd, dP=None):
        cols = [np.full(len(x), P) + surrogate.contrast(x, y, dd, *th)]
        for i in range(4):
            h = np.zeros(4)
            h[i] = 2e-5
            cols.append((surrogate.contrast(x, y, dd, *(th + h)) - surrogate.contrast(x, y, dd, *(th - h))) / 4e-5)
        cols.append(np.full(len(x), 1e-3))        # drift offset, in mN
        if dP is not None:
            cols.append(k_scale * dP)             # thickness change
        return np.array(cols).T
    x0, x1, y0, y1 = region
    dP_meas = dP_cand = None
    gx, gy = np.meshgrid(np.arange(x0, x1 + 1e-12, step_m), np.arange(y0, y1 + 1e-12, step_m), indexing="ij")
    cand = np.c_[gx.ravel(), gy.ravel()]
    thick = prior is not None and thickness_sigma > 0
    if thick:
        # a probe stopped above the nominal surface (one higher than registered: a negative nominal depth, which
        # fem refuses; a review's block3d run with the surface 4.5 mm high ended in a traceback after round 0) at
        # the table's shallowest level, as the contrast columns take it
        dP_meas = prior_and_thickness_slope3d(prior, meas.x_m, meas.y_m,
                                              np.maximum(meas.depth_m, surrogate.levels[0]))[1]
        nx, ny = np.linspace(x0, x1, THICKNESS_GRID), np.linspace(y0, y1, THICKNESS_GRID)
        X, Y = np.meshgrid(nx, ny, indexing="ij")
        V = prior_and_thickness_slope3d(prior, X.ravel(), Y.ravel(), d)[1].reshape(X.shape)
        dP_cand = _bilinear(nx, ny, V, cand[:, 0], cand[:, 1])
    Je = jac(meas.x_m, meas.y_m, np.clip(meas.depth_m, surrogate.levels[0], surrogate.levels[-1]),
             dP_meas) / meas.sigma_n[:, None]
    F = Je.T @ Je + 1e-12 * np.eye(Je.shape[1])
    if thick:
        F[-1, -1] += 1.0 / thickness_sigma ** 2
    dd = float(np.clip(d, surrogate.levels[0], surrogate.levels[-1]))
    Jc = jac(cand[:, 0], cand[:, 1], np.full(len(cand), dd), dP_cand) / sig
    Fi = np.linalg.inv(F)
    want = np.array([1, 2, 3])                    # x, y, depth columns
    out = []
    for _ in range(n):
        G = Jc @ Fi
        gain = np.sum(G[:, want] ** 2, axis=1) / (1.0 + np.sum(G * Jc, axis=1))
        k = int(np.argmax(gain))
        out.append(cand[k])
        g = Fi @ Jc[k]
        Fi = Fi - np.outer(g, g) / (1.0 + Jc[k] @ g)
    return np.array(out)


def converged3d(loc: Localization3D, target_m: float, but_side: bool = False) -> bool:
    """Whether the loop may stop at ``loc``; ``but_side``: were it not for its stone's lying near a side."""
    return bool(loc.detected and max(loc.sigma_x_m, loc.sigma_y_m, loc.sigma_depth_m) <= target_m
                and not [b for b in loc.at_bound if not (but_side and b == NEAR_SIDE)])


def adaptive3d(prior, execute, *, coarse_xy_m, plan_round, surrogate, region, budget_probes: int = 100,
               n_refine: int = 16, target_m: float = 5e-4, progress=None, weak_lr: float = WEAK_LR,
               workers: int = 1, thickness_sigma: float = THICKNESS_SIGMA,
               fem_correction: bool = True) -> AdaptiveResult:
    """Run the loop over a block. ``plan_round(xy (n x 2)) -> plan``; ``execute(plan, round_index) -> records``;
    ``region`` (x0, x1, y0, y1): where refinement probes may go (the planner's probed area). ``prior`` has no
    stones. ``workers``: each localization's fits on that many processes (planner.forkmap: the same estimates).
    ``thickness_sigma``: the prior's relative uncertainty of the block's thickness (0: known). ``fem_correction``:
    a round whose stone lies near a side and whose loop would stop there (converged but for that, or the budget
    spent) is localized again with the table corrected by fem at the fitted stone (planner.correct3d); False: the
    stone stays flagged NEAR_SIDE."""
    if prior.stones:
        raise ValueError("adaptive3d() takes the prior scene (no stones)")
    say = progress or (lambda msg: None)
    rounds, meas, loc = [], None, None
    xy = np.asarray(coarse_xy_m, float).reshape(-1, 2)
    used, k, reason = 0, 0, "budget"
    while True:
        t0 = time.perf_counter()
        plan = plan_round(xy)
        recs = execute(plan, k)
        m = Measurements.from_records(recs, plan.motion, statuses=MEASURED)
        used += len(xy)
        meas = m if meas is None else meas.concat(m)
        if len(meas) < MIN_MEASUREMENTS3D:
            loc = Localization3D(detected=False, lr=float("nan"), lr_threshold=float("nan"))
            reason = too_few(len(meas), used, MIN_MEASUREMENTS3D)
            say(f"round {k}: {len(xy)} probes ({used} in all): {reason}")
            break
        loc = localize3d(prior, meas, surrogate, workers=workers, thickness_sigma=thickness_sigma)
        n = min(n_refine, budget_probes - used)
        if fem_correction and NEAR_SIDE in loc.at_bound and (n < 4 or converged3d(loc, target_m, but_side=True)):
            # the answer may be this round's: the stone near a side fitted again with the side's effect (fem)
            say(f"round {k}: the stone lies within {SIDE_REACH3D_M * 1e3:g} mm of a side: fitting it again with the "
                f"side's effect on its contrast (fem at the fitted stone)")
            loc = localize3d(prior, meas, surrogate, workers=workers, thickness_sigma=thickness_sigma, sides=True)
        rounds.append(Round(k, [[float(a), float(b)] for a, b in xy], [float(p.depth_m) for p in plan.probes],
                            len(xy), loc.to_dict(), plan, time.perf_counter() - t0))
        if k == 0:
            reach = probe_reach(plan, prior_force(plan))   # (the coarse plan's: what a re-run's depth limit may be)
        say(f"round {k}: {len(xy)} probes ({used} in all): " + describe3d(loc, reach))
        if converged3d(loc, target_m):
            reason = "target uncertainty reached"
            break
        if not loc.detected and loc.lr < weak_lr:
            reason = "no stone (no candidate worth refining)"
            break
        if n < 4:
            reason = "probe budget spent"
            break
        xy = design_positions3d(loc, meas, n, surrogate, region, prior=prior, thickness_sigma=thickness_sigma)
        k += 1
    return AdaptiveResult(loc, meas, rounds, used, reason)


def describe3d(loc: Localization3D, reach: ProbeReach = ProbeReach()) -> str:
    """A block's localization in one line; ``reach`` as planner.refine.depth_hint takes it."""
    if not loc.detected:
        return (f"no stone (LR {loc.lr:.1f} < {loc.lr_threshold:g}; peak contrast {loc.peak_contrast_n * 1e3:.2f} "
                f"mN)" + no_stone_caveats(loc, 4))
    return (f"stone at x {loc.x_m * 1e3:.2f} +- {loc.sigma_x_m * 1e3:.2f} mm, y {loc.y_m * 1e3:.2f} +- "
            f"{loc.sigma_y_m * 1e3:.2f} mm, depth {loc.depth_m * 1e3:.2f} +- {loc.sigma_depth_m * 1e3:.2f} mm, "
            f"diameter {loc.diameter_m * 1e3:.2f} +- {loc.sigma_diameter_m * 1e3:.2f} mm (LR {loc.lr:.0f})"
            + caveats(loc, reach))
