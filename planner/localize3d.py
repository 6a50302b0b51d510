"""Where is the stone in a block? 3D localization from probe measurements and the prior (stone-free) block only.

The 2D localizer's method (planner.localize) over a surface instead of a line:

1. Contrast: each probe's force against the prior block's (planner.tissue_response3d) at the same position and true
   indentation, after the best stiffness scale.
2. Peak: the probe with the largest contrast (at the most common depth), moved to the contrast-weighted centroid of
   the probes within 5 mm of it that show a positive contrast.
3. Fit: the spherical stone (xs, ys, depth, diameter) whose fem contrast (planner.surrogate3d) best explains the
   measurements, by weighted least squares (scipy least_squares; sigma = the probe's noise plus the surrogate's
   model error), jointly with the nuisance the surgeon does not know (issue 14): the tissue's stiffness scale (force
   is proportional to E at a fixed Poisson ratio), the true surface's offset and its tilt about both tissue axes
   (from the contact onsets the driver records, when at least ``MIN_ONSETS`` probes felt contact), the block's
   thickness (a relative change with a Gaussian prior, by default the 2D localizer's ``THICKNESS_SIGMA``; 0: the
   thickness known; the prior's response at three heights, planner.tissue_response3d) and a sensor drift (an offset
   growing with the time since the free-air baseline). Uncertainty: the Jacobian covariance (inflated by chi2/dof
   when above 1), propagated to (x, y, depth, diameter); the x-y covariance gives the uncertainty ellipse.
4. Detection: likelihood ratio LR = chi2_0 - chi2_1 of "stone" against "no stone" (the nuisance alone), reported when
   LR >= ``LR_THRESHOLD3D``. Under "no stone" LR is the maximum over (xs, ys, depth, diameter) of a chi2: one more
   free position than in 2D, so the threshold is higher; the 3D accuracy study measures the false-alarm rate it gives
   (docs/loop3d.md).

Not in 3D (said in docs/loop3d.md): the profile-likelihood depth interval (the Jacobian's sigma is reported).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from fem.contact import STONE_LAYER_MAX
from fem.scene import SceneError
from planner.correct3d import table_error_n
from planner.forkmap import fork_map
from planner.localize import (
    BELOW_BOTTOM,
    CRUSH_PASSES,
    CRUSH_REL_ERR,
    DRIFT_SIGMA_N_PER_S,
    FLOOR_GAP_M,
    MAX_THICKNESS_SIGMA,
    MIN_MEASUREMENTS,
    MIN_ONSETS,
    MIN_THICKNESS_SIGMA,
    MODEL_ABS_ERR_N,
    NEAR_SIDE,
    ONSET_RATIO_MIN,
    ONSET_SIGMA_M,
    SIDE_REACH3D_M,
    SIGMA_BOUND_TOL,
    THICKNESS_SIGMA,
    Localization,
    Measurements,
    _Forward,
    below_bottom,
    dwell_relaxation,
    nuisance_at_bound,
)
from planner.tissue_response3d import PriorResponse3D

LR_THRESHOLD3D = 25.0
PEAK_RADIUS_M = 5e-3
N_AREA_STARTS = 5           # the stone fit's extra candidates: a 5 x 5 grid over the probed area, the surface untilted
SIDE_PASSES = 4             # fem corrections of a stone near a side at most (planner.correct3d; each about a minute)
N_FLAT_STARTS = 2           # (the best two of them start fits, beside the best n_starts around the contrast's peak)
# nuisance parameters, after the stone's (xs [mm], ys [mm], log clearance [log mm], diameter [mm]):
NUISANCE3D = ("drift_mn_per_s", "log_stiffness_scale", "surface_offset_mm", "surface_tilt_x_mrad",
              "surface_tilt_y_mrad", "thickness_change")
NUIS_X_SCALE = np.array([0.1, 0.05, 0.1, 1.0, 1.0, 0.03])
NUIS_LO = np.array([-np.inf, -1.5, -6.0, -200.0, -200.0, -0.25])
NUIS_HI = np.array([np.inf, 1.5, 6.0, 200.0, 200.0, 0.25])
NUISANCE_BOUND_NAMES3D = (None, "stiffness_scale", "surface_offset", "surface_tilt_x", "surface_tilt_y",
                          "thickness_scale")       # at_bound's names (planner.localize.nuisance_at_bound)


def _f(v):
    return None if v is None or not math.isfinite(v) else float(v)


@dataclass
class Localization3D(Localization):
    y_m: float = float("nan")
    sigma_y_m: float = float("inf")
    corr_xy: float = float("nan")            # correlation of the x and y estimates (the ellipse's tilt)
    peak_y_m: float = float("nan")
    fem_correction: dict | None = None       # the table corrected by fem at the fitted stone (planner.correct3d)

    def to_dict(self) -> dict:
        d = super().to_dict()
        d["estimate"]["y_m"] = {"value": _f(self.y_m), "sigma": _f(self.sigma_y_m)}
        d["estimate"]["corr_xy"] = _f(self.corr_xy)
        d["evidence"]["peak_y_m"] = _f(self.peak_y_m)
        d["evidence"]["fem_correction"] = self.fem_correction
        return d

    @property
    def sigma_lateral_m(self) -> float:
        """The larger semi-axis of the 1-sigma uncertainty ellipse in the plane."""
        return float(math.sqrt(max(np.linalg.eigvalsh(self.cov_xy_m2())[-1], 0.0)))

    def cov_xy_m2(self) -> np.ndarray:
        c = self.corr_xy if math.isfinite(self.corr_xy) else 0.0
        sx, sy = self.sigma_x_m, self.sigma_y_m
        return np.array([[sx * sx, c * sx * sy], [c * sx * sy, sy * sy]])


def surrogate_bounds(sur) -> dict:
    b = sur.bounds() if callable(sur.bounds) else sur.bounds
    return {k: tuple(float(v) for v in b[k]) for k in ("xs_m", "ys_m", "s_m", "diam_m")}


class _Forward3D:
    """Forces (and onset and drift residuals) of the prior + nuisance (+ stone) model at the measured probes."""

    def __init__(self, prior, meas: Measurements, surrogate, nuisance: bool,
                 thickness_sigma: float = THICKNESS_SIGMA):
        self.meas, self.sur = meas, surrogate
        self.thickness_sigma = float(thickness_sigma)
        thick = bool(nuisance and self.thickness_sigma > 0)
        self.resp = PriorResponse3D(prior, meas.x_m, meas.y_m, meas.depth_m, thickness=thick)
        self.xc_m = meas.x_m - 0.5 * prior.tissue.width_m
        self.yc_m = meas.y_m - 0.5 * prior.tissue.length_m
        self.on = np.flatnonzero(np.isfinite(meas.onset_m) & np.isfinite(meas.onset_threshold_n)
                                 & (meas.onset_threshold_n > 0))
        enough = nuisance and len(self.on) >= MIN_ONSETS
        self.free = np.array([True, nuisance, enough, enough and np.ptp(meas.x_m[self.on]) > 0.01,
                              enough and np.ptp(meas.y_m[self.on]) > 0.01, thick])
        self.levels = np.asarray(surrogate.levels, float)
        self._memo_tables: dict[str, dict] = {}
        self.table_err_n = None     # the table's error per probe, held fixed (planner.correct3d; None: not used)
        # the stone's share of the force at each contact onset, as in 2D (planner.localize._Forward): its contrast
        # ratio C / P at the prior's onset depth (the table's first level at least)
        self.d_onset = np.full(len(meas), self.levels[0])
        if len(self.on):
            self.d_onset[self.on] = np.clip(self.resp.depth_at_force_m(meas.onset_threshold_n[self.on], self.on,
                                                                       eta=0.0), self.levels[0], self.levels[-1])
        self.p_onset = np.maximum(self.resp.force_n(self.d_onset, eta=0.0)[self.on], 1e-12)

    # the 2D model's memo of its parts (a Jacobian's one-parameter steps repeat most of them): here the prior's force
    # unless the surface or the thickness moves, the contrast when only the scale or the drift does, the onsets'
    # depths unless the scale or the thickness does
    _memo = _Forward._memo

    def depth(self, nu) -> np.ndarray:
        return self.meas.depth_m + 1e-3 * (nu[2] + nu[3] * self.xc_m + nu[4] * self.yc_m)

    def contrast(self, stone, d, eta: float = 0.0) -> np.ndarray:
        """The stone's contrast at true indentations ``d`` (the table's, for the prior's thickness; beyond the
        table's levels scaled like the block's force at the thickness change ``eta``)."""
        xs, ys, dep, D = stone
        dc = np.clip(d, self.levels[0], self.levels[-1])
        C = np.asarray(self.sur.contrast(self.meas.x_m, self.meas.y_m, dc, xs, ys, dep, D), float)
        if self.table_err_n is not None:
            C = C + self.table_err_n
        out = dc != d
        if out.any():
            C = C.copy()
            C[out] *= self.resp.force_n(d, eta=eta)[out] / np.maximum(self.resp.force_n(dc, eta=eta)[out], 1e-12)
        return C

    def forces(self, stone, nu) -> np.ndarray:
        surf = (float(nu[2]), float(nu[3]), float(nu[4]))     # the true indentation depends on the surface only
        eta = float(nu[5])
        d = self._memo("depth", surf, lambda: self.depth(nu))
        F = self._memo("prior", (*surf, eta), lambda: self.resp.force_n(d, eta=eta))
        if stone is not None:
            F = F + self._memo("contrast", (*map(float, stone), *surf, eta), lambda: self.contrast(stone, d, eta))
        return math.exp(nu[1]) * F + nu[0] * 1e-3 * self.meas.tau_s

    def correct(self, error_n) -> None:
        """Add the table's error ``error_n`` (per probe) to every contrast from now on; the remembered parts go."""
        self.table_err_n = np.asarray(error_n, float)
        self._memo_tables.clear()

    def onset_ratio(self, stone) -> np.ndarray:
        """1 + C / P at each contact onset for ``stone`` (1 without one), floored as in 2D."""
        if stone is None or not len(self.on):
            return np.ones(len(self.on))
        xs, ys, dep, D = map(float, stone)
        C = self._memo("onset_contrast", (xs, ys, dep, D), lambda: np.asarray(
            self.sur.contrast(self.meas.x_m, self.meas.y_m, self.d_onset, xs, ys, dep, D), float)[self.on])
        return np.maximum(1.0 + C / self.p_onset, ONSET_RATIO_MIN)

    def extra(self, nu, stone=None) -> np.ndarray:
        """Residuals of the drift's and thickness's priors and of the contact onsets (with ``stone``, its share of
        the force at each onset)."""
        r = [np.array([nu[0] * 1e-3 / DRIFT_SIGMA_N_PER_S])]
        if self.free[5]:
            r.append(np.array([nu[5] / self.thickness_sigma]))
        if self.free[2]:
            on = self.on
            key = (float(nu[1]), float(nu[5])) + (() if stone is None else tuple(map(float, stone)))
            d_thr = self._memo("onset", key, lambda: self.resp.depth_at_force_m(
                self.meas.onset_threshold_n[on] / math.exp(nu[1]) / self.onset_ratio(stone), on, eta=nu[5]))
            pred = d_thr - 1e-3 * (nu[2] + nu[3] * self.xc_m[on] + nu[4] * self.yc_m[on])
            r.append((self.meas.onset_m[on] - pred) / ONSET_SIGMA_M)
        return np.concatenate(r)

    def full(self, v) -> np.ndarray:
        nu = np.zeros(len(NUISANCE3D))
        nu[self.free] = v
        return nu


