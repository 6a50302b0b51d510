"""Where is the stone? Localization from probe measurements and the prior (stone-free) scene only.

Inputs are, by construction, what a surgeon has: ``prior`` (a Scene with no stones: ``localize`` refuses one with
stones) and ``Measurements`` (probe positions, reached depths, measured forces and their noise), nothing else.

1. Contrast: measured force minus fem's prediction for the prior tissue at the same position and depth. The side edges
   and the probe depth change the force everywhere (the prior predicts that); a stone is what the prior leaves
   unexplained.
2. Peak: the largest contrast, refined between waypoints by the parabola through it and its neighbours.
3. Fit: the stone (xs, depth, diameter) whose fem contrast (planner.surrogate) best explains the measurements, by
   weighted least squares (scipy least_squares, sigma = sensor noise of each probe's mean plus the surrogate's
   interpolation error), with a nuisance force offset that grows with the time since the force's reference was
   taken (F/T drift: the free-air baseline of the same descent, or the sensor's zeroing; ``Measurements.tau_s``). Uncertainty: the Jacobian covariance (inflated by chi2/dof when above 1),
   propagated to (x, depth, diameter); the depth-diameter correlation is reported (a larger, deeper stone looks like a
   smaller, shallower one: the profile's *width* tells the depth, its *height* then the size).
   The tissue's unknowns are fitted with the stone (``NUISANCE``): stiffness scale, thickness, surface offset and
   tilt (from the contact onsets), and the amplitude a of the prior's own finite-strain correction g(x, d)
   (planner.finite_strain_response: fem's neo-Hookean force of the PRIOR over its linear one, minus 1); the model
   force is scale (prior + contrast) (1 + a g) + drift. Detection keeps a free in both hypotheses; the estimate uses
   it only where it lowers the stone fit's chi2 by more than ``FS_GAIN_MIN`` (times chi2/dof when above 1).
4. Detection: likelihood ratio of "stone" against "no stone" (the nuisance model only): LR = chi2_0 - chi2_1. A stone is
   reported when LR >= ``LR_THRESHOLD``. Under "no stone" with a correct noise model, LR is the maximum over xs of a
   chi2 with ~2-3 dof; the threshold is set from Monte-Carlo runs on healthy tissue (bench/accuracy_study.py reports
   the false-alarm rate it measures; the nominal rate is below 1e-3).
"""
from __future__ import annotations

import copy
import math
import pickle
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from core.arrays import clip
from core.contracts import FILTER_WINDOW, N_ZERO_AVERAGE
from core.peak import parabola_peak
from fem.contact import STONE_LAYER_MAX, surface_model
from planner.finite_strain_response import FiniteStrainRows, prior_finite_strain, unsupported
from planner.forkmap import fork_map
from planner.surrogate import load_surrogate
from planner.tissue_response import PriorResponse

LR_THRESHOLD = 20.0          # detection threshold on chi2_0 - chi2_1 (see module doc)
MODEL_REL_ERR = 0.01         # surrogate interpolation error, relative to the contrast (measured: max 1.4 %, RMS 0.12 %)
MODEL_ABS_ERR_N = 2e-4       # and an absolute floor (N)
FLOOR_GAP_M = 2e-3           # a candidate stone keeps this much tissue below it (the starts; detectability's grid)
N_X_STARTS = 11              # stone starts spread evenly over the table's x range, besides those around the peak

MIN_MEASUREMENTS = 4          # usable probes a localization needs (a stone has 3 parameters)
MIN_MEASUREMENTS3D = 6        # and a 3D block's round (x, y, depth, size, the tissue's scale and drift)


@dataclass
class Measurements:
    """Probe measurements: one entry per probe (SI)."""
    x_m: np.ndarray              # tip position along the surface at the dwell
    depth_m: np.ndarray          # depth reached (below the NOMINAL surface: the tissue pose the plan was made in)
    force_n: np.ndarray          # mean contact force over the dwell
    sigma_n: np.ndarray          # standard error of force_n (sensor noise of the mean and of the zeroing)
    tau_s: np.ndarray            # time from the force's reference (free-air baseline, else the sensor's zeroing)
    #                              to the middle of the dwell (the drift grows with it)
    index: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    onset_m: np.ndarray | None = None         # depth (below the nominal surface) where contact was first felt; NaN
    onset_threshold_n: np.ndarray | None = None   # the true force contact was felt at: the threshold less the
    #                              reading's zero-force offset then and the first crossing's noise bias; NaN
    dwell_start_n: np.ndarray | None = None   # force over the first / last fifth of the dwell (relaxation); NaN
    dwell_end_n: np.ndarray | None = None
    y_m: np.ndarray | None = None             # tip position along a 3D block's length at the dwell (0: a 2D section)

    OPTIONAL = ("onset_m", "onset_threshold_n", "dwell_start_n", "dwell_end_n")
    FIELDS = ("x_m", "depth_m", "force_n", "sigma_n", "tau_s", "index") + OPTIONAL + ("y_m",)

    def __post_init__(self):
        for k in self.OPTIONAL:
            if getattr(self, k) is None:
                setattr(self, k, np.full(len(self.x_m), np.nan))
        if self.y_m is None:
            self.y_m = np.zeros(len(self.x_m))

    def __len__(self):
        return len(self.x_m)

    @staticmethod
    def from_records(records, motion=None, statuses=("ok",)) -> "Measurements":
        """From the driver's probe records (probes.jsonl dicts). A record with a free-air baseline (robot.records:
        the descent's readings >= 1 mm above the surface) gives dwell mean - baseline, whose noise is that of the two
        means (the zeroing's error cancels), and the time between them. Without one: the dwell mean relative to the
        sensor's zeroing, with its 50-sample error; ``motion`` (planfile.Motion) then gives the time from zeroing to
        the dwell, and without it every probe gets the same time (the drift is a plain offset). The contact onset
        and the dwell's first and last fifth are kept when recorded (NaN otherwise)."""
        rows = []
        for r in records:
            if r.status not in statuses or r.force_mean_n is None or r.depth_reached_m is None or r.implausible:
                continue
            x = r.contact_x_m if r.contact_x_m is not None else r.x_m
            d = float(r.depth_reached_m)
            std = r.force_std_n or r.noise_std_n or 0.0
            n = max(int(r.n_samples or 1), 1)
            f = float(r.force_mean_n)
            base = 0.0
            if r.force_baseline_n is not None and r.baseline_to_dwell_s is not None:
                # relative to the free-air baseline of the same descent: the zeroing's error cancels
                base = float(r.force_baseline_n)
                std_b = r.force_baseline_std_n or std
                sig = math.sqrt(std ** 2 / n + std_b ** 2 / max(int(r.n_samples_baseline), 1))
                tau = float(r.baseline_to_dwell_s)
            else:
                sig = math.sqrt(std ** 2 * (1.0 / n + 1.0 / N_ZERO_AVERAGE))
                tau = 1.0 if motion is None else ((motion.approach_height_m + d) / motion.probe_speed_m_s
                                                  + 0.5 * motion.dwell_s)

            # the onset: the FILTERED reading (relative to the sensor's zeroing) first passed the threshold; the true
            # force there is the threshold less what the sensor read at zero force then (the baseline's line at the
            # contact: the drift since the zeroing; a record without it: the baseline) less the first crossing's
            # noise bias
            thr_on = None
            if r.contact_threshold_n is not None:
                zero_f = getattr(r, "force_baseline_at_contact_n", None)
                thr_on = (float(r.contact_threshold_n) - (base if zero_f is None else float(zero_f))
                          - ONSET_BIAS_SIGMAS * float(std if r.noise_std_n is None else r.noise_std_n)
                          / math.sqrt(FILTER_WINDOW))

            def opt(v, minus=0.0):
                return float("nan") if v is None else float(v) - minus
            y = r.contact_y_m if r.contact_y_m is not None else r.y_m
            rows.append((float(x), d, f - base, sig, tau, int(r.index), opt(r.contact_depth_m),
                         opt(thr_on), opt(getattr(r, "force_dwell_start_n", None), base),
                         opt(getattr(r, "force_dwell_end_n", None), base), float(y)))
        rows.sort(key=lambda t: t[:6])
        a = np.array(rows, dtype=float).reshape(-1, 11)
        return Measurements(a[:, 0], a[:, 1], a[:, 2], np.maximum(a[:, 3], 1e-5), a[:, 4], a[:, 5].astype(int),
                            a[:, 6], a[:, 7], a[:, 8], a[:, 9], a[:, 10])

    def concat(self, other: "Measurements") -> "Measurements":
        parts = [np.concatenate([getattr(self, k), getattr(other, k)]) for k in self.FIELDS]
        order = np.argsort(parts[0], kind="stable")
        return Measurements(*[p[order] for p in parts])


