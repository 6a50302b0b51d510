"""Where to probe and how deep: raster positions over the top surface, the tissue frame in the base frame, and the
per-waypoint indentation depth chosen from a force prediction.

2D section: the raster is a line of waypoints along the top surface (tissue-frame x), ``margin_m`` from both side
edges. Depths come from a force model ``force_n(x_m, depth_m) -> float`` (fem's ``surface_model(prior).force_n``;
any callable that is 0 at depth 0 and increases with depth) for the *prior* (stone-free) tissue. On a 3D block the
positions are (x_m, y_m) (planner.area) and the force model ``force_n(x_m, y_m, depth_m)``; ``choose_depths`` takes
either, and a fast exact depth search for fem's 3D model (planner.depth3d).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from core.contracts import HARD_FORCE_LIMIT_N, MAX_FORCE_EXPONENT, MIN_FORCE_EXPONENT, PlanError
from core.ur5e import pose_to_T


def default_tissue_pose(width_m: float, height_m: float) -> list[float]:
    """The tissue frame in the base frame when nobody says otherwise: the section lies on the table the arm stands on
    (top surface ``height_m`` above the base plane), its width running along the base y axis, centred at y = 0 and
    0.40 m in front of the base (x); tissue x = base y, tissue z = base z (up), so the tool points straight down."""
    return [0.40, -0.5 * width_m, float(height_m), 0.0, 0.0, math.pi / 2]


def raster_positions(width_m: float, *, n: int | None = None, spacing_m: float | None = None,
                     margin_m: float = 0.005) -> np.ndarray:
    """Waypoint x positions (tissue frame) over [margin, width - margin]: ``n`` evenly spaced (both ends included),
    or as many as fit at ``spacing_m`` centred in the interval. Exactly one of n / spacing_m."""
    if (n is None) == (spacing_m is None):
        raise PlanError("give either a waypoint count (--waypoints) or a spacing (--spacing-m), not both")
    if not (0 <= margin_m < width_m / 2):
        raise PlanError(f"--margin-m {margin_m} must lie in [0, width/2 = {width_m / 2:g}) m")
    lo, hi = margin_m, width_m - margin_m
    return interval_positions(lo, hi, n=n, spacing_m=spacing_m)


def interval_positions(lo_m: float, hi_m: float, *, n: int | None = None,
                       spacing_m: float | None = None) -> np.ndarray:
    """Evenly spaced positions on [lo, hi] (for adaptive refinement over an x-interval)."""
    if hi_m < lo_m:
        raise PlanError(f"empty interval [{lo_m}, {hi_m}] m")
    if n is not None:
        if n < 1:
            raise PlanError(f"--waypoints must be at least 1, got {n}")
        return np.array([0.5 * (lo_m + hi_m)]) if n == 1 else np.linspace(lo_m, hi_m, n)
    if not (spacing_m and spacing_m > 0):
        raise PlanError(f"--spacing-m must be positive, got {spacing_m}")
    k = int(math.floor((hi_m - lo_m) / spacing_m + 1e-9))
    start = 0.5 * (lo_m + hi_m) - 0.5 * k * spacing_m
    return start + spacing_m * np.arange(k + 1)


@dataclass
class Targets:
    """Base-frame targets of a raster: tip positions above / in the tissue and the inward normal."""
    approach_m: np.ndarray   # (N, 3)
    indent_m: np.ndarray     # (N, 3)
    normal_in: np.ndarray    # (3,) unit inward normal of the (flat) top surface, base frame


def targets(x_m: Sequence[float], depth_m: Sequence[float], tissue_pose_base: Sequence[float],
            approach_height_m: float, y_m: Sequence[float] | None = None) -> Targets:
    """Surface points -> base frame. Tissue frame: (x_m, y_m, 0) is the surface point (y_m = 0 on a 2D section; a 3D
    block's top face otherwise), +z outward."""
    T = pose_to_T(tissue_pose_base)
    R, o = T[:3, :3], T[:3, 3]
    x = np.asarray(x_m, dtype=float)
    d = np.asarray(depth_m, dtype=float)
    surf = o[None, :] + x[:, None] * R[:, 0][None, :]
    if y_m is not None:
        surf = surf + np.asarray(y_m, dtype=float)[:, None] * R[:, 1][None, :]
    z_out = R[:, 2]
    return Targets(approach_m=surf + approach_height_m * z_out, indent_m=surf - d[:, None] * z_out,
                   normal_in=-z_out.copy())


# ---------------------------------------------------------------------------------------------------------------
# depth choice

def depth_for_force(force_n: Callable[[float, float], float], x_m: float, target_n: float, depth_max_m: float,
                    guess_m: float | None = None, tol_m: float = 2e-6, rtol_force: float = 5e-4,
                    power: float = 1.2) -> tuple[float, float]:
    """The largest depth in [0, depth_max] whose predicted force is <= target (force monotone in depth, 0 at 0), to
    within ``tol_m`` in depth or ``rtol_force`` in force. Steps are power-law secants (F ~ c d^p, p re-estimated from
    the last two evaluations) aimed just below the target, kept inside the bracket, else geometric bisection;
    ``guess_m`` (e.g. the neighbour's depth) usually makes it 2-3 force evaluations. Returns (depth_m, force_n);
    the returned force never exceeds the target."""
    lo, f_lo, hi = 0.0, 0.0, None
    d = depth_max_m if guess_m is None else min(max(guess_m, 1e-6 * depth_max_m), depth_max_m)
    aim = target_n * (1.0 - 0.5 * rtol_force)
    prev = None
    for _ in range(60):
        f = float(force_n(x_m, d))
        if f <= target_n:
            lo, f_lo = d, f
            if d >= depth_max_m or f >= target_n * (1.0 - rtol_force):
                break
        else:
            hi = d
        if hi is not None and hi - lo <= tol_m:
            break
        p = power
        if prev is not None and prev[1] > 0 and f > 0 and prev[0] != d:
            p_est = math.log(f / prev[1]) / math.log(d / prev[0])
            if 0.3 < p_est < 5.0:
                p = p_est
        prev = (d, f)
        nxt = d * (aim / f) ** (1.0 / p) if f > 0 else 2.0 * d
        top = depth_max_m if hi is None else hi
        if not (lo < nxt < top) or nxt == d:
            nxt = math.sqrt(max(lo, 1e-3 * top) * top) if hi is not None else min(2.0 * d, depth_max_m)
        d = min(nxt, depth_max_m)
    return lo, f_lo


@dataclass
class DepthChoice:
    depth_m: np.ndarray
    force_n: np.ndarray
    target_force_n: float
    limited_by: list[str]    # per waypoint: "depth" (depth limit reached first) or "force"


def choose_depths(force_n: Callable[..., float], x_m: Sequence, *, force_limit_n: float,
                  depth_limit_m: float, force_fraction: float = 0.5, min_depth_m: float = 0.001,
                  depth_for: Callable | None = None) -> DepthChoice:
    """Per waypoint: as deep as the limits allow (a deeper probe feels a buried stone more), i.e. the depth where the
    prior's predicted force reaches ``force_fraction * force_limit_n``, capped at ``depth_limit_m``. The fraction
    leaves head-room for stiffer-than-predicted tissue (a stone raises the force; the driver stops at the limit).
    Refuses when even ``min_depth_m`` (the shallowest useful probe) would exceed the force budget.

    Positions: ``x_m`` on a 2D section (``force_n(x_m, depth_m)``), or (x_m, y_m) pairs on a 3D block
    (``force_n(x_m, y_m, depth_m)``). ``depth_for(position, target_n, depth_max_m, guess_m) -> (depth_m, force_n)``
    replaces the generic search (``depth_for_force``) when given, e.g. depth3d.ContactDepths3D.depth_for; it must
    return a force that is exact at its depth and at most the target."""
    if depth_limit_m <= 0 or force_limit_n <= 0:
        raise PlanError("--force-limit-n and --depth-limit-m must be positive")
    if not (0 < force_fraction <= 1):
        raise PlanError(f"--force-fraction must lie in (0, 1], got {force_fraction}")
    if min_depth_m > depth_limit_m:
        raise PlanError(f"--depth-limit-m {depth_limit_m * 1e3:.2f} mm is below the smallest useful depth "
                            f"--min-depth-m {min_depth_m * 1e3:.2f} mm: raise the depth limit or lower --min-depth-m")
    target = force_fraction * force_limit_n
    depths, forces, why = [], [], []
    guess = None
    for x in x_m:
        at = (float(x),) if np.ndim(x) == 0 else tuple(float(v) for v in x)
        if depth_for is not None:
            d, f = depth_for(at, target, depth_limit_m, guess)
        elif len(at) == 1:
            d, f = depth_for_force(force_n, at[0], target, depth_limit_m, guess_m=guess)
        else:
            d, f = depth_for_force(lambda _, dd, at=at: force_n(*at, dd), at[0], target, depth_limit_m, guess_m=guess)
        if d < min_depth_m:  # (if d >= min_depth, monotonicity already puts min_depth within the budget)
            f_min = float(force_n(*at, min_depth_m))
            if f_min > target:
                need = f_min / force_fraction
                where = " ".join(f"{k} = {v * 1e3:.1f} mm," for k, v in zip("xy", at))[:-1]
                if need > HARD_FORCE_LIMIT_N:
                    raise PlanError(
                        f"the prior tissue is predicted to push back {f_min:.3g} N at the smallest useful depth "
                        f"{min_depth_m * 1e3:.2f} mm ({where}): a plan within the force budget would need a force "
                        f"limit of {need:.3g} N, above the hard cap {HARD_FORCE_LIMIT_N:g} N; check the scene's "
                        f"tissue.youngs_pa (too stiff for this probe), or lower --min-depth-m")
                raise PlanError(
                    f"force limit {force_limit_n:g} N is too low: the prior tissue is predicted to push back "
                    f"{f_min:.3g} N at the smallest useful depth {min_depth_m * 1e3:.2f} mm ({where}), "
                    f"above the planning budget {force_fraction:g} x {force_limit_n:g} N = {target:.3g} N. Raise "
                    f"--force-limit-n to at least {need:.3g} N, raise --force-fraction, or lower --min-depth-m.")
            d, f = min_depth_m, f_min   # within the search tolerance of the root
        guess = d
        depths.append(d)
        forces.append(f)
        why.append("depth" if d >= depth_limit_m else "force")
    return DepthChoice(np.array(depths), np.array(forces), target, why)


def force_exponents(force_n: Callable[..., float], positions: Sequence, depth_m: Sequence[float],
                    force_at_depth_n: Sequence[float], threshold_n: float,
                    depth_for: Callable | None = None) -> list[float | None]:
    """Per waypoint, the prior's force ~ depth^p over the chord from ``threshold_n`` to the planned depth (the planner
    passes SURFACE_FIT_FROM_FRACTION of the contact threshold: where the driver's fit of the force curve starts): the
    driver counts the indentation at which it felt contact from it, so that its depth limit is below the surface,
    not below the contact felt (robot.tissue_depth). Where the prior does not reach the threshold by the planned
    depth, the chord over the depth's second half; None where neither is defined or p lies outside
    [MIN_FORCE_EXPONENT, MAX_FORCE_EXPONENT] (the driver then counts from the contact felt). ``positions``,
    ``force_n`` and ``depth_for`` as in ``choose_depths``."""
    out, guess = [], None
    for pos, d, f in zip(positions, depth_m, force_at_depth_n):
        at = (float(pos),) if np.ndim(pos) == 0 else tuple(float(v) for v in pos)
        d, f, p = float(d), float(f), None
        if f > threshold_n:
            if depth_for is not None:
                d0, f0 = depth_for(at, threshold_n, d, guess)
            else:
                d0, f0 = depth_for_force(lambda _, dd, at=at: force_n(*at, dd), at[0], threshold_n, d, guess_m=guess)
            if 0 < d0 < d and f0 > 0:
                p, guess = math.log(f / f0) / math.log(d / d0), d0
        elif f > 0:
            f_half = float(force_n(*at, 0.5 * d))
            if f_half > 0:
                p = math.log(f / f_half) / math.log(2.0)
        if p is not None and MIN_FORCE_EXPONENT - 1e-3 <= p < MIN_FORCE_EXPONENT:
            p = MIN_FORCE_EXPONENT      # a flat punch's exact 1 read 0.9999999999999998 by rounding (session 54)
        out.append(p if p is not None and MIN_FORCE_EXPONENT <= p <= MAX_FORCE_EXPONENT else None)
    return out
