"""The accuracy study's trials: localization and adaptive refinement over random stones (``run_accuracy``).

    palpate study accuracy --out DIR [--quick] [--workers N | --scheduler ADDRESS]   (or bench/accuracy_study.py)

Per trial a random rigid stone (diameter 6-16 mm, top clearance 2-34 mm, centre 5-41 mm deep, x 15-55 mm) is put
into the prior tissue; fem's surface model of that TRUE scene gives the force; a measurement model with the sensor's
statistics gives the probe records; the belief side (planner.refine.adaptive -> planner.localize) sees only the prior
and those records. Reports (tables, ratios, figure): planner.accuracy_report, planner.plots_accuracy.

Measurement model (``FastArm``): per probe the dwell mean of the true force at the planned depth plus the simulated
arm's error terms (robot/sensor.py) as the driver records them (robot/records.py): white noise of the 250-sample
dwell mean and of the descent's ~2200-sample free-air baseline it is referenced to (the zeroing's 50-sample error
cancels between the two), and the sensor's drift rate (random per run) times the 5 s between the two. It reproduces
what robot.sim + robot.driver record about 100x faster (checked: on the simulated arm, `palpate run paper --sim`,
the baseline-referenced forces scatter about fem's with 0.20 mN around a drift offset; this model: 0.20 mN; test:
tests/test_robot_sim.py::test_free_air_baseline_removes_the_zeroing_error). Positions are the ones the planner is
asked for; the CasADi planner adds joint configurations but does not move waypoints, so it is skipped here
(``palpate run`` uses it).

Methods compared per stone: ``adaptive`` (15-probe coarse raster + refinement rounds of 10 until the target
uncertainty or the budget) and ``dense-N`` even rasters (N = 15 ... 113) with the same fem fit; for each even raster
(and the larger ``peak-N``, N = 161, 241) also the classic model-free answer, the raster's maximum: ``peak_fit``
(parabola over the top half of the contrast) and the 3-point vertex. ``equal_accuracy`` turns these into "how many
probes does an even raster need for the adaptive run's error" with bootstrap intervals (planner.accuracy_report).
How much any placement could gain at all: bench/design_bound.py (Cramer-Rao).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.contracts import Motion, ProbeRecord, ProbeStatus, sensor_spec
from fem.contact import surface_model
from fem.scene import Stone
from planner.detectability import baseline_samples, p_detect, probe_sigma_n, probe_tau_s
from planner.localize import Measurements, localize, prior_force
from planner.raster import raster_positions
from planner.refine import adaptive
from planner.surrogate import _forces, stone_model
from planner.tasks import Runner, rows_with, run_pieces

DENSE = (15, 21, 29, 41, 57, 81, 113)   # even rasters localized with the same fem fit (and the model-free peak fit)
PEAK_ONLY = (161, 241)                  # larger even rasters for the model-free maximum finder only
BOOT = 1000                             # bootstrap resamples of the stones for the ratios' intervals
STRATEGIES = ("design", "raster")
DEPTH_M = 0.004           # the planner's depth on this tissue (depth limit 4 mm, force far below the limit)


def continued_force(model):
    """``model.force_n``, continued where fem refuses the indentation (a stone so shallow that the tip would crush
    the tissue against it: fem.contact.check_waypoint) with the local power law in depth (planner.surrogate._forces
    with the limit kept; the table itself holds the linear model's forces there since session 49); a real probe
    there stops at its force limit first. Elsewhere unchanged."""
    def f(x_m: float, depth_m: float) -> float:
        try:
            return model.force_n(x_m, depth_m)
        except ValueError:
            levels = depth_m * np.array([0.25, 0.375, 0.5, 0.625, 0.75, 0.875, 1.0])
            return float(_forces(model, levels, [x_m], past_crush=False)[-1, 0])
    return f


class FastArm:
    """Probe records from a TRUE force model and the sensor's statistics (see module doc)."""

    def __init__(self, force_n, sensor: str, rng, motion: Motion = Motion(), period_s: float = 0.002):
        self.f, self.sp, self.rng, self.mo = force_n, sensor_spec(sensor), rng, motion
        self.n = int(round(motion.dwell_s / period_s))
        self.nb = baseline_samples(motion, period_s)
        self.drift = rng.normal(0.0, self.sp.drift_n_per_s)
        self.count = 0

    def execute(self, x_m, k=0, depth_m=DEPTH_M):
        return [self.record(lambda x=float(x): self.f(x, depth_m), float(x), depth_m) for x in np.asarray(x_m, float)]

    def record(self, true_force, x_m: float, depth_m: float, y_m: float = 0.0) -> ProbeRecord:
        """One probe's record at (x_m, y_m) pressed ``depth_m`` deep; ``true_force()`` gives the true force."""
        s = self.sp
        tau = float(probe_tau_s(self.mo, depth_m))
        t_base = 0.5 * self.nb * 0.002                      # from zeroing to the baseline's middle
        zero_err = self.rng.normal(0, s.noise_std_n / math.sqrt(50))
        base = self.rng.normal(0, s.noise_std_n / math.sqrt(self.nb)) - zero_err + self.drift * t_base
        dwell = (true_force() + self.rng.normal(0, s.noise_std_n / math.sqrt(self.n)) - zero_err
                 + self.drift * (t_base + tau))
        std = s.noise_std_n * (1 + self.rng.normal(0, 1 / math.sqrt(2 * self.n)))
        rec = ProbeRecord(index=self.count, x_m=x_m, y_m=y_m, depth_reached_m=depth_m, status=ProbeStatus.OK,
                          force_mean_n=dwell, force_std_n=abs(std), n_samples=self.n, force_baseline_n=base,
                          n_samples_baseline=self.nb, baseline_to_dwell_s=tau)
        self.count += 1
        return rec


class _Loc:
    def __init__(self, detected, lr, x, d, D, sx, sd, sD, px):
        self.detected, self.lr, self.x_m, self.depth_m, self.diameter_m = detected, lr, x, d, D
        self.sigma_x_m, self.sigma_depth_m, self.sigma_diameter_m, self.peak_x_m = sx, sd, sD, px


def random_stone(rng, W):
    D = rng.uniform(6e-3, 16e-3)
    s = rng.uniform(2e-3, min(34e-3, 46e-3 - D))
    return Stone(x_m=rng.uniform(15e-3, W - 15e-3), depth_m=s + D / 2, diameter_m=D)


def trial(prior, sur, stone, sensor, seed, budget, target_m):
    rng = np.random.default_rng(seed)
    truth = prior if stone is None else prior.with_stones([stone])
    model = surface_model(prior) if stone is None else stone_model(truth)
    fast = FastArm(continued_force(model), sensor, rng)
    W = prior.tissue.width_m
    rows = []

    def row(method, loc, n, extra=None):
        r = {"seed": seed, "sensor": sensor, "method": method, "n_probes": n, "detected": int(loc.detected),
             "lr": loc.lr, "x_est_m": loc.x_m, "depth_est_m": loc.depth_m, "diam_est_m": loc.diameter_m,
             "sigma_x_m": loc.sigma_x_m, "sigma_depth_m": loc.sigma_depth_m, "sigma_diam_m": loc.sigma_diameter_m,
             "peak_x_m": loc.peak_x_m}
        if stone is not None:
            r.update(x_m=stone.x_m, depth_m=stone.depth_m, diam_m=stone.diameter_m,
                     err_x_m=loc.x_m - stone.x_m, err_depth_m=loc.depth_m - stone.depth_m,
                     err_diam_m=loc.diameter_m - stone.diameter_m, err_peak_m=loc.peak_x_m - stone.x_m)
        r.update(extra or {})
        rows.append(r)

    coarse = raster_positions(W, n=15, margin_m=0.005)
    sig = probe_sigma_n(sensor_spec(sensor))
    pd0 = (p_detect(prior, (stone.x_m, stone.depth_m, stone.diameter_m), x_m=coarse, depth_m=np.full(15, DEPTH_M),
                    sigma_n=sig, surrogate=sur) if stone is not None else None)   # null in JSON: no stone
    for strategy in STRATEGIES:
        t0 = time.perf_counter()
        res = adaptive(prior, fast.execute, coarse_x_m=coarse, budget_probes=budget, target_m=target_m,
                       surrogate=sur, motion=Motion(), strategy=strategy)
        extra = {"rounds": len(res.rounds), "time_s": time.perf_counter() - t0, "stop": res.stop_reason,
                 "p_detect_pred": pd0}
        if strategy == STRATEGIES[0] and res.localization.detected:   # the depth's profile interval (as palpate run)
            iv = localize(prior, res.measurements, sur, profile=True).depth_interval_m
            extra.update(depth_lo95_m=iv["95"][0], depth_hi95_m=iv["95"][1], depth_lo68_m=iv["68"][0],
                         depth_hi68_m=iv["68"][1])
        row(f"adaptive-{strategy}", res.localization, res.probes_used, extra)
        cum = np.cumsum([rd.n_probes for rd in res.rounds])
        for n in (15, 25, 35, 45):     # the estimate with at most n probes (an early stop keeps its final one)
            if n > budget:
                break
            rd = res.rounds[int(np.searchsorted(cum, n, side="right")) - 1]
            e = rd.localization["estimate"]
            loc_r = _Loc(rd.localization["detected"], rd.localization["evidence"]["likelihood_ratio"],
                         *[e[k]["value"] if e[k]["value"] is not None else float("nan") for k in
                           ("x_m", "depth_m", "diameter_m")],
                         *[e[k]["sigma"] if e[k]["sigma"] is not None else float("inf") for k in
                           ("x_m", "depth_m", "diameter_m")], rd.localization["evidence"]["peak_x_m"] or float("nan"))
            row(f"round-{strategy}@{n}", loc_r, n)
    for N in DENSE + PEAK_ONLY:
        x = raster_positions(W, n=N, margin_m=0.005)
        m = Measurements.from_records(fast.execute(x), Motion())
        pf = peak_fit(m.x_m, m.force_n - prior_force(prior, m))
        extra = {"peakfit_x_m": pf}
        if stone is not None:
            extra["err_peakfit_m"] = pf - stone.x_m
        if N in PEAK_ONLY:          # no fit, no detection decision: every stone counts (no healthy rows)
            if stone is not None:
                rows.append({"seed": seed, "sensor": sensor, "method": f"peak-{N}", "n_probes": N, "detected": 1,
                             "x_m": stone.x_m, "depth_m": stone.depth_m, **extra})
            continue
        loc = localize(prior, m, sur)
        pd = (p_detect(prior, (stone.x_m, stone.depth_m, stone.diameter_m), x_m=x, depth_m=np.full(N, DEPTH_M),
                       sigma_n=sig, surrogate=sur) if stone is not None else None)   # null in JSON: no stone
        row(f"dense-{N}", loc, N, {"p_detect_pred": pd, **extra})
    return rows


def peak_fit(x, c) -> float:
    """The best model-free maximum finder we know for a dense raster: the least-squares parabola through the
    contiguous run of probes whose (3-point smoothed) contrast is at least half the largest, vertex clipped to that
    run (at least the largest point and its two neighbours). Unbiased for a symmetric bump, and it averages noise
    over the whole top of the bump, where the 3-point vertex (``localize.peak_estimate``) uses three probes."""
    o = np.argsort(x)
    x, c = np.asarray(x, float)[o], np.asarray(c, float)[o]
    cs = np.convolve(np.pad(c, 1, mode="edge"), np.ones(3) / 3, mode="valid")
    k = int(np.argmax(cs))
    lo = hi = k
    while lo > 0 and cs[lo - 1] >= 0.5 * cs[k]:
        lo -= 1
    while hi < len(c) - 1 and cs[hi + 1] >= 0.5 * cs[k]:
        hi += 1
    lo, hi = max(0, min(lo, k - 1)), min(len(c) - 1, max(hi, k + 1))
    if hi - lo < 2:
        return float(x[k])
    a, b, _ = np.polyfit(x[lo:hi + 1] - x[k], c[lo:hi + 1], 2)
    if a >= 0:
        return float(x[k])
    return float(np.clip(x[k] - b / (2 * a), x[lo], x[hi]))


def errors_by_seed(rows, sensor, method, key):
    """{seed: |error|} of the detected stone scenes of one method."""
    return {r["seed"]: abs(r[key]) for r in rows if r["method"] == method and r["sensor"] == sensor and "x_m" in r
            and r["detected"] and np.isfinite(r.get(key, np.nan))}


@dataclass(frozen=True)
class Trial:
    """One piece of the study: a stone (x_m, depth_m, diameter_m) or None (healthy), its seed and settings."""
    index: int
    seed: int
    stone: tuple[float, float, float] | None
    sensor: str = "nano17"
    budget: int = 45
    target_m: float = 5e-4

    @property
    def name(self) -> str:
        return f"trial-{self.index:04d}-seed{self.seed}"


def study_trials(width_m: float, trials: int, healthy: int, sensor: str = "nano17", budget: int = 45,
                 target_m: float = 5e-4, seed: int = 1) -> list[Trial]:
    """The study's pieces: ``trials`` random stones then ``healthy`` stone-free scenes, drawn from one generator
    seeded by ``seed`` (the same stones whoever runs them); trial i is seeded ``seed * 100000 + i``."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(trials + healthy):
        st = random_stone(rng, width_m) if i < trials else None
        out.append(Trial(index=i, seed=seed * 100000 + i, sensor=sensor, budget=budget, target_m=target_m,
                         stone=None if st is None else (st.x_m, st.depth_m, st.diameter_m)))
    return out


def run_trial(sur, t: Trial) -> list[dict]:
    """The rows of one trial (a module-level function: dask workers import it). ``sur.prior`` is the tissue."""
    stone = None if t.stone is None else Stone(x_m=t.stone[0], depth_m=t.stone[1], diameter_m=t.stone[2])
    return trial(sur.prior, sur, stone, t.sensor, seed=t.seed, budget=t.budget, target_m=t.target_m)


def run_accuracy(sur, trials: list[Trial], runner: Runner = Runner(), store: Path | None = None) -> list[dict]:
    """Every trial's rows, in trial order, on ``runner`` (planner.tasks: serial, LocalCluster or a scheduler);
    finished trials are kept in ``store`` and read back by a re-run."""
    per = run_pieces(run_trial, sur, trials, [t.name for t in trials], runner=runner, store=store,
                     desc="accuracy trials", shape=rows_with("seed", "sensor", "method", "n_probes", "detected"))
    return [r for rows in per for r in rows]