@dataclass
class Localization:
    detected: bool
    lr: float                    # chi2_0 - chi2_1
    lr_threshold: float
    x_m: float = float("nan")
    depth_m: float = float("nan")
    diameter_m: float = float("nan")
    sigma_x_m: float = float("inf")
    sigma_depth_m: float = float("inf")
    sigma_diameter_m: float = float("inf")
    corr_depth_diameter: float = float("nan")
    chi2_0: float = float("nan")
    chi2_1: float = float("nan")
    dof_1: int = 0
    offset_drift_n_per_s: float = 0.0
    peak_x_m: float = float("nan")
    peak_contrast_n: float = float("nan")
    at_bound: list = field(default_factory=list)
    n_probes: int = 0
    contrast_n: np.ndarray | None = None       # per probe: measured - prior prediction - fitted offset
    prior_n: np.ndarray | None = None          # per probe: prior prediction
    fit_contrast_n: np.ndarray | None = None   # per probe: the fitted stone's contrast
    depth_interval_m: dict = field(default_factory=dict)   # profile likelihood: {"68": [lo, hi], "95": [lo, hi]}
    nuisance: dict = field(default_factory=dict)   # the tissue and sensor unknowns fitted with the stone (NUISANCE)
    n_beyond_linear_range: int = 0   # readings the linear model does not cover under the fitted stone (CRUSH_REL_ERR)
    chi2_fit: float = float("nan")   # the stone fit's chi2 with its final weights (those readings' model error in
    #                                  them: the poor-fit check's); chi2_1, the LR's, is the first fit's, as chi2_0
    surface_rise_at_stone_m: float = 0.0   # the fitted surface above the nominal one over the stone (offset and tilt;
    #                                  a probe planned d deep there indents d + this)

    def to_dict(self) -> dict:
        def f(v):
            return None if v is None or not math.isfinite(v) else float(v)
        return {"detected": bool(self.detected),
                "estimate": {"x_m": {"value": f(self.x_m), "sigma": f(self.sigma_x_m)},
                             "depth_m": {"value": f(self.depth_m), "sigma": f(self.sigma_depth_m)},
                             "diameter_m": {"value": f(self.diameter_m), "sigma": f(self.sigma_diameter_m)},
                             "corr_depth_diameter": f(self.corr_depth_diameter),
                             "depth_interval_m": {k: [f(a), f(b)] for k, (a, b) in self.depth_interval_m.items()}},
                "evidence": {"likelihood_ratio": f(self.lr), "threshold": f(self.lr_threshold),
                             "chi2_no_stone": f(self.chi2_0), "chi2_stone": f(self.chi2_1), "dof_stone": self.dof_1,
                             "peak_x_m": f(self.peak_x_m), "peak_contrast_n": f(self.peak_contrast_n),
                             "fit_at_bound": list(self.at_bound),
                             "offset_drift_n_per_s": f(self.offset_drift_n_per_s),
                             "readings_beyond_linear_range": int(self.n_beyond_linear_range),
                             "chi2_stone_final": f(self.chi2_fit),
                             "surface_rise_at_stone_m": f(self.surface_rise_at_stone_m)},
                "nuisance": {k: ({"value": f(v[0]), "sigma": f(v[1])} if isinstance(v, tuple) else v)
                             for k, v in self.nuisance.items()},
                "n_probes": self.n_probes}


def prior_force(prior, meas: Measurements) -> np.ndarray:
    """fem's force for the prior (stone-free) tissue at each probe's position and reached depth."""
    m = surface_model(prior)
    W = prior.tissue.width_m
    return np.array([m.force_n(float(min(max(x, 0.0), W)), float(d)) for x, d in zip(meas.x_m, meas.depth_m)])


def peak_estimate(x: np.ndarray, c: np.ndarray) -> tuple[float, float]:
    """Sub-waypoint peak of a contrast profile: the vertex of the parabola through the largest value and its two
    neighbours (in x order; repeated positions averaged). At an end of the raster: that end."""
    xu, inv = np.unique(np.round(np.asarray(x, float), 7), return_inverse=True)
    cu = np.bincount(inv, weights=c) / np.bincount(inv)
    k = int(np.argmax(cu))
    if k == 0 or k == len(xu) - 1:
        return float(xu[k]), float(cu[k])
    return parabola_peak(xu, cu, k - 1, k + 1)


# ---- the forward model: (prior response + stone contrast) x stiffness scale x (1 + a g) + drift, at the true
# indentation; g: the prior's own finite-strain correction (planner.finite_strain_response), a its fitted amplitude
# nuisance parameters, after the stone's (xs [mm], log clearance [log mm], diameter [mm]):
NUISANCE = ("drift_mn_per_s", "log_stiffness_scale", "surface_offset_mm", "surface_tilt_mrad", "thickness_change",
            "finite_strain_amplitude")
NUIS_X_SCALE = np.array([0.1, 0.05, 0.1, 1.0, 0.03, 0.1])
NUIS_LO = np.array([-np.inf, -1.5, -6.0, -200.0, -0.25, 0.0])
NUIS_HI = np.array([np.inf, 1.5, 6.0, 200.0, 0.25, 5.0])
FS_PRIOR_MEAN = 0.5         # prior on the finite-strain amplitude a (0: linear tissue, 1: neo-Hookean with the
FS_PRIOR_SIGMA = 1.0        # prior's parameters): weak, both within 1 sigma; a >= 0 (no tissue softens against the
#                             linear model at finite strain; a free sign let "no stone" mimic a central stone's bump
#                             with a < 0: the paper run's LR fell 1701 -> 1597 against 1600 with the bound)
FS_GAIN_MIN = 9.0           # the stone's estimate uses the finite-strain term when it lowers chi2 by more (see localize)
ONSET_SIGMA_M = 6e-5        # scatter of a probe's contact onset about the model's (measured: 0.042 mm, paper, nano17)
ONSET_BIAS_SIGMAS = 1.25    # the first noisy crossing of the filtered reading comes early: at a true force this many
#                             filtered-noise sigmas (noise_std / sqrt(FILTER_WINDOW)) below the threshold (measured
#                             against the simulator's true force at each onset, nano17, 2 mm/s: 1.20-1.31 on the paper
#                             section and block3d alike; in depth 74 um there, 105-110 um on block3d's sphere)
THICKNESS_SIGMA = 0.06      # prior uncertainty of the thickness (relative, 1 sigma: a uniform +-10 % has 0.058)
MAX_THICKNESS_SIGMA = 0.10  # a 3D block's (planner.localize3d, --thickness-sigma-m) at most: tabulated at 1 -+ 0.1
MIN_THICKNESS_SIGMA = 1e-3  # ... and at least, unless 0 (known): below, its prior's residual eta / sigma overflows the
#                             fit (1e-160 left every sigma 0 and a stone the default prior does not see; 1e-300 raised)
SIGMA_BOUND_TOL = 1e-9      # relative slack on both bounds: a bound printed in m (%g) and typed back is accepted
DRIFT_SIGMA_N_PER_S = 1e-3  # prior on the drift rate (1 sigma): 10x the nano17 datasheet's; with the stiffness scale
#                             free, a constant offset and a larger scale otherwise mimic a central stone's bump
ONSET_RATIO_MIN = 0.5       # 1 + C / P at a contact onset at least (a contrast below -P / 2: not a hard stone's)
FS_CONTRAST_ERR = 0.15      # model error of the stone's contrast per unit finite-strain amplitude (a neo-Hookean tissue's
#                             contrast differs from the linear one times the prior's correction by 4-14 % over the
#                             stone and up to 30-70 % on its flanks at 3-4 mm: bench/contrast_finite_strain.py)
FS_LEAN_PER_M = 300.0       # ... and a correlated part of it, one mode: a neo-Hookean stone's contrast also leans
#                             towards the section's nearer side, by L a g(d) of the linear contrast per FS_LEAN_SPAN_M
#                             from the stone (g: the prior's finite-strain shape), L = k (FS_LEAN_REACH_M - the
#                             stone's distance to that side, and at most k times its distance from the middle): 0 at
#                             the middle, by symmetry (fs_lean). Measured
#                             with fem on the paper section (bench/contrast_finite_strain.py, ten stones 2.5-25 mm from
#                             the middle: docs/mismatch.md): k 0.15-0.8 / mm, 0.15 for deep stones, the most for small shallow
#                             ones; k = 0.3 / mm is the median. Independent per-reading errors average out over many
#                             probes; a lean does not, and it moves x: its effect on the fit is added to the covariance
#                             (_lean_cov)
FS_LEAN_REACH_M = 0.035     # (the table's side effects reach as far: planner.surrogate._grid_xs)
FS_LEAN_SPAN_M = 0.010      # (the mode: L a g(d) C clip((x - xs) / FS_LEAN_SPAN_M, -1, 1): measured to 10-15 mm)
CRUSH_REL_ERR = 0.5         # model error, relative to the stone's contrast, of a reading the linear model does not cover
#                             (the tissue over the stone crushed: see _fit_stone); set by session 45's study (docs/mismatch.md)
CRUSH_PASSES = 3            # refits at most while the fitted stone moves to another set of such readings
MIN_ONSETS = 4              # fewer contact onsets: the surface is taken as the nominal one (offset and tilt fixed)