def _stone(p):
    """(xs_m, ys_m, depth_m, diameter_m) from the fit's parameters (xs_mm, ys_mm, log s_mm, D_mm)."""
    s, D = math.exp(p[2]) * 1e-3, p[3] * 1e-3
    return p[0] * 1e-3, p[1] * 1e-3, s + 0.5 * D, D


def peak_estimate3d(x, y, c, radius_m: float = PEAK_RADIUS_M) -> tuple[float, float, float]:
    """(x, y, contrast) of the contrast's peak: the largest probe's contrast, at the contrast-weighted centroid of
    the probes within ``radius_m`` of it with a positive contrast."""
    k = int(np.argmax(c))
    near = (np.hypot(x - x[k], y - y[k]) <= radius_m) & (c > 0)
    if not near.any():            # no probe shows a positive contrast (healthy-looking tissue): the largest one
        return float(x[k]), float(y[k]), float(c[k])
    w = c[near]
    return float(np.sum(w * x[near]) / np.sum(w)), float(np.sum(w * y[near]) / np.sum(w)), float(c[k])


def _fit_no_stone(fw: _Forward3D, sig, v0=None, workers: int = 1):
    """The best no-stone model (nuisance only): from ``v0`` (or the prior's block) and, with the thickness free, from
    a block thicker and thinner by twice its prior sigma (as in 2D: a thickness far from the prior's is a valley of
    its own)."""
    def resid(v):
        nu = fw.full(v)
        return np.concatenate([(fw.meas.force_n - fw.forces(None, nu)) / sig, fw.extra(nu)])

    def fit(v):
        return least_squares(resid, v, bounds=(NUIS_LO[fw.free], NUIS_HI[fw.free]), x_scale=NUIS_X_SCALE[fw.free],
                             diff_step=1e-5, max_nfev=200)
    starts = [np.zeros(int(fw.free.sum()))] + ([v0] if v0 is not None else [])
    if fw.free[5]:
        for e in (-2 * fw.thickness_sigma, 2 * fw.thickness_sigma):
            nu = np.zeros(len(NUISANCE3D))
            nu[5] = e
            starts.append(nu[fw.free])
    best = None
    for sol in fork_map(fit, starts, workers):
        if best is None or sol.cost < best.cost:
            best = sol
    return best


