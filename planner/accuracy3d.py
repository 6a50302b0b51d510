"""The 3D accuracy study's trials (issue 16): random spherical stones and healthy blocks, the coarse grid plus
adaptive refinement against even grids, Nano17-class noise.

    palpate study accuracy3d --out DIR [--stones 50] [--healthy 20] [--workers N | --scheduler ADDRESS]

Per trial a random rigid stone (diameter 6-16 mm, centre 8-35 mm deep with at least 2 mm of tissue above it,
anywhere over the central ``STONE_REGION_M`` of the probed area) is put into the prior block; 3D fem's surface model
of that TRUE block gives the force; the measurement model of the 2D study (planner.accuracy.FastArm: the dwell mean
and the free-air baseline's white noise, the zeroing error, a random drift) gives the probe records; the belief side
(planner.refine3d.adaptive3d -> planner.localize3d) sees only the prior and those records.

Resolution: the study's prior and truths are solved on the scene's own mesh (block3d's default: 15-25 s per truth
here). The prior and each truth are different meshes (a stone changes the mesh), so the localizer meets the mesh
ripple it meets in `palpate run`: about 0.05-0.1 mN on block3d's mesh. The surrogate table's coarse mesh (0.016 m,
grade 0.5; 7 s per truth) is no truth for a study: its ripple, 0.2-0.6 mN against a 1.4 mN peak contrast of the
paper's stone, put that stone 6.7 mm off (docs/loop3d.md); a coarse scene passed with ``--scene`` is studied on
its own mesh all the same.

Methods per stone: ``adaptive`` (a 6 x 6 coarse grid, every other probe shallower: planner.refine3d.coarse_depths,
then refinement rounds of 12 until the target uncertainty or the budget) and ``grid-N`` even grids (6x6 ... 12x12,
the same two depths) over the same area with the same fit. ``p_detect_pred``: the
detectability analysis (planner.detect3d) of the coarse grid for that stone, which defines the envelope
(p >= 0.9) that the detection target refers to.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.contracts import Motion, ProbeRecord, sensor_spec
from fem.contact3d import surface_model3d
from fem.scene import Stone
from planner.accuracy import FastArm
from planner.area import Region, area_raster, probe_bounds
from planner.detect3d import p_detect3d
from planner.detectability import probe_sigma_n, probe_tau_s
from planner.localize import DRIFT_SIGMA_N_PER_S, Measurements
from planner.localize3d import localize3d
from planner.refine3d import SHALLOW_FRACTION, adaptive3d, coarse_depths
from planner.surrogate3d import stone_model3d
from planner.tasks import Runner, rows_with, run_pieces
from planner.tissue_response3d import prior_and_thickness_slope3d

COARSE = (6, 6)
GRIDS = ((6, 6), (8, 8), (10, 10), (12, 12))
DEPTH_M = 0.004                 # the planner's depth on block3d (depth limit 4 mm; the force far below the limit)
STONE_REGION_M = 0.030          # stones are centred over the middle 30 x 30 mm of the probed area
FAILED = "failed"                # the method of a trial that raised: its one row carries the error


def random_stone3d(rng, prior) -> Stone:
    x0, x1, y0, y1 = probe_bounds(prior)
    cx, cy, h = 0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.5 * STONE_REGION_M
    D = rng.uniform(6e-3, 16e-3)
    depth = rng.uniform(max(8e-3, 2e-3 + D / 2), 35e-3)
    return Stone(x_m=rng.uniform(cx - h, cx + h), y_m=rng.uniform(cy - h, cy + h), depth_m=depth, diameter_m=D)


class FastArm3D(FastArm):
    """planner.accuracy.FastArm over a block: probe records at (x, y) from a TRUE force model f(x, y, depth)."""

    def execute3d(self, xy_m, depth_m=DEPTH_M) -> list[ProbeRecord]:
        """Records at the (N, 2) positions ``xy_m``, pressed ``depth_m`` deep (one, or one per probe)."""
        xy = np.asarray(xy_m, float).reshape(-1, 2)
        d = np.broadcast_to(np.asarray(depth_m, float), (len(xy),))
        return [self.record(lambda x=float(x), y=float(y), dd=float(dd): self.f(x, y, dd), float(x), float(dd), float(y))
                for (x, y), dd in zip(xy, d)]


@dataclass
class _Plan:
    """What adaptive3d reads of a plan: the probes' (x, y, depth) and the motion (positions only: the CasADi planner
    adds joint configurations but does not move waypoints, so the study skips it, as the 2D study does)."""
    probes: list
    motion: Motion


@dataclass
class _Probe:
    x_m: float
    y_m: float
    depth_m: float


def _plan(xy, depth_m=None) -> _Plan:
    xy = np.asarray(xy, float).reshape(-1, 2)
    d = np.full(len(xy), DEPTH_M) if depth_m is None else np.asarray(depth_m, float)
    return _Plan([_Probe(float(x), float(y), float(di)) for (x, y), di in zip(xy, d)], Motion())


def grid_xy(prior, grid) -> np.ndarray:
    x0, x1, y0, y1 = probe_bounds(prior)
    return area_raster(prior, region=Region.rectangle(x0, y0, x1, y1), grid=grid).positions_m


def trial3d(prior, sur, stone, sensor: str, seed: int, budget: int, target_m: float) -> list[dict]:
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    model = surface_model3d(prior) if stone is None else stone_model3d(prior.with_stones([stone]))
    t_model = time.perf_counter() - t0

    def force(x, y, d):
        try:
            return model.force_n(x, y, d)
        except ValueError:       # deeper than the linear model allows over a shallow stone: such a probe stops at
            return model.force_n(x, y, 0.5 * d) * 2 ** 1.5     # the force limit first (continued as d^1.5)
    fast = FastArm3D(force, sensor, rng)
    sp = sensor_spec(sensor)
    sig = probe_sigma_n(sp)
    rows = []

    def row(method, loc, n, extra=None):
        r = {"seed": seed, "sensor": sensor, "method": method, "n_probes": n, "detected": int(loc.detected),
             "lr": loc.lr, "x_est_m": loc.x_m, "y_est_m": loc.y_m, "depth_est_m": loc.depth_m,
             "diam_est_m": loc.diameter_m, "sigma_x_m": loc.sigma_x_m, "sigma_y_m": loc.sigma_y_m,
             "sigma_depth_m": loc.sigma_depth_m, "sigma_diam_m": loc.sigma_diameter_m,
             "stiffness_scale": loc.nuisance.get("stiffness_scale", (np.nan,))[0] if loc.nuisance else np.nan}
        if stone is not None:
            r.update(x_m=stone.x_m, y_m=stone.y_m, depth_m=stone.depth_m, diam_m=stone.diameter_m,
                     err_x_m=loc.x_m - stone.x_m, err_y_m=loc.y_m - stone.y_m,
                     err_lateral_m=float(np.hypot(loc.x_m - stone.x_m, loc.y_m - stone.y_m)),
                     err_depth_m=loc.depth_m - stone.depth_m, err_diam_m=loc.diameter_m - stone.diameter_m)
        r.update(extra or {})
        rows.append(r)

    prior_model = surface_model3d(prior)

    def predicted(xy, d):
        """(p_detect of the stone, prior forces) for probes at ``xy`` pressed ``d`` deep (planner.detect3d)."""
        if stone is None:
            return None                  # null in the piece's JSON (NaN is not JSON): no stone to detect
        P, dP = prior_and_thickness_slope3d(prior, xy[:, 0], xy[:, 1], d)
        return p_detect3d((stone.x_m, stone.y_m, stone.depth_m, stone.diameter_m), x_m=xy[:, 0], y_m=xy[:, 1],
                          depth_m=d, sigma_n=sig, surrogate=sur, prior_force_n=P, tau_s=probe_tau_s(Motion(), d),
                          thickness_slope_n=dP)

    coarse = grid_xy(prior, COARSE)
    d0 = coarse_depths(np.full(len(coarse), DEPTH_M))
    pd0 = predicted(coarse, d0)
    t1 = time.perf_counter()
    res = adaptive3d(prior, lambda plan, k: fast.execute3d([(p.x_m, p.y_m) for p in plan.probes],
                                                           [p.depth_m for p in plan.probes]),
                     coarse_xy_m=coarse, plan_round=lambda xy: _plan(xy, d0 if len(xy) == len(coarse) and
                                                                     np.array_equal(xy, coarse) else None),
                     surrogate=sur, region=probe_bounds(prior), budget_probes=budget, target_m=target_m)
    row("adaptive", res.localization, res.probes_used,
        {"rounds": len(res.rounds), "time_s": time.perf_counter() - t1, "truth_model_s": t_model,
         "stop": res.stop_reason, "p_detect_pred": pd0})
    for g in GRIDS:
        xy = grid_xy(prior, g)
        d = coarse_depths(np.full(len(xy), DEPTH_M))
        m = Measurements.from_records(fast.execute3d(xy, d), Motion())
        row(f"grid-{g[0]}x{g[1]}", localize3d(prior, m, sur), len(xy), {"p_detect_pred": predicted(xy, d)})
    if stone is not None:         # the best any placement could do, for the adaptive run's probe count
        P = prior_model.force_n(stone.x_m, stone.y_m, DEPTH_M)
        rows[0]["oracle_gain"] = oracle_gain(sur, (stone.x_m, stone.y_m, stone.depth_m, stone.diameter_m),
                                             probe_bounds(prior), P, sig, res.probes_used)
    return rows


def _jacobian(sur, stone, xy, d, P, tau) -> np.ndarray:
    """d force / d (x, y, depth, diameter, log scale, drift rate) at the TRUE stone, per probe (N x 6, N)."""
    th = np.array(stone, float)
    C = sur.contrast(xy[:, 0], xy[:, 1], d, *th)
    cols = []
    for i in range(4):
        h = np.zeros(4)
        h[i] = 2e-5
        cols.append((sur.contrast(xy[:, 0], xy[:, 1], d, *(th + h)) - sur.contrast(xy[:, 0], xy[:, 1], d, *(th - h)))
                    / 4e-5)
    return np.c_[np.array(cols).T, P + C, np.full(len(xy), tau)]


def oracle_gain(sur, stone, region, P: float, sigma_n: float, n: int) -> float:
    """How many times more probes an even grid (``n`` of them, the coarse grid's two depths) needs than the best
    placement for the same var(x) + var(y) + var(depth): a Cramer-Rao comparison at the TRUE stone (an oracle no
    adaptive scheme can beat). The placement is the greedy A-optimal one over a 1 mm grid of the region at the two
    depths (sequential, not the exact optimum: a lower bound on the best gain), started from the coarse 6 x 6 grid
    (what any run measures first), with the localizer's prior on the drift."""
    k = max(int(round(math.sqrt(n))), 2)
    x0, x1, y0, y1 = region
    g = np.array([(x, y) for x in np.linspace(x0, x1, k) for y in np.linspace(y0, y1, k)])
    d_even = coarse_depths(np.full(len(g), DEPTH_M))
    prior_prec = np.diag([0, 0, 0, 0, 0, sigma_n ** 2 / DRIFT_SIGMA_N_PER_S ** 2])

    def var_xyz(M):
        return float(np.trace(np.linalg.inv(M + 1e-18 * np.eye(6))[:3, :3]))
    tau = float(probe_tau_s(Motion(), DEPTH_M))
    J_even = _jacobian(sur, stone, g, d_even, P * (d_even / DEPTH_M) ** 1.5, tau)
    v_even = var_xyz(J_even.T @ J_even + prior_prec)
    c = coarse_depths(np.full(36, DEPTH_M))
    g6 = np.array([(x, y) for x in np.linspace(x0, x1, 6) for y in np.linspace(y0, y1, 6)])
    M = _jacobian(sur, stone, g6, c, P * (c / DEPTH_M) ** 1.5, tau)
    M = M.T @ M + prior_prec
    gx, gy = np.meshgrid(np.arange(x0, x1 + 1e-12, 1e-3), np.arange(y0, y1 + 1e-12, 1e-3), indexing="ij")
    cand = np.c_[gx.ravel(), gy.ravel()]
    Jc = np.vstack([_jacobian(sur, stone, cand, np.full(len(cand), dd), P * (dd / DEPTH_M) ** 1.5, tau)
                    for dd in (DEPTH_M, SHALLOW_FRACTION * DEPTH_M)])
    Fi = np.linalg.inv(M)
    for _ in range(max(n - 36, 0)):
        G = Jc @ Fi
        gain = np.sum(G[:, :3] ** 2, axis=1) / (1.0 + np.sum(G * Jc, axis=1))
        j = int(np.argmax(gain))
        v = Fi @ Jc[j]
        Fi = Fi - np.outer(v, v) / (1.0 + Jc[j] @ v)
    return float(v_even / np.trace(Fi[:3, :3]))


@dataclass(frozen=True)
class Trial3D:
    """One piece of the study: a stone (x_m, y_m, depth_m, diameter_m) or None (healthy), its seed and settings."""
    index: int
    seed: int
    stone: tuple[float, float, float, float] | None
    sensor: str = "nano17"
    budget: int = 84
    target_m: float = 5e-4

    @property
    def name(self) -> str:
        return f"trial3d-{self.index:04d}-seed{self.seed}"


def study_trials3d(prior, stones: int, healthy: int, sensor: str = "nano17", budget: int = 84,
                   target_m: float = 5e-4, seed: int = 1) -> list[Trial3D]:
    """``stones`` random stones then ``healthy`` stone-free blocks from one generator seeded by ``seed``."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(stones + healthy):
        st = random_stone3d(rng, prior) if i < stones else None
        out.append(Trial3D(index=i, seed=seed * 100000 + i, sensor=sensor, budget=budget, target_m=target_m,
                           stone=None if st is None else (st.x_m, st.y_m, st.depth_m, st.diameter_m)))
    return out


def run_trial3d(shared: dict, t: Trial3D) -> list[dict]:
    """The rows of one trial (module level: dask workers import it). ``shared``: {"sur", "prior"}."""
    prior = shared["prior"]
    stone = None if t.stone is None else Stone(x_m=t.stone[0], y_m=t.stone[1], depth_m=t.stone[2],
                                               diameter_m=t.stone[3])
    try:
        return trial3d(prior, shared["sur"], stone, t.sensor, seed=t.seed, budget=t.budget, target_m=t.target_m)
    except Exception as e:  # noqa: BLE001 - a trial that fails is a study's finding: counted, and the study goes on
        return [{"seed": t.seed, "method": FAILED, "stone": t.stone is not None, "error": f"{type(e).__name__}: {e}"}]


def run_accuracy3d(sur, prior, trials: list[Trial3D], runner: Runner = Runner(), store: Path | None = None) -> list[dict]:
    per = run_pieces(run_trial3d, {"sur": sur, "prior": prior}, trials, [t.name for t in trials], runner=runner,
                     store=store, desc="3D accuracy trials", shape=rows_with("seed", "method"))
    return [r for rows in per for r in rows]