class _Forward:
    """Forces (and onset and prior residuals) of the prior + nuisance (+ stone) model at the measured probes."""

    def __init__(self, prior, meas: Measurements, surrogate, nuisance: bool, finite_strain: bool | None = None):
        shape = prior_finite_strain(prior) if nuisance and finite_strain is not False else None
        if finite_strain and shape is None:
            raise ValueError(f"finite_strain=True: fem's finite-strain model does not cover this prior "
                             f"({unsupported(prior) or 'nuisance=False'})")
        self.meas, self.sur = meas, surrogate
        self.resp = PriorResponse(prior, meas.x_m)
        self.width_m = prior.tissue.width_m
        self.xc_m = meas.x_m - 0.5 * self.width_m
        self.on = np.flatnonzero(np.isfinite(meas.onset_m) & np.isfinite(meas.onset_threshold_n)
                                 & (meas.onset_threshold_n > 0))
        self.fs: FiniteStrainRows | None = None if shape is None else shape.at(meas.x_m)
        free = [True, nuisance, nuisance and len(self.on) >= MIN_ONSETS,
                nuisance and len(self.on) >= MIN_ONSETS and np.ptp(meas.x_m[self.on]) > 0.01, nuisance,
                self.fs is not None]
        self.free = np.array(free)
        self.levels = getattr(surrogate, "levels", None)
        # g at each contact onset: at the indentation where the prior's force reaches the threshold (0.3-0.8 mm; g is
        # 0.5-3 % there and the fitted stiffness and thickness change it by a fraction of that: held, not re-solved in
        # every evaluation)
        self._memo_tables: dict[str, dict] = {}
        self.g_onset = None
        # the stone's contrast ratio C / P at each contact onset (held at the prior's onset depth, the table's first
        # level at least, where the model takes the contrast to scale like the force): a stone reaches the threshold
        # sooner (the onset model without it put a side stone's onsets 0.11 mm shallow, 2 onset sigmas, and a fitted
        # tilt and offset took that: biases of 3-5 sigma, session 44's review)
        self.d_onset = np.zeros(len(meas))
        if len(self.on):
            d_on = self.resp.depth_at_force_m(meas.onset_threshold_n[self.on], 0.0, self.on)
            if self.fs is not None:
                self.g_onset = FiniteStrainRows(self.fs.rows[self.on], self.fs.depth_m).g(d_on)
            self.d_onset[self.on] = d_on
        if self.levels is not None:
            self.d_onset = clip(self.d_onset, self.levels[0], self.levels[-1])
        self.p_onset = np.maximum(self.resp.force_n(self.d_onset, 0.0)[self.on], 1e-12)

    def stiffening(self, d, nu) -> np.ndarray | float:
        """1 + a g(x, d): the finite-strain factor at each probe's true indentation ``d`` (1 without the term)."""
        if self.fs is None or nu[5] == 0.0:
            return 1.0
        return 1.0 + nu[5] * self.fs.g(d)

    def tissue_force(self, d, nu) -> np.ndarray:
        """The stone-free tissue's force at true indentations ``d``, before the stiffness scale."""
        return self.resp.force_n(d, nu[4]) * self.stiffening(d, nu)

    def depth(self, nu) -> np.ndarray:
        return self.meas.depth_m + 1e-3 * (nu[2] + nu[3] * self.xc_m)

    def contrast(self, stone, d, eta) -> np.ndarray:
        xs, dep, D = stone
        return self.contrast_many(np.array([xs]), dep, D, d, eta)[0]

    def _many(self, d, xs_m, dep: float, D: float) -> np.ndarray:
        if hasattr(self.sur, "contrast_many"):
            return self.sur.contrast_many(self.meas.x_m, d, xs_m, dep, D)
        return np.array([self.sur.contrast(self.meas.x_m, d, x, dep, D) for x in xs_m])

    def contrast_many(self, xs_m: np.ndarray, dep: float, D: float, d, eta) -> np.ndarray:
        """The contrast of stones (depth ``dep``, diameter ``D``) at each of ``xs_m``: (len(xs_m), n probes)."""
        if self.levels is None:
            return self._many(d, xs_m, dep, D)
        dc = clip(d, self.levels[0], self.levels[-1])     # beyond the table: the contrast scales like the force
        C = self._many(dc, xs_m, dep, D)
        out = dc != d
        if out.any():
            C[:, out] *= self.resp.force_n(d, eta)[out] / np.maximum(self.resp.force_n(dc, eta)[out], 1e-12)
        return C

    def _memo(self, table: str, key: tuple, make):
        """``make()``, remembered under ``key`` (the exact parameters it depends on) for the next evaluations: a
        finite-difference Jacobian moves one parameter at a time, so most parts of the model repeat the base point's
        (the contrast when only the scale, drift or finite-strain amplitude moves; the prior's force when only the
        stone does). The same numbers as computing them again, bit for bit. Callers must not modify the result."""
        memo = self._memo_tables.setdefault(table, {})
        v = memo.get(key)
        if v is None:
            if len(memo) >= 64:
                memo.clear()
            v = memo[key] = make()
        return v

    def forces(self, stone, nu) -> np.ndarray:
        surf = (nu[2], nu[3])                   # the true indentation depends on the surface's offset and tilt only
        d = self._memo("depth", surf, lambda: self.depth(nu))
        F = self._memo("prior", (*surf, nu[4]), lambda: self.resp.force_n(d, nu[4]))
        if stone is not None:
            F = F + self._memo("contrast", (*stone, *surf, nu[4]), lambda: self.contrast(stone, d, nu[4]))
        st = self._memo("stiffening", (*surf, nu[5]), lambda: self.stiffening(d, nu))
        return math.exp(nu[1]) * F * st + nu[0] * 1e-3 * self.meas.tau_s

    def extra(self, nu, stone=None) -> np.ndarray:
        """Residuals of the contact onsets (the surface height and the scale; with ``stone``, its contrast at the
        onset) and of the drift and thickness priors."""
        return self._memo("extra", (*nu, self.free.tobytes(), stone), lambda: self._extra(nu, stone))

    def onset_ratio(self, stone) -> np.ndarray:
        """1 + C / P at each contact onset for ``stone`` (1 without one): the stone's share of the force there,
        floored at ONSET_RATIO_MIN."""
        if stone is None or not len(self.on):
            return np.ones(len(self.on))
        xs, dep, D = stone
        C = self._memo("onset_contrast", tuple(stone),
                       lambda: self._many(self.d_onset, np.array([xs]), dep, D)[0][self.on])
        return np.maximum(1.0 + C / self.p_onset, ONSET_RATIO_MIN)

    def onset_ratio_slopes(self, p) -> np.ndarray:
        """d (1 + C / P) / d(xs_mm, log s_mm, D_mm) at each contact onset: (n onsets, 3) (0 where floored)."""
        stone = _stone(p)
        xs, dep, D = stone
        if hasattr(self.sur, "contrast_slopes"):
            S = self.sur.contrast_slopes(self.meas.x_m, self.d_onset, xs, dep, D)[:3, self.on]
            S = np.array([1e-3 * S[0], S[1], 1e-3 * S[2]])
        else:                   # central differences in q
            S = np.zeros((3, len(self.on)))
            for j, h in enumerate((1e-4, 1e-6, 1e-4)):
                qp, qm = np.array(p, float), np.array(p, float)
                qp[j] += h
                qm[j] -= h
                S[j] = (self._many(self.d_onset, np.array([_stone(qp)[0]]), *_stone(qp)[1:])[0][self.on]
                        - self._many(self.d_onset, np.array([_stone(qm)[0]]), *_stone(qm)[1:])[0][self.on]) / (2 * h)
        floored = self.onset_ratio(stone) <= ONSET_RATIO_MIN
        return np.where(floored[:, None], 0.0, (S / self.p_onset).T)

    def _onset_force(self, nu, stone) -> np.ndarray:
        """The prior's force (before the scale) that reaches each onset's threshold: the threshold over the scale,
        the finite-strain factor at the onset and, with ``stone``, its share of the force there."""
        thr = self.meas.onset_threshold_n[self.on] / math.exp(nu[1])
        if self.g_onset is not None:
            thr = thr / (1.0 + nu[5] * self.g_onset)
        return thr if stone is None else thr / self.onset_ratio(stone)

    def _extra(self, nu, stone=None) -> np.ndarray:
        r = [np.array([nu[0] * 1e-3 / DRIFT_SIGMA_N_PER_S])]
        if self.free[4]:
            r.append(np.array([nu[4] / THICKNESS_SIGMA]))
        if self.free[5]:
            r.append(np.array([(nu[5] - FS_PRIOR_MEAN) / FS_PRIOR_SIGMA]))
        if self.free[2]:
            on = self.on
            d_thr = self.resp.depth_at_force_m(self._onset_force(nu, stone), nu[4], on)
            pred = d_thr - 1e-3 * (nu[2] + nu[3] * self.xc_m[on])
            r.append((self.meas.onset_m[on] - pred) / ONSET_SIGMA_M)
        return np.concatenate(r) if r else np.zeros(0)

    def full(self, v) -> np.ndarray:
        nu = np.zeros(len(NUISANCE))
        nu[self.free] = v
        return nu

    # ---- the derivatives, in closed form: every part of the model is an interpolant (planner.surrogate,
    # planner.tissue_response, planner.finite_strain_response), differentiated exactly; one pass (about three
    # evaluations' cost) replaces the finite-difference Jacobian's evaluation per parameter (8-9), and the columns
    # are the derivatives, not a 1e-4 step's secants

    def contrast_slopes(self, stone, d, eta) -> np.ndarray:
        """d/d(xs_m, log s, diameter_m at fixed s, depth, eta) of ``contrast`` at each probe: (5, n probes)."""
        xs, dep, D = stone
        if not hasattr(self.sur, "contrast_slopes"):       # a surrogate without its own: central differences
            return self._contrast_slopes_numeric(stone, d, eta)
        dc = d if self.levels is None else clip(d, self.levels[0], self.levels[-1])
        S = np.zeros((5, len(self.meas)))
        S[:4] = self.sur.contrast_slopes(self.meas.x_m, dc, xs, dep, D)
        out = dc != d
        if out.any():           # beyond the table: C(dc) P(d) / P(dc), dc held at the table's end
            Pd, Pc = self.resp.force_n(d, eta)[out], np.maximum(self.resp.force_n(dc, eta)[out], 1e-12)
            Pd_d, Pd_eta = (a[out] for a in self.resp.force_slopes(d, eta))
            Pc_eta = self.resp.force_slopes(dc, eta)[1][out]
            C = self._many(dc, np.array([xs]), dep, D)[0][out]
            S[:3, out] *= Pd / Pc
            S[3, out] = C * Pd_d / Pc
            S[4, out] = C * (Pd_eta / Pc - Pd * Pc_eta / Pc ** 2)
        return S

    def _contrast_slopes_numeric(self, stone, d, eta) -> np.ndarray:
        xs, dep, D = stone
        s = dep - 0.5 * D
        h, e = 1e-7, 1e-6
        steps = (((xs + h, dep, D), d, eta), ((xs - h, dep, D), d, eta),
                 ((xs, s * math.exp(e) + 0.5 * D, D), d, eta), ((xs, s * math.exp(-e) + 0.5 * D, D), d, eta),
                 ((xs, dep + 0.5 * h, D + h), d, eta), ((xs, dep - 0.5 * h, D - h), d, eta),
                 (stone, d + h, eta), (stone, d - h, eta), (stone, d, eta + e), (stone, d, eta - e))
        C = [self.contrast(*a) for a in steps]
        return np.array([(C[2 * j] - C[2 * j + 1]) / (2 * w) for j, w in enumerate((h, e, h, h, e))])

    def force_jac(self, p, nu) -> np.ndarray:
        """d forces / d(xs_mm, log s_mm, D_mm, *NUISANCE) at each probe for the stone ``_stone(p)`` (None: no stone,
        its columns 0): (n probes, 3 + len(NUISANCE))."""
        surf = (nu[2], nu[3])                   # the parts ``forces`` computed at this point, from its memo
        d = self._memo("depth", surf, lambda: self.depth(nu))
        K = math.exp(nu[1])
        B = self._memo("prior", (*surf, nu[4]), lambda: self.resp.force_n(d, nu[4]))   # before scale and stiffening
        B_d, B_eta = self.resp.force_slopes(d, nu[4])
        g = g_d = 0.0
        if self.fs is not None:
            g, g_d = self.fs.g(d), self.fs.slope(d)
        st = 1.0 + nu[5] * g
        J = np.zeros((len(self.meas), 3 + len(NUISANCE)))
        if p is not None:
            stone = _stone(p)
            B = B + self._memo("contrast", (*stone, *surf, nu[4]), lambda: self.contrast(stone, d, nu[4]))
            S = self.contrast_slopes(stone, d, nu[4])
            J[:, :3] = ((K * st) * np.array([1e-3 * S[0], S[1], 1e-3 * S[2]])).T
            B_d, B_eta = B_d + S[3], B_eta + S[4]
        dF_dd = K * (B_d * st + B * nu[5] * g_d)
        J[:, 3] = 1e-3 * self.meas.tau_s
        J[:, 4] = K * B * st
        J[:, 5] = 1e-3 * dF_dd
        J[:, 6] = 1e-3 * self.xc_m * dF_dd
        J[:, 7] = K * B_eta * st
        J[:, 8] = K * B * g
        return J

    def extra_jac(self, nu, p=None) -> np.ndarray:
        """d extra / d(xs_mm, log s_mm, D_mm, *NUISANCE) with the stone ``_stone(p)`` (None: no stone, its columns
        0): (len(extra), 3 + len(NUISANCE))."""
        stone = None if p is None else _stone(p)
        E = self._extra_jac(nu, stone)
        Es = np.zeros((len(E), 3))
        if p is not None and self.free[2]:   # the onsets' rows, last: d pred / d q = dd_dlf * (-d log ratio / d q)
            on = self.on
            dd_dlf = self.resp.depth_at_force_slopes(self._onset_force(nu, stone), nu[4], on)[0]
            dpred = -(dd_dlf / self.onset_ratio(stone))[:, None] * self.onset_ratio_slopes(p)
            Es[len(E) - len(on):] = -dpred / ONSET_SIGMA_M     # (the residual is onset - pred)
        return np.hstack([Es, E])

    def _extra_jac(self, nu, stone=None) -> np.ndarray:
        """d extra / d NUISANCE: (len(extra), len(NUISANCE))."""
        rows = [np.eye(len(NUISANCE))[0] * 1e-3 / DRIFT_SIGMA_N_PER_S]
        if self.free[4]:
            rows.append(np.eye(len(NUISANCE))[4] / THICKNESS_SIGMA)
        if self.free[5]:
            rows.append(np.eye(len(NUISANCE))[5] / FS_PRIOR_SIGMA)
        if self.free[2]:
            on = self.on
            thr = self._onset_force(nu, stone)
            dlf_da = np.zeros(len(on))
            if self.g_onset is not None:
                dlf_da = -self.g_onset / (1.0 + nu[5] * self.g_onset)
            dd_dlf, dd_deta = self.resp.depth_at_force_slopes(thr, nu[4], on)
            Jo = np.zeros((len(on), len(NUISANCE)))      # d pred / d nu; the residual is -(that) / ONSET_SIGMA_M
            Jo[:, 1] = -dd_dlf
            Jo[:, 2] = -1e-3
            Jo[:, 3] = -1e-3 * self.xc_m[on]
            Jo[:, 4] = dd_deta
            Jo[:, 5] = dd_dlf * dlf_da
            rows.extend(-Jo / ONSET_SIGMA_M)
        return np.array(rows)