def localize3d(prior, meas: Measurements, surrogate, *, lr_threshold: float = LR_THRESHOLD3D,
               nuisance: bool = True, n_starts: int = 4, workers: int = 1,
               thickness_sigma: float = THICKNESS_SIGMA, sides: bool = False) -> Localization3D:
    """Detect and locate a spherical stone from ``meas`` given only the ``prior`` (stone-free) block and the
    ``surrogate`` (planner.surrogate3d). ``nuisance``: fit the stiffness scale, the true surface (offset and
    tilts, from the contact onsets) and the block's thickness jointly with the stone (default); False: only the
    drift. ``thickness_sigma``: the prior's relative uncertainty of the block's thickness (1 sigma; 0: known, not
    fitted). ``workers``: the fits' starts on that many processes (planner.forkmap: the same estimate). ``sides``: a
    stone fitted within SIDE_REACH3D_M of a side face is fitted again with the table's error at the fitted stone from
    fem (planner.correct3d: a minute or more per pass); False: it is flagged NEAR_SIDE in ``at_bound`` instead."""
    if prior.stones:
        raise ValueError("localize3d() takes the prior scene (no stones): the localizer must not see the truth")
    if not prior.is_3d:
        raise ValueError("localize3d() takes a 3D block (tissue.length_m); planner.localize handles a 2D section")
    if not (math.isfinite(thickness_sigma) and (thickness_sigma == 0.0 or MIN_THICKNESS_SIGMA * (1 - SIGMA_BOUND_TOL)
                                                 <= thickness_sigma <= MAX_THICKNESS_SIGMA * (1 + SIGMA_BOUND_TOL))):
        raise ValueError(f"thickness_sigma={thickness_sigma}: must be 0 (known) or between {MIN_THICKNESS_SIGMA} and "
                         f"{MAX_THICKNESS_SIGMA}")
    if len(meas) < MIN_MEASUREMENTS + 1:
        raise ValueError(f"need at least {MIN_MEASUREMENTS + 1} probe measurements, got {len(meas)}")
    fw = _Forward3D(prior, meas, surrogate, nuisance, thickness_sigma)
    nf = int(fw.free.sum())
    rel_err = float(getattr(surrogate, "rel_err", 0.02))
    abs_err = float(getattr(surrogate, "abs_err_n", MODEL_ABS_ERR_N))
    sig_a = np.sqrt(meas.sigma_n ** 2 + abs_err ** 2)
    h0 = _fit_no_stone(fw, sig_a, workers=workers)
    nu0 = fw.full(h0.x)
    A = fw.resp.force_n(fw.depth(nu0), eta=nu0[5])[:, None]
    wa = 1.0 / sig_a
    coef = np.linalg.lstsq(A * wa[:, None], meas.force_n * wa, rcond=None)[0]
    contrast = meas.force_n - A @ coef
    dq = np.round(meas.depth_m, 4)
    vals, cnt = np.unique(dq, return_counts=True)
    sel = dq == vals[np.argmax(cnt)]
    px, py, pc = peak_estimate3d(meas.x_m[sel], meas.y_m[sel], contrast[sel])

    sig = np.sqrt(meas.sigma_n ** 2 + (rel_err * np.maximum(contrast, 0.0)) ** 2 + abs_err ** 2)
    w = 1.0 / sig ** 2
    h0 = _fit_no_stone(fw, sig, h0.x, workers)
    chi2_0 = 2.0 * h0.cost
    nu0 = fw.full(h0.x)
    b = surrogate_bounds(surrogate)
    lo = np.array([b["xs_m"][0] * 1e3, b["ys_m"][0] * 1e3, math.log(b["s_m"][0] * 1e3), b["diam_m"][0] * 1e3])
    hi = np.array([b["xs_m"][1] * 1e3, b["ys_m"][1] * 1e3, math.log(b["s_m"][1] * 1e3), b["diam_m"][1] * 1e3])
    nlo, nhi = NUIS_LO[fw.free], NUIS_HI[fw.free]
    H = prior.tissue.height_m * 1e3

    def resid(q):
        nu = fw.full(q[4:])
        stone = _stone(q[:4])
        return np.concatenate([(meas.force_n - fw.forces(stone, nu)) / sig, fw.extra(nu, stone)])

    # starts: a grid of (clearance, diameter) under the peak and around it, the scale and the drift profiled out
    # (linear), the surface as the no-stone fit found it; and a coarser one across the whole probed area with that
    # surface untilted (session 39's review: an off-centre stone in a stiffer block, the no-stone fit's tilts 3 sigma
    # taking its slope, the contrast's peak elsewhere, every start there ending at the bounds: NO STONE, LR 1.2)
    def scored(nu_s, positions, ls_nodes, d_nodes):
        d0 = fw.depth(nu_s)
        P0 = fw.resp.force_n(d0, eta=nu_s[5])
        out = []
        for ls in ls_nodes:
            for D in d_nodes:
                if math.exp(ls) + D > H - FLOOR_GAP_M * 1e3:
                    continue
                for x, y in positions:
                    p = np.array([np.clip(x, lo[0], hi[0]), np.clip(y, lo[1], hi[1]), ls, D])
                    M = np.c_[P0 + fw.contrast(_stone(p), d0, nu_s[5]), meas.tau_s]
                    cf = np.linalg.lstsq(M * np.sqrt(w)[:, None], meas.force_n * np.sqrt(w), rcond=None)[0]
                    out.append((float(np.sum(w * (meas.force_n - M @ cf) ** 2)), p, cf, nu_s))
        return sorted(out, key=lambda t: t[0])
    around = [(px * 1e3 + dx, py * 1e3 + dy) for dx in (-3.0, 0.0, 3.0) for dy in (-3.0, 0.0, 3.0)]
    cands = scored(nu0, around, np.linspace(lo[2], hi[2], 9), np.linspace(lo[3], hi[3], 6))[:n_starts]
    nu_flat = nu0.copy()
    nu_flat[3:5] = 0.0
    if fw.free[3] or fw.free[4]:
        grid = [np.linspace(lo[k], hi[k], N_AREA_STARTS) for k in (0, 1)]
        across = [(x, y) for x in grid[0] for y in grid[1]]
        cands += scored(nu_flat, across, np.linspace(lo[2], hi[2], 5), np.linspace(lo[3], hi[3], 4))[:N_FLAT_STARTS]
    starts = []
    for _, p, cf, nu_s in cands:
        nu = nu_s.copy()
        nu[0] = cf[1] * 1e3
        if fw.free[1] and cf[0] > 0:
            nu[1] = float(np.clip(math.log(cf[0]), NUIS_LO[1] + 1e-6, NUIS_HI[1] - 1e-6))
        starts.append(np.concatenate([p, nu[fw.free]]))

    def fit(q0):
        return least_squares(resid, q0, bounds=(np.concatenate([lo, nlo]), np.concatenate([hi, nhi])),
                             x_scale=np.concatenate([[1.0, 1.0, 0.1, 1.0], NUIS_X_SCALE[fw.free]]), diff_step=1e-4,
                             max_nfev=300)
    best = None
    for sol in fork_map(fit, starts, workers):
        if best is None or sol.cost < best.cost:
            best = sol
    chi2_1 = 2.0 * best.cost
    lr = max(chi2_0 - chi2_1, 0.0)
    # readings the linear model does not cover under the fitted stone: a model error, and the fit again (the 2D
    # localizer's, planner.localize._fit_stone)
    sig_fit = sig
    beyond = np.zeros(len(meas), dtype=bool)
    for _ in range(CRUSH_PASSES):
        now = _beyond_linear_range3d(fw, meas, best.x, prior.indenter.radius_m)
        if np.array_equal(now, beyond):
            break
        beyond = now
        nu_b = fw.full(best.x[4:])
        c_fit = math.exp(nu_b[1]) * fw.contrast(_stone(best.x[:4]), fw.depth(nu_b), nu_b[5])
        sig = np.sqrt(sig_fit ** 2 + np.where(beyond, CRUSH_REL_ERR * np.maximum(c_fit, 0.0), 0.0) ** 2)
        best = fit(best.x)
    # a stone near a side face: the table's error there from fem at the fitted stone, held fixed, and the fit again
    # from there (planner.correct3d); again while the stone moves by more than half its sigma. The detection (LR,
    # chi2 with and without a stone) stays the table's; a stone no tissue holds is not solved (its flags say so)
    corrected = None
    if sides and lr >= lr_threshold and near_side(prior, *_stone(best.x[:4])[:2]):
        passes, q_table, settled, why = [], best.x.copy(), False, ""
        while len(passes) < SIDE_PASSES:
            st = _stone(best.x[:4])
            try:
                err = table_error_n(prior, surrogate, st, meas.x_m, meas.y_m, fw.depth(fw.full(best.x[4:])))
            except SceneError as e:
                why = " ".join(str(e).split())
                break
            fw.correct(err.error_n)
            best = fit(best.x)
            passes.append(err)
            moved = np.abs(np.subtract(_stone(best.x[:4]), st))
            if np.all(moved <= 0.5 * _stone_sigmas(best, nf)):   # (each pass moved it 0.2-0.6 of the one before)
                settled = True
                break
        if passes:
            # the readings beyond the linear range under the corrected stone, and the fit again if they changed
            now = _beyond_linear_range3d(fw, meas, best.x, prior.indenter.radius_m)
            if not np.array_equal(now, beyond):
                beyond = now
                nu_b = fw.full(best.x[4:])
                c_fit = math.exp(nu_b[1]) * fw.contrast(_stone(best.x[:4]), fw.depth(nu_b), nu_b[5])
                sig = np.sqrt(sig_fit ** 2 + np.where(beyond, CRUSH_REL_ERR * np.maximum(c_fit, 0.0), 0.0) ** 2)
                best = fit(best.x)
            shift = np.subtract(_stone(best.x[:4]), _stone(q_table[:4]))
            corrected = {"passes": len(passes), "settled": settled, "solve_s": float(sum(e.solve_s for e in passes)),
                         "largest_error_n": float(np.max(np.abs(passes[-1].error_n))),
                         "last_move_m": {k: float(v) for k, v in zip(("x", "y", "depth", "diameter"), moved)},
                         "shift_from_table_fit_m": {k: float(v) for k, v in zip(("x", "y", "depth", "diameter"),
                                                                                 shift)}}
            if why:
                corrected["stopped"] = why
    q = best.x
    dof = max(len(best.fun) - 4 - nf, 1)
    cov_q, cov = _covariances(best, nf)
    xs, ys, dep, D = _stone(q[:4])
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))

    def corr(i, j):
        return float(cov[i, j] / (sd[i] * sd[j])) if sd[i] > 0 and sd[j] > 0 else float("nan")
    names = ("x", "y", "clearance", "diameter")
    at_bound = [n for n, v, a, z in zip(names, q[:4], lo, hi) if min(v - a, z - v) < 1e-3 * (z - a)]
    detected = bool(lr >= lr_threshold)
    if detected:
        at_bound += nuisance_at_bound(q[4:], fw.free, NUIS_LO, NUIS_HI, NUISANCE_BOUND_NAMES3D)
        if near_side(prior, xs, ys) and not (corrected and corrected["settled"]):   # the table alone is biased
            at_bound.append(NEAR_SIDE)                         # there (or its correction did not settle)
        if below_bottom(dep, D, prior.tissue.height_m, fw.full(q[4:])[5]):
            at_bound.append(BELOW_BOTTOM)
    else:                                # the no-stone fit's (the rejected stone fit's bounds are not the answer's)
        at_bound = nuisance_at_bound(h0.x, fw.free, NUIS_LO, NUIS_HI, NUISANCE_BOUND_NAMES3D)
    nu_1 = fw.full(q[4:])
    # the tissue and sensor unknowns as the accepted model fitted them: with the stone when one is reported, else
    # the no-stone fit (a stone family forced onto healthy tissue would report a scale bent to absorb its contrast)
    if detected:
        nu = nu_1
        var_nu = np.diag(cov_q)[4:]
    else:
        nu = fw.full(h0.x)
        var_nu = np.diag(np.linalg.pinv(h0.jac.T @ h0.jac)) * max(1.0, chi2_0 / max(len(h0.fun) - nf, 1))
    sd_nu = np.zeros(len(NUISANCE3D))
    sd_nu[fw.free] = np.sqrt(np.maximum(var_nu, 0.0))
    k = math.exp(nu[1])
    rel, rel_sd, rel_n = dwell_relaxation(meas)
    nuis = {"stiffness_scale": (k, k * sd_nu[1]), "surface_offset_m": (nu[2] * 1e-3, sd_nu[2] * 1e-3),
            "surface_tilt_x_rad": (nu[3] * 1e-3, sd_nu[3] * 1e-3),
            "surface_tilt_y_rad": (nu[4] * 1e-3, sd_nu[4] * 1e-3),
            "thickness_scale": (1.0 + nu[5], sd_nu[5]), "thickness_prior_sigma": fw.thickness_sigma,
            "sensor_drift_n_per_s": (nu[0] * 1e-3, sd_nu[0] * 1e-3),
            "dwell_relaxation_fraction": (rel, rel_sd), "probes_with_dwell_history": rel_n,
            "contact_onsets_used": int(len(fw.on)) if fw.free[2] else 0,
            "fit": "stone" if detected else "no stone",
            "fixed": ["stiffness_scale" if n == "log_stiffness_scale" else n
                      for n, f in zip(NUISANCE3D, fw.free) if not f]}
    prior_n = k * fw.resp.force_n(fw.depth(nu), eta=nu[5])
    return Localization3D(
        detected=detected, lr=float(lr), lr_threshold=lr_threshold, x_m=xs, y_m=ys, depth_m=dep,
        diameter_m=D, sigma_x_m=float(sd[0]), sigma_y_m=float(sd[1]), sigma_depth_m=float(sd[2]),
        sigma_diameter_m=float(sd[3]), corr_depth_diameter=corr(2, 3), corr_xy=corr(0, 1), chi2_0=float(chi2_0),
        chi2_1=float(chi2_1), dof_1=dof, offset_drift_n_per_s=float(nu[0] * 1e-3), peak_x_m=px, peak_y_m=py,
        peak_contrast_n=pc, at_bound=at_bound, n_probes=len(meas), nuisance=nuis,
        contrast_n=meas.force_n - nu[0] * 1e-3 * meas.tau_s - prior_n, prior_n=prior_n,
        fit_contrast_n=math.exp(nu_1[1]) * fw.contrast((xs, ys, dep, D), fw.depth(nu_1), nu_1[5]),
        n_beyond_linear_range=int(beyond.sum()), chi2_fit=2.0 * float(best.cost), fem_correction=corrected,
        surface_rise_at_stone_m=1e-3 * float(nu[2] + nu[3] * (xs - 0.5 * prior.tissue.width_m)
                                             + nu[4] * (ys - 0.5 * prior.tissue.length_m)))


