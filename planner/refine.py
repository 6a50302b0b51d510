"""Adaptive refinement: a coarse raster, then finer rasters around the candidate until the fit's uncertainty is below
a target or the probe budget is spent.

Every round is planned by the same CasADi planner with the same safety limits (``plan.replan`` of the coarse plan:
frames, limits, motion, force-chosen depths), executed by whatever ``execute(plan, round) -> records`` the caller
hands in (the driver on a simulated or real arm), and localized from the prior scene and *all* measurements so far.
``adaptive`` never sees a true scene: it gets the prior and measurements only (see commands/run.py for the split).

Where to probe next (``strategy``):
* "raster": ``n_refine`` waypoints evenly over the candidate x +- h, h = 0.8 depth + 3 mm (clipped to 6..20 mm): the
  contrast's flanks (lateral position) and its width (depth) live there; far tails carry little. The new waypoints
  are staggered half a spacing against the previous round's so the profile is sampled ever more finely.
* "design" (default): the ``n_refine`` positions (0.5 mm grid, repeats allowed) that shrink var(x) + var(depth) of
  the current estimate most, chosen greedily from the Fisher information of (x, depth, diameter, drift offset) at
  the estimate (surrogate derivatives). It puts probes on the flanks, the centre and the far ends (the ends pin the
  drift offset, which is otherwise confounded with a broad, deep stone's contrast).
Probing the same positions at a second, shallower depth was considered and rejected: with the 4 mm depth limit the
contrast's shape hardly changes with probe depth (its ratio between depths is the same for a 25 mm and a 40 mm
deep stone to 0.5 %), so a second depth buys no depth information that another position would not (Fisher check:
sigma_depth 0.88 mm with half the refinement probes at 2 mm against 0.89 mm all at 4 mm, paper stone).
A weak candidate (LR above ``weak_lr`` but below the detection threshold) gets refinement rounds too: more probes
where the evidence is decide between "small or deep stone" and "noise".
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from core.contracts import MEASURED, PlanOptions
from fem import recall
from fem.contact import STONE_LAYER_MAX
from fem.scene import from_dict
from planner.localize import (
    BELOW_BOTTOM,
    CRUSH_REL_ERR,
    MIN_MEASUREMENTS,
    NEAR_SIDE,
    SIDE,
    SIDE_REACH3D_M,
    STONE_PARAMS,
    Localization,
    Measurements,
    localize,
)
from planner.surrogate import load_surrogate
from planner.tissue_response import THICKNESS_STEP, fem_deepest_m, prior_and_thickness_slope

WEAK_LR = 12.0


@dataclass
class Round:
    index: int
    x_m: list
    depth_m: list
    n_probes: int
    localization: dict
    plan: object = None          # planfile.Plan (None in position-only studies)
    elapsed_s: float = 0.0


@dataclass
class AdaptiveResult:
    localization: Localization
    measurements: Measurements
    rounds: list = field(default_factory=list)
    probes_used: int = 0
    stop_reason: str = ""


def refine_positions(loc: Localization, n: int, width_m: float, margin_m: float, previous_x=None) -> np.ndarray:
    """``n`` waypoints around the candidate (see module doc), inside [margin, width - margin]."""
    if loc.detected and math.isfinite(loc.x_m):
        centre = loc.x_m
        h = float(np.clip(0.8 * loc.depth_m + 3e-3, 6e-3, 20e-3)) if math.isfinite(loc.depth_m) else 12e-3
    else:
        centre, h = loc.peak_x_m, 12e-3
    lo, hi = max(margin_m, centre - h), min(width_m - margin_m, centre + h)
    if hi - lo < 2e-3:
        lo, hi = max(margin_m, hi - 2e-3), min(width_m - margin_m, lo + 2e-3)
    x = np.linspace(lo, hi, n)
    if previous_x is not None and len(previous_x) and n > 1:
        prev = np.asarray(previous_x)
        step = (hi - lo) / (n - 1)
        if np.min(np.abs(x[:, None] - prev[None, :])) < 0.25 * step:
            x = lo + (np.arange(n) + 0.5) * (hi - lo) / n      # cell midpoints: staggered, still inside
    return x


MIN_DESIGN_DEPTH_M = 1e-4      # the design's shallowest indentation for the tissue's columns (0 gives no force)


def design_positions(loc: Localization, meas: Measurements, n: int, surrogate, width_m: float, margin_m: float,
                     depth_m: float | None = None, step_m: float = 5e-4, prior=None) -> np.ndarray:
    """``n`` waypoints chosen one by one to shrink var(x) + var(depth) of the current estimate most (greedy A-optimal
    sequential design over a 0.5 mm grid; Fisher information of (x, depth, diameter, offset) from the surrogate's
    derivatives at the estimate plus the probes already made; with ``prior`` and a localization that fitted the
    tissue's stiffness scale, also the scale and the thickness change, whose columns are the prior's force (plus the
    contrast) and its thickness derivative). Repeated positions are allowed (they are re-measured).
    Falls back to ``refine_positions`` without a detected, finite estimate."""
    if not (loc.detected and math.isfinite(loc.x_m) and math.isfinite(loc.depth_m)):
        return refine_positions(loc, n, width_m, margin_m, meas.x_m)
    d = float(np.median(meas.depth_m)) if depth_m is None else depth_m
    if prior is not None:       # inside fem's range: a surface higher than registered stops the probes at the depth
        #                         limit, their nominal depths about 0 (the design then knows the tissue's columns less)
        d = float(np.clip(d, MIN_DESIGN_DEPTH_M, 0.95 * fem_deepest_m(prior, 1 - THICKNESS_STEP)))
    sig = float(np.median(meas.sigma_n))
    th = np.array([loc.x_m, loc.depth_m, loc.diameter_m])
    tissue = prior is not None and "stiffness_scale" not in loc.nuisance.get("fixed", ["stiffness_scale"])

    def jac(x, dd):
        cols = []
        if tissue:        # the prior's force and thickness slope at this depth (the design's one depth)
            P, dP = prior_and_thickness_slope(prior, x, d)
            cols += [P + surrogate.contrast(x, dd, *th), dP]
        for i in range(3):
            h = np.zeros(3)
            h[i] = 2e-5
            cols.append((surrogate.contrast(x, dd, *(th + h)) - surrogate.contrast(x, dd, *(th - h))) / 4e-5)
        cols.append(np.ones(len(x)) * 1e-3)       # offset in mN
        return np.array(cols).T
    Je = jac(meas.x_m, meas.depth_m) / meas.sigma_n[:, None]
    F = Je.T @ Je + 1e-12 * np.eye(Je.shape[1])
    cand = np.arange(margin_m, width_m - margin_m + 1e-12, step_m)
    Jc = jac(cand, np.full(len(cand), d)) / sig
    Fi = np.linalg.inv(F)
    out = []
    for _ in range(n):
        G = Jc @ Fi                               # (ncand, 4)
        gain = (G[:, -4] ** 2 + G[:, -3] ** 2) / (1.0 + np.sum(G * Jc, axis=1))     # x and depth
        k = int(np.argmax(gain))
        out.append(cand[k])
        g = Fi @ Jc[k]
        Fi = Fi - np.outer(g, g) / (1.0 + Jc[k] @ g)
    return np.sort(np.array(out))


def converged(loc: Localization, target_m: float) -> bool:
    return bool(loc.detected and max(loc.sigma_x_m, loc.sigma_depth_m) <= target_m and not loc.at_bound)


def adaptive(prior, execute, *, coarse_x_m, plan_round=None, budget_probes: int = 45, n_refine: int = 10,
             target_m: float = 5e-4, motion=None, surrogate=None, margin_m: float = 0.005, progress=None,
             weak_lr: float = WEAK_LR, strategy: str = "design", workers: int = 1) -> AdaptiveResult:
    """Run the loop. ``plan_round(x_m) -> plan`` makes a plan (None: position-only, ``execute`` gets the positions);
    ``execute(plan_or_x, round_index) -> list of probe records`` (the driver's dicts). ``prior`` has no stones.
    ``strategy``: "design" (design_positions) or "raster" (refine_positions: an even, finer raster around it).
    ``workers``: the fits of each localization on that many processes (planner.forkmap: the same estimates)."""
    if prior.stones:
        raise ValueError("adaptive() takes the prior scene (no stones)")
    W = prior.tissue.width_m
    say = progress or (lambda msg: None)
    rounds, meas, loc = [], None, None
    x = np.asarray(coarse_x_m, float)
    used, k, reason = 0, 0, "budget"
    prev_x = None
    while True:
        t0 = time.perf_counter()
        plan = plan_round(x) if plan_round is not None else None
        recs = execute(plan if plan is not None else x, k)
        m = Measurements.from_records(recs, motion if plan is None else plan.motion,
                                      statuses=MEASURED)
        used += len(x)
        meas = m if meas is None else meas.concat(m)
        if len(meas) < MIN_MEASUREMENTS:        # every probe failed or read a force no tissue gives
            loc = Localization(detected=False, lr=float("nan"), lr_threshold=float("nan"))
            reason = too_few(len(meas), used, MIN_MEASUREMENTS)
            say(f"round {k}: {len(x)} probes ({used} in all): {reason}")
            break
        loc = localize(prior, meas, surrogate, workers=workers)
        dep = [p.depth_m for p in plan.probes] if plan is not None else list(m.depth_m)
        rounds.append(Round(k, [float(v) for v in x], [float(v) for v in dep], len(x), loc.to_dict(), plan,
                            time.perf_counter() - t0))
        if k == 0:
            # (the coarse plan's: what a re-run's depth limit may be)
            reach = probe_reach(plan, prior_force(plan) if plan is not None else None)
        say(f"round {k}: {len(x)} probes ({used} in all): " + describe(loc, reach))
        if converged(loc, target_m):
            reason = "target uncertainty reached"
            break
        if not loc.detected and loc.lr < weak_lr:
            reason = "no stone (no candidate worth refining)"
            break
        n = min(n_refine, budget_probes - used)
        if n < 3:
            reason = "probe budget spent"
            break
        prev_x = x
        if strategy == "design":
            x = design_positions(loc, meas, n, surrogate or load_surrogate(prior), W, margin_m, prior=prior)
        else:
            x = refine_positions(loc, n, W, margin_m, prev_x)
        k += 1
    return AdaptiveResult(loc, meas, rounds, used, reason)


def too_few(usable: int, used: int, need: int) -> str:
    """Why a round cannot be localized: fewer usable measurements than a fit needs."""
    why = (" (the others failed or read forces no tissue gives: see probes.jsonl's status, reason and implausible)"
           if usable < used else "")
    return f"too few usable measurements: {usable} of {used} probes, a fit needs at least {need}{why}"


MIN_HINT_DEPTH_M = PlanOptions().min_depth_m   # a shallower depth limit is not suggested: `palpate run` refuses a
#                              --depth-limit-m below the shallowest useful probe (the suggestion said 0.5 mm before)
HINT_MARGIN = 0.9            # the suggested limit's share of what the linear model covers over the fitted stone (its
#                              top is an estimate: at the full share a re-run still pressed 29 readings past it)


def linear_range_depth_m(loc) -> float:
    """The planned (nominal) probe depth that keeps a probe over the fitted stone within what the linear model covers
    (``HINT_MARGIN`` of fem.contact.STONE_LAYER_MAX of the tissue over its top, less the fitted surface's rise there:
    a surface higher than registered is indented deeper by the same planned depth), floored to 0.1 mm; NaN without a
    finite estimate."""
    top = loc.depth_m - 0.5 * loc.diameter_m
    rise = getattr(loc, "surface_rise_at_stone_m", 0.0)
    if not (math.isfinite(top) and math.isfinite(rise)):
        return math.nan
    return math.floor((HINT_MARGIN * STONE_LAYER_MAX * max(top, 0.0) - rise) * 1e4) / 1e4


CONTACT_MARGIN = 1.5         # a suggested depth limit leaves every probe pressing at least this many contact thresholds
#                              (session 51: a 3D block's shallow stone was told 1.1 mm, where probes press 0.01 N
#                              against a 0.02 N threshold and feel no contact)
FORCE_EXPONENT = 1.5         # a probe's force ~ depth^p where its plan has no exponent: Hertz's sphere (a deeper floor
#                              than the 2D cylinder's 1.1-1.2)


def contact_floor_m(plan, force_n=None, upto_m: float | None = None) -> float:
    """The shallowest depth limit (0.1 mm steps) at which every probe of ``plan`` is still predicted to press
    ``CONTACT_MARGIN`` x the contact threshold on the prior tissue: its predicted force continued from its planned
    depth as depth^p (its plan's force exponent, else ``FORCE_EXPONENT``), then, with ``force_n(probe, depth_m)``
    (fem's force of the plan's prior: ``prior_force``), raised in 0.1 mm steps until fem's own force at every probe
    exceeds that (the continuation alone came out up to 5 % short: session 59's review was told a 2.0 mm limit at
    which its next run's probes pressed 0.0298 N against 0.030 N, and that run stopped at its first probe). The
    result may be the plan's own depth limit or deeper (no shallower limit lets its probes feel the tissue); the
    steps go up to ``upto_m`` (default: the plan's depth limit, all a hint needs to know). NaN without a plan or its
    predictions, or where fem refuses the depth."""
    probes = getattr(plan, "probes", None)
    if not probes or getattr(plan, "limits", None) is None:
        return math.nan
    target = CONTACT_MARGIN * plan.motion.contact_threshold_n
    need = []
    for p in probes:
        f, d = p.predicted_force_n, p.depth_m
        if not (f is not None and f > 0 and d > 0):
            return math.nan
        need.append(d * (target / f) ** (1.0 / (p.force_exponent or FORCE_EXPONENT)))
    floor = math.ceil(max(need) * 1e4 - 1e-6) / 1e4
    if force_n is None:
        return floor
    try:
        top = plan.limits.depth_limit_m if upto_m is None else upto_m
        while floor < top and not all(force_n(p, floor) > target for p in probes):
            floor = round(floor + 1e-4, 4)
    except ValueError:              # fem refuses the depth (deeper than its model covers): no floor to say
        return math.nan
    return floor


def prior_force(plan):
    """``force_n(probe, depth_m)``: fem's force of ``plan``'s prior scene at a probe's position (what plan_raster
    predicts its forces with), remembered (fem.recall, fem.recall3d)."""
    prior = from_dict(plan.scene, default_name=plan.scene.get("name", "prior"))
    if prior.is_3d:
        from fem import recall3d  # (the 3D model's code: loaded for a block only)
        return lambda p, d: recall3d.force_n(prior, p.x_m, p.y_m, d)
    return lambda p, d: recall.force_n(prior, p.x_m, d)


# session 51, the mismatch study's 27 shallow stones run again at the suggested depth: on linear tissue x within 2
# sigma 81 -> 100 %, on neo-Hookean tissue 91 -> 45 % (the finite strain of the thin layer over the stone is not in
# the model, and shallow probes' small sigmas no longer hide it; docs/mismatch.md)
HINT_CAUTION = " (on tissue stiffening at finite strain, x's sigma may then come out too small)"


class ProbeReach(NamedTuple):
    """What a run's plan says of the depths a suggested depth limit may take (NaN: unknown)."""
    floor_m: float = math.nan      # contact_floor_m: shallower, its probes would not feel the tissue
    deepest_m: float = math.nan    # its deepest planned probe: a limit this deep or deeper changes nothing


def probe_reach(plan, force_n=None) -> ProbeReach:
    """``plan``'s ProbeReach; ``force_n`` as contact_floor_m takes it."""
    depths = [p.depth_m for p in getattr(plan, "probes", None) or ()]
    return ProbeReach(contact_floor_m(plan, force_n), max(depths) if depths else math.nan)


def suggested_limit_m(loc, reach: ProbeReach = ProbeReach()) -> tuple[float, float]:
    """(the depth limit to suggest, what the linear model over the fitted stone asks for): the second when it is
    deep enough that the probes still feel the tissue (``reach.floor_m``) and the planner takes it, else the nearest
    such; NaN (no suggestion) when the estimate is not finite or the model asks for no less than the probes went (the
    readings past the range then came from where the fitted surface is higher than over the stone's centre: nothing
    a limit would change). ``reach``: the run's plan's (``probe_reach``)."""
    safe = linear_range_depth_m(loc)
    if not math.isfinite(safe) or safe >= reach.deepest_m:
        return math.nan, safe
    lo = max(MIN_HINT_DEPTH_M, reach.floor_m) if math.isfinite(reach.floor_m) else MIN_HINT_DEPTH_M
    limit = max(safe, lo)
    if limit >= reach.deepest_m:     # no limit shallower than the probes went lets them feel the tissue
        return math.nan, safe
    return limit, safe


def depth_hint(loc, reach: ProbeReach = ProbeReach()) -> str:
    """The depth limit that keeps a re-run's probes within the linear model over the fitted stone (``; ...`` or ""),
    as ``suggested_limit_m`` chooses it, and why."""
    limit, safe = suggested_limit_m(loc, reach)
    if not math.isfinite(limit):
        return ""
    if limit == safe:
        return (f"; probes no deeper than {safe * 1e3:.1f} mm over it stay within that model: --depth-limit-m {safe:g}"
                + HINT_CAUTION)
    why = (f"they press the tissue {CONTACT_MARGIN:g}x the contact threshold only from {limit * 1e3:.1f} mm"
           if limit > MIN_HINT_DEPTH_M else f"the planner takes no probe shallower than {limit * 1e3:g} mm")
    return (f"; that model holds over it only for probes no deeper than {max(safe, 0.0) * 1e3:.1f} mm, but {why}: "
            f"--depth-limit-m {limit:g} comes nearest" + HINT_CAUTION)


def caveats(loc, reach: ProbeReach = ProbeReach()) -> str:
    """What makes a detected stone's estimate doubtful, for the line that reports it ("" when nothing): a parameter
    at its fit's bound (the table's range: the stone may lie beyond it, and the rest of the estimate with it) and a fit
    the data reject (chi2 above its degrees of freedom by more than 4 standard deviations, sqrt(2 dof): one stone in
    the prior's tissue does not explain the forces). ``reach``: as ``depth_hint`` takes it."""
    out = []
    bounds = [b for b in loc.at_bound if b in STONE_PARAMS]
    if bounds:
        out.append(f"at the fit's bound: {', '.join(bounds)} (the stone may lie beyond the range the table "
                   f"covers, and the rest of the estimate be pulled off with it: its sigmas do not say so)")
    tissue = [b for b in loc.at_bound if b not in STONE_PARAMS and b not in (SIDE, NEAR_SIDE, BELOW_BOTTOM)]
    if tissue:
        out.append(f"the tissue's {', '.join(tissue)} at the fit's bound (the tissue or its surface is unlike the "
                   f"prior beyond what the fit allows: the stone's estimate may be pulled off with it, and its sigmas "
                   f"do not say so)")
    if SIDE in loc.at_bound:
        out.append("the fitted stone would cross the section's side (no tissue holds it there, and the table's "
                   "forces there are extrapolated, not fem's): its sigma does not say how far off it may be")
    if BELOW_BOTTOM in loc.at_bound:
        out.append("the fitted stone reaches below the tissue's bottom (as its thickness is fitted): no tissue holds it "
                   "there, and the table's forces there are extrapolated, not fem's; its depth and diameter are not "
                   "measured, and their sigmas do not say how far off they may be")
    fc = getattr(loc, "fem_correction", None)
    if NEAR_SIDE in loc.at_bound and fc:
        out.append(f"the fitted stone lies within {SIDE_REACH3D_M * 1e3:.0f} mm of the block's side, and fem's "
                   f"correction of the table there did not settle ({fc['passes']} passes"
                   + (f"; stopped: {fc['stopped']}" if fc.get("stopped") else "") + "): its sigmas do not say how "
                   "far off it may be")
    elif NEAR_SIDE in loc.at_bound:
        out.append(f"the fitted stone lies within {SIDE_REACH3D_M * 1e3:.0f} mm of the block's side: the 3D table takes "
                   f"its contrast as a stone's away from the sides (a 10 mm stone 13 mm from one came out 2 mm too "
                   f"shallow and 1.6 mm too small, 12 and 14 sigma, with a noise-free sensor; 0.7 mm, 3-4 sigma, 21 mm "
                   f"from it): its sigmas do not say how far off it may be")
    n_beyond = getattr(loc, "n_beyond_linear_range", 0)
    if n_beyond:
        # (session 50's review: on a 30 mm section, shallow stones' diameters 3-6 sigma small with only this warning,
        # and within 1 sigma when probed no deeper than the linear model covers over them)
        hint = depth_hint(loc, reach)
        out.append(f"the stone's top lies within the probes' reach: {n_beyond} readings pressed the tissue over it "
                   f"beyond what the linear model covers (taken with a {CRUSH_REL_ERR:.0%} error on the stone's "
                   f"contrast there, in the sigmas; its depth and diameter may still be biased beyond them){hint}")
    dof = loc.dof_1
    chi2 = loc.chi2_fit if math.isfinite(getattr(loc, "chi2_fit", math.nan)) else loc.chi2_1
    if dof and chi2 > dof + 4.0 * math.sqrt(2.0 * dof):
        out.append(f"poor fit: chi2 {chi2:.0f} on {dof} degrees of freedom (another stone, or tissue unlike "
                   f"the prior?)")
    return "".join(f"; warning: {c}" for c in out)


def no_stone_caveats(loc, n_stone: int = 3) -> str:
    """What makes a no-stone answer doubtful ("" when nothing): the no-stone fit's tissue at its bound, and the
    no-stone fit the data reject, as ``caveats`` says of a stone's (its degrees of freedom the stone fit's plus the stone's ``n_stone`` parameters). Session 44's
    review: a healthy soft block under a high surface, chi2 66 on 28, answered NO STONE without a word."""
    out = []
    tissue = [b for b in loc.at_bound if b not in STONE_PARAMS and b != SIDE]
    if tissue:           # (the no-stone fit's own: since session 52 a NO STONE answer reports that fit's tissue)
        out.append(f"the tissue's {', '.join(tissue)} at the no-stone fit's bound (the tissue or its surface is "
                   f"unlike the prior beyond what the fit allows: the answer is less sure than its LR says)")
    dof = loc.dof_1 + n_stone if loc.dof_1 else 0
    if dof and math.isfinite(loc.chi2_0) and loc.chi2_0 > dof + 4.0 * math.sqrt(2.0 * dof):
        out.append(f"poor fit without a stone: chi2 {loc.chi2_0:.0f} on {dof} degrees of freedom (tissue "
                   f"unlike the prior, or a stone the fit did not find: the answer is less sure than its LR says)")
    return "".join(f"; warning: {c}" for c in out)


def describe(loc: Localization, reach: ProbeReach = ProbeReach()) -> str:
    """A localization in one line (its caveats after "; warning: "); ``reach`` as ``depth_hint`` takes it."""
    if not loc.detected:
        return (f"no stone (LR {loc.lr:.1f} < {loc.lr_threshold:g}; peak contrast {loc.peak_contrast_n * 1e3:.1f} mN)"
                + no_stone_caveats(loc))
    return (f"stone at x {loc.x_m * 1e3:.2f} +- {loc.sigma_x_m * 1e3:.2f} mm, depth {loc.depth_m * 1e3:.2f} +- "
            f"{loc.sigma_depth_m * 1e3:.2f} mm, diameter {loc.diameter_m * 1e3:.2f} +- "
            f"{loc.sigma_diameter_m * 1e3:.2f} mm (LR {loc.lr:.0f})" + caveats(loc, reach))


def renumber(plan, start: int):
    """The plan with probe indices start, start+1, ... (rounds share one probes.jsonl; the driver resumes by index)."""
    plan.probes = [dataclasses.replace(p, index=start + i) for i, p in enumerate(plan.probes)]
    return plan