def _jac(fw: _Forward, sig, p, nu) -> np.ndarray:
    """d residuals / d(xs_mm, log s_mm, D_mm, *free nuisance) (the stone's columns only with a stone ``p``)."""
    J = np.vstack([-fw.force_jac(p, nu) / sig[:, None], fw.extra_jac(nu, p)])
    cols = 3 + np.flatnonzero(fw.free)
    return J[:, np.concatenate([np.arange(3), cols]) if p is not None else cols]


def _jac_or_fd(jac):
    """The Jacobian least_squares is given: ``jac`` (closed form), or its own finite differences when ``JACOBIAN``
    says so (the previous method, kept to compare against: bench/localize_jacobian.py)."""
    if JACOBIAN not in ("analytic", "2-point"):
        raise ValueError(f"planner.localize.JACOBIAN = {JACOBIAN!r}: 'analytic' or '2-point'")
    return jac if JACOBIAN == "analytic" else "2-point"


JACOBIAN = "analytic"       # or "2-point": scipy's finite differences (diff_step as given at each fit)


@dataclass
class _Fit:
    """A least-squares solution's parts the report uses (scipy's OptimizeResult, or one cut down)."""
    x: np.ndarray
    cost: float
    fun: np.ndarray
    jac: np.ndarray


def _stone(p):
    xs, s, D = p[0] * 1e-3, math.exp(p[1]) * 1e-3, p[2] * 1e-3
    return xs, s + 0.5 * D, D