def _covariances(sol, nf: int) -> tuple[np.ndarray, np.ndarray]:
    """(of the fit's parameters, of (x, y, depth, diameter) in m): the Jacobian's, inflated by chi2/dof when above 1."""
    q = sol.x
    dof = max(len(sol.fun) - 4 - nf, 1)
    cov_q = np.linalg.pinv(sol.jac.T @ sol.jac) * max(1.0, 2.0 * sol.cost / dof)
    G = np.zeros((4, len(q)))
    G[0, 0], G[1, 1], G[2, 2], G[2, 3], G[3, 3] = 1e-3, 1e-3, math.exp(q[2]) * 1e-3, 0.5e-3, 1e-3   # d(x, y, depth, D)/dq
    return cov_q, G @ cov_q @ G.T


def _stone_sigmas(sol, nf: int) -> np.ndarray:
    return np.sqrt(np.maximum(np.diag(_covariances(sol, nf)[1]), 0.0))


def near_side(prior, xs_m: float, ys_m: float) -> bool:
    """Whether a stone centred at (xs_m, ys_m) lies within SIDE_REACH3D_M of a side face of the block."""
    t = prior.tissue
    return min(xs_m, t.width_m - xs_m, ys_m, t.length_m - ys_m) < SIDE_REACH3D_M


def _beyond_linear_range3d(fw: _Forward3D, meas: Measurements, q, tip_radius_m: float) -> np.ndarray:
    """Per reading: whether the stone ``q[:4]`` lies under the tip's footprint with the reading's true indentation
    deeper than STONE_LAYER_MAX of the tissue layer over it (fem.contact3d's rule)."""
    xs, ys, dep, D = _stone(q[:4])
    d = fw.depth(fw.full(q[4:]))
    under = np.hypot(meas.x_m - xs, meas.y_m - ys) < tip_radius_m + 0.5 * D
    return under & (d > STONE_LAYER_MAX * (dep - 0.5 * D))