def _fit_no_stone(fw: _Forward, sig, v0=None, workers: int = 1):
    """The best no-stone model (nuisance only): from ``v0`` (or the prior's tissue) and from thicker and thinner
    starts, so that a local minimum cannot make "no stone" look worse than it is (that would inflate the LR).
    ``workers``: the starts' fits on that many processes (planner.forkmap; the same result)."""
    def resid(v):
        nu = fw.full(v)
        return np.concatenate([(fw.meas.force_n - fw.forces(None, nu)) / sig, fw.extra(nu)])

    def jac(v):
        return _jac(fw, sig, None, fw.full(v))
    starts = [np.zeros(len(NUISANCE))] + ([fw.full(v0)] if v0 is not None else [])
    if fw.free[4]:
        starts += [np.array([0, 0, 0, 0, e, 0]) for e in (-2 * THICKNESS_SIGMA, 2 * THICKNESS_SIGMA)]
    if fw.free[5]:          # and the prior's tissue as a neo-Hookean solid
        starts.append(np.array([0, 0, 0, 0, 0, 1.0]))
    def fit(nu):
        return least_squares(resid, nu[fw.free], jac=_jac_or_fd(jac), bounds=(NUIS_LO[fw.free], NUIS_HI[fw.free]),
                             x_scale=NUIS_X_SCALE[fw.free], diff_step=1e-5, max_nfev=200)
    best = None
    for sol in fork_map(fit, starts, workers):
        if best is None or sol.cost < best.cost:
            best = sol
    return best


def _scale_and_drift(a: np.ndarray, tau: np.ndarray, f: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each row a_i of ``a``: the weighted least squares f ~ c0 a_i + c1 tau (weights ``w``), by its 2 x 2 normal
    equations, all rows at once: (chi2 per row, (c0, c1) per row)."""
    wa = w * a
    saa, sat, saf = (wa * a).sum(1), wa @ tau, wa @ f
    stt, stf = float(w @ (tau * tau)), float(w @ (tau * f))
    det = saa * stt - sat * sat
    ok = det > 1e-12 * saa * stt
    with np.errstate(divide="ignore", invalid="ignore"):
        coef = np.c_[(saf * stt - sat * stf) / det, (saa * stf - sat * saf) / det]
    sw = np.sqrt(w)
    for i in np.flatnonzero(~ok):        # (next to) collinear with tau, or no force at all: the minimum-norm answer
        coef[i] = np.linalg.lstsq(np.c_[a[i], tau] * sw[:, None], f * sw, rcond=None)[0]
    r = f - coef[:, :1] * a - coef[:, 1:] * tau
    return (w * r * r).sum(1), coef


def _depth_held(resid, jac, d_mm: float):
    """The stone fit's residuals and their Jacobian in p = (xs_mm, D_mm, *nuisance), the stone's depth held at
    ``d_mm`` (its clearance s = d - D/2, at least 1 um)."""
    def q(p):
        return np.concatenate([[p[0], math.log(max(d_mm - 0.5 * p[1], 1e-3)), p[1]], p[2:]])

    def r(p):
        return resid(q(p))

    def r_jac(p):
        J = jac(q(p))
        s = d_mm - 0.5 * p[1]
        dls_dD = -0.5 / s if s > 1e-3 else 0.0
        return np.column_stack([J[:, 0], J[:, 2] + dls_dD * J[:, 1], J[:, 3:]])
    return r, r_jac


def _depth_profile(resid, jac, q, lo, hi, dep, sd, chi2_min, scale, H_mm, nlo, nhi, n: int = 25,
                   workers: int = 1) -> dict:
    """Profile likelihood of the depth: chi2 minimised over (x, diameter, nuisance) with the depth held at each of
    ``n`` values; the 68 % / 95 % intervals are where chi2 - chi2_min <= 1 / 4 (times the chi2/dof inflation).
    ``workers``: the depths' fits on that many processes (planner.forkmap; the same intervals)."""
    d_hat = dep * 1e3
    w = min(max(4 * sd * 1e3, 2.0), 20.0)
    grid = np.linspace(max(d_hat - w, math.exp(lo[1]) + lo[2] / 2), min(d_hat + w, H_mm - 2.0), n)
    grid = np.unique(np.append(grid, d_hat))
    def chi2_at(d):
        r, r_jac = _depth_held(resid, jac, d)
        D0 = float(np.clip(q[2], lo[2], hi[2]))
        dlo, dhi = max(lo[2], 2 * (d - math.exp(hi[1]))), min(hi[2], 2 * (d - math.exp(lo[1])))
        if dhi - dlo <= 2e-6:          # the diameter has (next to) no room at this depth
            return np.inf
        lb, ub = np.concatenate([[lo[0], dlo], nlo]), np.concatenate([[hi[0], dhi], nhi])
        x0 = np.concatenate([[q[0], float(np.clip(D0, dlo + 1e-6, dhi - 1e-6))], q[3:]])
        # the fit's optimum may sit on (or, by round-off, a hair beyond) a bound that this depth's box moved: start
        # inside (found by the mismatch study: "Initial guess is outside of provided bounds")
        sol = least_squares(r, np.clip(x0, lb, ub), jac=_jac_or_fd(r_jac), bounds=(lb, ub), diff_step=1e-4,
                            max_nfev=200)
        return 2 * sol.cost
    prof = np.array(fork_map(chi2_at, grid, workers))
    # at the estimate's own depth the fit itself is a point of the profile: its chi2 at most (a held fit there may
    # find none: an estimate with the smallest diameter at the smallest clearance leaves the diameter no room, and
    # the interval was built around the next depth, excluding the estimate; session 50's review, a 30 mm section)
    k_hat = int(np.argmin(np.abs(grid - d_hat)))
    prof[k_hat] = min(prof[k_hat], chi2_min)
    base = min(chi2_min, prof.min())
    out = {}
    k0 = int(np.argmin(prof))
    for key, level in (("68", 1.0), ("95", 4.0)):
        lev = base + level * scale
        ends = []
        for step in (-1, 1):       # walk out from the minimum; interpolate the crossing
            k = k0
            while 0 <= k + step < len(grid) and prof[k + step] <= lev:
                k += step
            if 0 <= k + step < len(grid) and np.isfinite(prof[k + step]):
                t = (lev - prof[k]) / (prof[k + step] - prof[k])
                ends.append(grid[k] + t * (grid[k + step] - grid[k]))
            else:
                ends.append(grid[k])      # the end of the searched range (or the table's)
        out[key] = (float(min(ends) * 1e-3), float(max(ends) * 1e-3))
    return out


SIDE = "side"      # at_bound's entry for a fitted stone that would cross the section's side
NEAR_SIDE = "near side"     # ... and for a block's stone within SIDE_REACH3D_M of a side face (planner.localize3d)
BELOW_BOTTOM = "below the bottom"   # ... and for a stone reaching below the tissue's bottom (as its thickness is fitted)
SIDE_REACH3D_M = 0.022      # The 3D table (planner.surrogate3d) takes every stone's contrast as a stone's away from the
#                             block's side faces. On a 50 x 50 x 30 mm block (a 10 mm stone 12 mm deep, y at the
#                             middle; docs/localize.md "A stone near a block's side"), against direct fem: RMS 2.5-3.1 % of the peak
#                             and up to 12-19 % at single probes (between the stone and the side) with its centre 8-13
#                             mm from a side, 1.5-1.7 % / 6-7 % at 18 mm, 0.9-1.4 % / 3-4 % at 25 mm; and runs with a
#                             noise-free sensor (the table's bias alone): the worst of x, depth and diameter 14, 9.6,
#                             4.7 and 3.7 sigma off with the stone 13, 15, 18 and 21 mm from a side, 1.4 sigma at 25
STONE_PARAMS = ("x", "y", "clearance", "diameter")     # at_bound's entries for the stone's own parameters
# at_bound's names for the nuisance parameters (NUISANCE's order; None: unbounded)
NUISANCE_BOUND_NAMES = (None, "stiffness_scale", "surface_offset", "surface_tilt", "thickness_scale",
                        "finite_strain_amplitude")


def nuisance_at_bound(v, free, lo, hi, names) -> list[str]:
    """The free nuisance parameters ``v`` (of ``names``, masked by ``free``) within 1e-3 of their range from a bound
    (the fit stretched the tissue or the surface as far as it may, so the stone's estimate may be pulled off with
    it; a session-47 review: a stone 7 mm from the side reported 32 mm away, the thickness at its bound). The
    finite-strain amplitude's lower bound (0, linear tissue) is where it belongs, not a stretch."""
    out = []
    for x, a, z, n in zip(v, np.asarray(lo)[free], np.asarray(hi)[free], np.asarray(names, dtype=object)[free]):
        if n is None or not (math.isfinite(a) and math.isfinite(z)):
            continue
        tol = 1e-3 * (z - a)
        if z - x < tol or (x - a < tol and n != "finite_strain_amplitude"):
            out.append(n)
    return out


def crosses_side(x_m: float, diameter_m: float, width_m: float) -> bool:
    """Whether a stone of ``diameter_m`` centred at ``x_m`` would reach a side of a section ``width_m`` wide: no
    tissue holds it there, and a section under 60 mm has its table's entries there extrapolated, not fem's
    (planner.surrogate._fill_sideways)."""
    return x_m - diameter_m / 2 <= 0.0 or x_m + diameter_m / 2 >= width_m


def below_bottom(depth_m: float, diameter_m: float, height_m: float, thickness_change: float) -> bool:
    """Whether a stone reaches below the tissue's bottom, the tissue ``height_m`` thick times 1 + the fitted
    ``thickness_change``: no tissue holds it there, and the table's entries there are extrapolated (a session-54
    review: a 4 mm stone fitted 36.7 mm deep in 35 mm tissue, unflagged)."""
    return depth_m + 0.5 * diameter_m > height_m * (1.0 + thickness_change)


def dwell_relaxation(meas: Measurements) -> tuple[float, float, int]:
    """The fraction the force falls from the dwell's first fifth to its last (value, standard error, probes used),
    over the probes whose dwell force is well above the noise; (nan, nan, 0) without dwell histories."""
    a, b = meas.dwell_start_n, meas.dwell_end_n
    ok = np.isfinite(a) & np.isfinite(b) & (a > 20 * meas.sigma_n)
    if ok.sum() < 2:
        return float("nan"), float("nan"), int(ok.sum())
    r = 1.0 - b[ok] / a[ok]
    return float(np.mean(r)), float(np.std(r, ddof=1) / math.sqrt(ok.sum())), int(ok.sum())


def localize(prior, meas: Measurements, surrogate=None, *, lr_threshold: float = LR_THRESHOLD,
             model_rel_err: float = MODEL_REL_ERR, profile: bool = False, nuisance: bool = True,
             finite_strain: bool | None = None, workers: int = 1) -> Localization:
    """Detect and locate a stone from ``meas`` given only the ``prior`` (stone-free) scene. ``profile``: also the
    profile-likelihood interval of the depth (``depth_interval_m``), honest where the Jacobian's is not (a deep
    stone's depth is strongly non-Gaussian: deeper-and-bigger is hard to rule out). ``nuisance``: fit the tissue's
    stiffness scale, thickness and true surface (offset and tilt, from the contact onsets) jointly with the stone
    (default); False: the prior's tissue and the nominal surface are taken as true (only the drift is fitted).
    ``finite_strain``: with ``nuisance``, fit the amplitude of the prior's finite-strain correction (the tissue
    may be a neo-Hookean solid, or any blend towards the linear one: planner.finite_strain_response); None (default):
    whenever fem's finite-strain model covers the prior (2D plane strain, a rigid-treated tip), False: never, True:
    ValueError when it does not cover it."""
    if prior.stones:
        raise ValueError("localize() takes the prior scene (no stones): the localizer must not see the truth")
    if len(meas) < MIN_MEASUREMENTS:
        raise ValueError(f"need at least {MIN_MEASUREMENTS} probe measurements, got {len(meas)}")
    if surrogate is None:
        surrogate = load_surrogate(prior)
    key = pickle.dumps((prior, [getattr(meas, k) for k in Measurements.FIELDS], lr_threshold, model_rel_err,
                        nuisance, finite_strain, JACOBIAN))
    last = _LAST_FIT.get("fit")
    if last is not None and last[0] == key and last[1] is surrogate:
        loc, profile_args = last[2]        # the same fit again (the run's last round, then its final report)
    else:
        # on a copy: the stored fit's profile reads the measurements later, whatever the caller does to its arrays
        meas = Measurements(**{k: np.array(getattr(meas, k)) for k in Measurements.FIELDS})
        loc, profile_args = _fit_stone(prior, meas, surrogate, lr_threshold, model_rel_err, nuisance, finite_strain,
                                       workers)
        _LAST_FIT["fit"] = (key, surrogate, (loc, profile_args))
    loc = copy.deepcopy(loc)
    if profile:
        loc.depth_interval_m = _depth_profile(*profile_args, workers=workers)
    return loc


# The last fit: the run localizes its last round's measurements, then the same ones again for the final report with
# the depth's profile; the second call takes the fit (the same numbers: a deterministic function of its inputs, which
# the key holds in full, and the same surrogate object) and adds the profile.
_LAST_FIT: dict = {}


def _fit_stone(prior, meas: Measurements, surrogate, lr_threshold: float, model_rel_err: float, nuisance: bool,
               finite_strain: bool | None, workers: int = 1) -> tuple[Localization, tuple]:
    """The fit and its report without the depth's profile; and the profile's arguments."""
    fw = _Forward(prior, meas, surrogate, nuisance, finite_strain)
    nf = int(fw.free.sum())
    sig_a = np.sqrt(meas.sigma_n ** 2 + MODEL_ABS_ERR_N ** 2)
    h0 = _fit_no_stone(fw, sig_a, workers=workers)
    nu0 = fw.full(h0.x)
    # the contrast for the peak and the model-error allowance: against the prior's thickness on the fitted surface
    # (and the fitted finite-strain factor), with only a scale and the drift fitted (linear): a no-stone fit's
    # thickness can take a central stone's bump and move the contrast's peak to an end
    nu_pk = nu0.copy()
    nu_pk[4] = 0.0
    A = fw.tissue_force(fw.depth(nu_pk), nu_pk)[:, None]
    wa = 1.0 / sig_a
    coef = np.linalg.lstsq(A * wa[:, None], meas.force_n * wa, rcond=None)[0]
    contrast = meas.force_n - A @ coef       # (no drift offset here: with the scale it mimics a central bump)
    # peak on the probes of the most common depth (the contrast grows with depth)
    dq = np.round(meas.depth_m, 4)
    vals, cnt = np.unique(dq, return_counts=True)
    sel = dq == vals[np.argmax(cnt)]
    px, pc = peak_estimate(meas.x_m[sel], contrast[sel])

    # noise + model error (relative to the contrast seen, so fixed during the fit)
    sig = np.sqrt(meas.sigma_n ** 2 + (model_rel_err * np.maximum(contrast, 0.0)) ** 2 + MODEL_ABS_ERR_N ** 2)
    w = 1.0 / sig ** 2
    h0 = _fit_no_stone(fw, sig, h0.x, workers)
    chi2_0 = 2.0 * h0.cost
    nu0 = fw.full(h0.x)
    free0 = fw.free.copy()           # (the stone fit may fix the finite-strain amplitude later: h0.x is over these)
    b = surrogate.bounds
    lo = np.array([b["xs_m"][0] * 1e3, math.log(b["s_m"][0] * 1e3), b["diam_m"][0] * 1e3])
    hi = np.array([b["xs_m"][1] * 1e3, math.log(b["s_m"][1] * 1e3), b["diam_m"][1] * 1e3])
    nlo, nhi = NUIS_LO[fw.free], NUIS_HI[fw.free]
    H = prior.tissue.height_m * 1e3

    def resid(q):     # q = (xs_mm, log s_mm, D_mm, *free nuisance)
        nu = fw.full(q[3:])
        stone = _stone(q[:3])
        return np.concatenate([(meas.force_n - fw.forces(stone, nu)) / sig, fw.extra(nu, stone)])

    def jac(q):
        return _jac(fw, sig, q[:3], fw.full(q[3:]))

    # starts: the table's (s, D) nodes around the peak; scale and drift profiled out (linear), the surface as H0
    # fitted it (the onsets pin it), the thickness at H0's value and at the prior's (a big stone drives H0's
    # thickness and scale far off: starting only there, the stone fit can stay in that valley)
    nu_prior = nu0.copy()
    nu_prior[4] = 0.0
    nu_nominal = np.zeros(len(NUISANCE))
    nu_nominal[5] = nu0[5]
    # and H0's tissue taken as linear (a = 0): a stone's bump can drive H0's finite-strain amplitude up (it stiffens
    # the deep probes as the stone does), and starts holding that amplitude can all stay in a valley of a wrong
    # stone (the mismatch study v6's trial 43: a 9.5 mm stone 7 mm from the side of neo-Hookean tissue, H0's a 4.1;
    # every start's fit ended at a 17 mm stone 42 mm deep, 41 mm away, chi2 409; from a = 0 the fit polished with a
    # free ends at the stone, chi2 19, and the fit with a held at 0 scores 85 there)
    nu_linear = nu0.copy()
    nu_linear[5] = 0.0
    starts = [(nu0, 4)]
    for nu_s in (nu_prior, nu_nominal, nu_linear):    # and the prior's tissue on the nominal surface
        if not any(np.allclose(nu_s, a) for a, _ in starts):
            starts.append((nu_s, 2))
    # the candidates' positions: around the peak, and across the whole section (a big deep stone near an end under
    # a tilted surface: the no-stone fit's tilt takes its slope, the contrast then peaks at the other end, and starts
    # only there end at the bounds with chi2 above the no-stone fit's; the mismatch study found 5 in 100)
    xs_peak = np.unique(np.clip(px * 1e3 + np.array([-3.0, 0.0, 3.0]), lo[0], hi[0]))
    xs_c = np.unique(np.r_[xs_peak, np.linspace(lo[0], hi[0], N_X_STARTS)])
    peak_set = set(xs_peak.tolist())     # (a set: np.isin on each of some 2,000 candidates took 50 ms a run)
    # the starts' fits hold the finite-strain amplitude at their start's value (H0's: it is close to the answer, and
    # with it free each fit took 1.6 times the iterations); the best is then polished with it free
    held = bool(fw.free[5])         # a is the last free nuisance parameter
    k_fit = len(lo) + len(nlo) - int(held)
    tasks = []                      # (q0, the held amplitude)
    for nu_s, n_starts in starts:
        d0 = fw.depth(nu_s)
        P0 = fw.resp.force_n(d0, nu_s[4])
        st0 = fw.stiffening(d0, nu_s)
        rows, params = [], []
        for ls in np.log(surrogate.s * 1e3):
            for D in surrogate.diam * 1e3:
                if math.exp(ls) + D > H - FLOOR_GAP_M * 1e3:
                    continue
                _, dep_c, D_c = _stone((0.0, ls, D))
                rows.append(fw.contrast_many(xs_c * 1e-3, dep_c, D_c, d0, nu_s[4]))   # (n_xc, n probes)
                params.extend(np.array([xc, ls, D]) for xc in xs_c)
        chi2s, coefs = _scale_and_drift((P0 + np.vstack(rows)) * st0, meas.tau_s, meas.force_n, w)
        cands = sorted(zip(chi2s.tolist(), params, coefs), key=lambda t: t[0])
        chosen = cands[:n_starts]           # (the candidates are distinct: xs_c is unique)
        # on H0's surface, the best candidate at the contrast's peak starts a fit whatever its rank: across the
        # whole section, a thickness and tilt trade can rank a central stone's candidates above every one at the
        # peak (the neo-Hookean study's trial 16: a 4.2 mm stone 6 mm deep at the end, its candidates chi2 43
        # against 27 in the middle, its fit 35 against 44 there: LR 8.5 -> 18.9)
        at_peak = [c for c in cands if float(c[1][0]) in peak_set]
        if nu_s is nu0 and at_peak and not any(float(c[1][0]) in peak_set for c in chosen):
            chosen.append(at_peak[0])
        for chi2, p, coef in chosen:
            nu = nu_s.copy()
            nu[0] = coef[1] * 1e3
            if fw.free[1] and coef[0] > 0:
                nu[1] = float(np.clip(math.log(coef[0]), NUIS_LO[1] + 1e-6, NUIS_HI[1] - 1e-6))
            tasks.append((np.concatenate([p, nu[fw.free]]), nu[5]))

    def fit_start(task):
        q0, a = task

        def resid_held(qh):
            return resid(np.append(qh, a)) if held else resid(qh)

        def jac_held(qh):
            return jac(np.append(qh, a))[:, :-1] if held else jac(qh)
        return least_squares(resid_held, q0[:k_fit], jac=_jac_or_fd(jac_held),
                             bounds=(np.concatenate([lo, nlo])[:k_fit], np.concatenate([hi, nhi])[:k_fit]),
                             x_scale=np.concatenate([[1.0, 0.1, 1.0], NUIS_X_SCALE[fw.free]])[:k_fit],
                             diff_step=1e-4, max_nfev=300)
    best, a_best = None, 0.0
    for sol, (_, a) in zip(fork_map(fit_start, tasks, workers), tasks):
        if best is None or sol.cost < best.cost:
            best, a_best = sol, a
    fs_gain = float("nan")
    if held:
        best = least_squares(resid, np.append(best.x, a_best), jac=_jac_or_fd(jac),
                             bounds=(np.concatenate([lo, nlo]), np.concatenate([hi, nhi])),
                             x_scale=np.concatenate([[1.0, 0.1, 1.0], NUIS_X_SCALE[fw.free]]), diff_step=1e-4,
                             max_nfev=300)
    chi2_1 = 2.0 * best.cost
    lr = max(chi2_0 - chi2_1, 0.0)      # "no stone" is the limit of the stone family: LR >= 0 (the optimizer's
    #                                    miss of that limit, a fraction of a unit, is not evidence either way)
    # The detection above has the finite-strain term in both hypotheses (a healthy neo-Hookean tissue is no stone).
    # The stone's estimate uses it only where the data warrant it: where the stone fit with a free is better than
    # with a = 0 by more than FS_GAIN_MIN (times chi2/dof when above 1); else a is fixed at 0 (in linear tissue a
    # free a trades against a weak or near-side stone's depth: the mismatch study's linear truths moved by up to 6 mm)
    fit = best
    a_fit = (0.0, 0.0)                  # the amplitude of the fit with a free (reported whichever fit is used)
    if held:
        dof_a = max(len(best.fun) - 3 - nf, 1)
        Jb = best.jac
        if JACOBIAN != "analytic" and best.active_mask[-1] != 0:   # at a bound, scipy's finite differences
            #                           return that column zeroed: a one-sided difference inward
            Jb = Jb.copy()
            step = 1e-3 * best.active_mask[-1] * -1.0
            Jb[:, -1] = (resid(np.append(best.x[:-1], best.x[-1] + step)) - best.fun) / step
        cov_a = np.linalg.pinv(Jb.T @ Jb) * max(1.0, chi2_1 / dof_a)
        a_fit = (float(best.x[-1]), float(math.sqrt(max(cov_a[-1, -1], 0.0))))
        fit = least_squares(lambda qh: resid(np.append(qh, 0.0)), best.x[:-1],
                            jac=_jac_or_fd(lambda qh: jac(np.append(qh, 0.0))[:, :-1]),
                            bounds=(np.concatenate([lo, nlo])[:-1], np.concatenate([hi, nhi])[:-1]),
                            x_scale=np.concatenate([[1.0, 0.1, 1.0], NUIS_X_SCALE[fw.free]])[:-1],
                            diff_step=1e-4, max_nfev=300)
        fs_gain = 2.0 * (fit.cost - best.cost)
        if fit.cost < best.cost:         # a = 0 lies in the free family: its better fit is the family's chi2
            chi2_1 = 2.0 * fit.cost
            lr = max(chi2_0 - chi2_1, 0.0)
        if fs_gain > FS_GAIN_MIN * max(1.0, chi2_1 / dof_a):
            fit = best
        else:                    # a = 0 from here on: fixed (the covariance, the profile and the report)
            fw.free[5] = False
            nf -= 1
            nlo, nhi = NUIS_LO[fw.free], NUIS_HI[fw.free]
    # readings the linear model does not cover under the fitted stone (the tip within STONE_LAYER_MAX of the tissue
    # layer over it: fem refuses them, the table and a simulated truth continue the force with a power law): an
    # error of CRUSH_REL_ERR of the stone's contrast there, and the fit again from here (fixed, as the contrast's
    # allowance is)
    # (again while the refit moves the stone to another set of such readings: CRUSH_PASSES at most)
    # and where the fit takes the tissue as stiffening at finite strain (amplitude a): an error of FS_CONTRAST_ERR a of
    # the contrast at every reading (the stone's own finite strain, which the prior's correction does not hold)
    sig_fit = sig
    beyond = np.zeros(len(meas), dtype=bool)
    fs_allow = FS_CONTRAST_ERR * max(float(fw.full(fit.x[3:])[5]), 0.0) if fw.free[5] else 0.0
    for k in range(CRUSH_PASSES):
        now = _beyond_linear_range(fw, fit.x, prior.indenter.radius_m)
        if np.array_equal(now, beyond) and not (k == 0 and fs_allow > 0.0):
            break
        beyond = now
        nu = fw.full(fit.x[3:])
        d_fit = fw.depth(nu)
        c_fit = math.exp(nu[1]) * fw.contrast(_stone(fit.x[:3]), d_fit, nu[4]) * fw.stiffening(d_fit, nu)
        c_pos = np.maximum(c_fit, 0.0)
        sig = np.sqrt(sig_fit ** 2 + np.where(beyond, CRUSH_REL_ERR * c_pos, 0.0) ** 2 + (fs_allow * c_pos) ** 2)
        fit = least_squares(resid, fit.x, jac=_jac_or_fd(jac), bounds=(np.concatenate([lo, nlo]),
                                                                     np.concatenate([hi, nhi])),
                            x_scale=np.concatenate([[1.0, 0.1, 1.0], NUIS_X_SCALE[fw.free]]), diff_step=1e-4,
                            max_nfev=300)
    q = fit.x
    n_res = len(fit.fun)
    dof = max(n_res - 3 - nf, 1)
    J = fit.jac
    infl = max(1.0, 2.0 * fit.cost / dof)
    # (the lean's amplitude: the fit's finite-strain amplitude, or where the estimate keeps the tissue linear, the
    # fit with it free: a neo-Hookean tissue's stone leans whether or not its estimate models the stiffening)
    cov_fit = np.linalg.pinv(J.T @ J) * infl
    cov_q = cov_fit + _lean_cov(fw, q, J, sig, fw.full(q[3:])[5] if fw.free[5] else a_fit[0])
    xs, dep, D = _stone(q[:3])
    s = math.exp(q[1]) * 1e-3
    G = np.zeros((3, len(q)))
    G[0, 0], G[1, 1], G[1, 2], G[2, 2] = 1e-3, s, 0.5e-3, 1e-3       # d(x, depth, D) / d q
    cov = G @ cov_q @ G.T
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    corr = float(cov[1, 2] / (sd[1] * sd[2])) if sd[1] > 0 and sd[2] > 0 else float("nan")
    names = ("x", "clearance", "diameter")
    at_bound = [n for n, v, a, z in zip(names, q[:3], lo, hi) if min(v - a, z - v) < 1e-3 * (z - a)]
    if crosses_side(xs, D, prior.tissue.width_m):
        at_bound.append(SIDE)
    if below_bottom(dep, D, prior.tissue.height_m, fw.full(q[3:])[4]):
        at_bound.append(BELOW_BOTTOM)
    detected = bool(lr >= lr_threshold)
    nu_1 = fw.full(q[3:])
    d_1 = fw.depth(nu_1)
    fit_c = math.exp(nu_1[1]) * fw.contrast((xs, dep, D), d_1, nu_1[4]) * fw.stiffening(d_1, nu_1)
    # the tissue and sensor unknowns as the accepted model fitted them (as in 3D): with the stone when one is
    # reported, else the no-stone fit (session 51's review: a NO STONE answer reported the rejected stone fit's
    # tissue, its bounds and a contrast against it)
    sd_nu = np.zeros(len(NUISANCE))
    if detected:
        nu, free_nu = nu_1, fw.free
        at_bound += nuisance_at_bound(q[3:], fw.free, NUIS_LO, NUIS_HI, NUISANCE_BOUND_NAMES)
        sd_nu[fw.free] = np.sqrt(np.maximum(np.diag(cov_q)[3:], 0.0))
    else:
        nu, free_nu = nu0, free0          # (the rejected stone fit's bounds are not the answer's)
        at_bound = nuisance_at_bound(h0.x, free0, NUIS_LO, NUIS_HI, NUISANCE_BOUND_NAMES)
        var0 = np.diag(np.linalg.pinv(h0.jac.T @ h0.jac)) * max(1.0, chi2_0 / max(len(h0.fun) - int(free0.sum()), 1))
        sd_nu[free0] = np.sqrt(np.maximum(var0, 0.0))
        a_fit = (float(nu0[5]), float(sd_nu[5]))
        fs_gain = float("nan")
    d_fit = fw.depth(nu)
    # (the profile's search grid is scaled by the depth's sigma from the fit alone: the lean is no likelihood's)
    sd_fit_depth = float(np.sqrt(max((G @ cov_fit @ G.T)[1, 1], 0.0)))
    profile_args = (resid, jac, q, lo, hi, dep, sd_fit_depth, 2.0 * fit.cost, infl, H, nlo, nhi)
    rel, rel_sd, rel_n = dwell_relaxation(meas)
    k = math.exp(nu[1])
    fixed = [n for n, f in zip(NUISANCE, free_nu) if not f]
    nuis = {"stiffness_scale": (k, k * sd_nu[1]), "thickness_scale": (1.0 + nu[4], sd_nu[4]),
            "surface_offset_m": (nu[2] * 1e-3, sd_nu[2] * 1e-3), "surface_tilt_rad": (nu[3] * 1e-3, sd_nu[3] * 1e-3),
            "sensor_drift_n_per_s": (nu[0] * 1e-3, sd_nu[0] * 1e-3),
            "finite_strain_amplitude": a_fit,
            "finite_strain_gain_chi2": fs_gain if math.isfinite(fs_gain) else None,
            "finite_strain_in_estimate": bool(free_nu[5]),
            "dwell_relaxation_fraction": (rel, rel_sd), "probes_with_dwell_history": rel_n,
            "contact_onsets_used": int(len(fw.on)) if free_nu[2] else 0,
            "fit": "stone" if detected else "no stone",
            "fixed": ["stiffness_scale" if f == "log_stiffness_scale" else f for f in fixed]}
    loc = Localization(depth_interval_m={}, detected=detected, lr=float(lr),
                       lr_threshold=lr_threshold, x_m=xs, depth_m=dep, diameter_m=D, sigma_x_m=float(sd[0]),
                       sigma_depth_m=float(sd[1]), sigma_diameter_m=float(sd[2]), corr_depth_diameter=corr,
                       chi2_0=float(chi2_0), chi2_1=float(chi2_1), dof_1=dof,
                       offset_drift_n_per_s=float(nu[0] * 1e-3), peak_x_m=px, peak_contrast_n=pc,
                       at_bound=at_bound, n_probes=len(meas), nuisance=nuis,
                       contrast_n=meas.force_n - nu[0] * 1e-3 * meas.tau_s - k * fw.tissue_force(d_fit, nu),
                       prior_n=k * fw.tissue_force(d_fit, nu), fit_contrast_n=fit_c,
                       n_beyond_linear_range=int(beyond.sum()), chi2_fit=2.0 * float(fit.cost),
                       surface_rise_at_stone_m=1e-3 * float(nu[2] + nu[3] * (xs - 0.5 * prior.tissue.width_m)))
    return loc, profile_args


def fs_lean(xs_m: float, width_m: float) -> float:
    """L: how far a neo-Hookean stone's contrast leans towards the section's nearer side (FS_LEAN_PER_M), in units of
    the prior's finite-strain correction a g per FS_LEAN_SPAN_M from the stone; 0 at the middle, and 0 from
    FS_LEAN_REACH_M of both sides; on a section narrower than twice that, no more than the stone's distance from the
    middle (by symmetry: 0 there, whatever the width)."""
    reach = max(FS_LEAN_REACH_M - min(xs_m, width_m - xs_m), 0.0)
    return FS_LEAN_PER_M * min(reach, abs(xs_m - 0.5 * width_m))


def _lean_cov(fw: _Forward, q, J: np.ndarray, sig: np.ndarray, amplitude: float) -> np.ndarray:
    """The covariance of the fit's parameters ``q`` from the finite-strain lean of the stone's contrast
    (FS_LEAN_PER_M: a systematic model error, one mode of its measured size taken as 1 sigma, its effect on the fit to
    first order: J+ times the mode's weighted residual), for a tissue stiffening at finite strain with ``amplitude``;
    0 for a linear one."""
    nu = fw.full(q[3:])
    stone = _stone(q[:3])
    xs = stone[0]
    lean = fs_lean(xs, fw.width_m)
    if fw.fs is None or not amplitude > 0.0 or lean == 0.0:
        return np.zeros((len(q), len(q)))
    d = fw.depth(nu)
    c_lin = math.exp(nu[1]) * np.maximum(fw.contrast(stone, d, nu[4]), 0.0)
    mode = lean * amplitude * fw.fs.g(d) * c_lin * np.clip((fw.meas.x_m - xs) / FS_LEAN_SPAN_M, -1.0, 1.0)
    r = np.zeros(J.shape[0])
    r[:len(mode)] = mode / sig
    dq = np.linalg.lstsq(J, r, rcond=None)[0]
    return np.outer(dq, dq)


def _beyond_linear_range(fw: _Forward, q, tip_radius_m: float) -> np.ndarray:
    """Per reading: whether the stone ``q[:3]`` lies under the tip's footprint with the reading's true indentation
    deeper than STONE_LAYER_MAX of the tissue layer over it (fem.contact.check_waypoint's rule)."""
    xs, dep, D = _stone(q[:3])
    d = fw.depth(fw.full(q[3:]))
    under = np.abs(fw.meas.x_m - xs) < tip_radius_m + 0.5 * D
    return under & (d > STONE_LAYER_MAX * (dep - 0.5 * D))
