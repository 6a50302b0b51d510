"""The 3D flow of `palpate run` (a block scene, issue 16): a coarse grid over the probed area, probe, localize the
stone in (x, y, depth) with its diameter, refine where the uncertainty shrinks most, report.

Loaded by app.commands.run for a 3D scene only (the 2D commands never import the 3D path). The split between truth
and belief is the 2D flow's (app.runexec): the executor holds the TRUE block inside its closure; this module hands
the loop (planner.refine3d -> planner.localize3d) the prior block (stones removed) and the probe records only. The
truth is written into result.json after localization, under ``sim``.
"""
from __future__ import annotations

import contextlib
import json
import math
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from app.cell import sim_range_report
from app.commands.output import write_json
from app.commands.plan import RUN_THRESHOLD_HINT, below_contact_threshold
from app.errors import UsageError
from app.figchild import FigureChild
from app.outlock import holding
from app.runexec import (
    INTERRUPTED_AT_REST,
    RunAborted,
    choose_executor,
    conclude,
    exit_code,
    localized,
    measured_on_disk,
    new_stats,
    open_out,
    plan_options_hint,
    refuse_unfelt,
    resuming_note,
    round_planner,
    run_limits,
    workers_for_fits,
)
from core.contracts import Plan, PlanError, sensor_spec
from planner.area import near_side_fraction, probe_bounds
from planner.detect3d import detectability3d
from planner.detectability import describe_smallest
from planner.draw_run3d import draw_run3d
from planner.localize import SIDE_REACH3D_M, THICKNESS_SIGMA
from planner.localize3d import Localization3D, surrogate_bounds
from planner.plan import plan_raster, replan
from planner.refine import prior_force, probe_reach
from planner.refine3d import adaptive3d, coarse_depths, describe3d
from planner.surrogate3d import load_surrogate3d
from planner.tissue_response3d import prior_and_thickness_slope3d, thickness_models_to_build


@dataclass
class RunContext:
    """What app.commands.run checked and decided before handing a 3D scene over (nothing written yet)."""
    t_wall: float
    out: Path
    scene: object            # the scene argument (the TRUTH for a simulated arm)
    prior: object            # the belief: a stone-free block
    plan0: Plan | None       # the coarse plan (--plan, or saved in OUT when resuming)
    cond: object             # robot.truth.TruthConditions (simulated arm) or None
    opts: dict               # run_options.json
    resume: bool
    fig_child: FigureChild | None = None     # draws the figure (a simulated run: app.figchild); None: here
    on_exit: contextlib.ExitStack | None = None   # the command's: holds OUT's lock until the process is done with it


def _say(msg: str) -> None:
    print(f"palpate run: {msg}", file=sys.stderr, flush=True)


def thickness_sigma(args, prior) -> float:
    """The localizer's prior on the block's thickness, relative: ``--thickness-sigma-m`` over the prior's height, or
    the 2D localizer's default."""
    v = getattr(args, "thickness_sigma_m", None)
    return THICKNESS_SIGMA if v is None else float(v) / prior.tissue.height_m


def _detectable(prior, plan0, sur, sensor: str, th_sigma: float) -> dict:
    """What the coarse grid can detect before probing (planner.detect3d: a stone under the grid's middle, the
    stiffness scale, the thickness (prior ``th_sigma``) and the drift unknown), said on one line; its dict for
    result.json."""
    if th_sigma == 0:               # (the thickness known: the plan's median force serves the scale's column)
        forces = [p.predicted_force_n for p in plan0.probes if p.predicted_force_n]
        det = detectability3d(plan0, sur, float(statistics.median(forces)) if forces else 0.0,
                              sensor_spec=sensor_spec(sensor))
        return _said(det, sensor, th_sigma)
    missing = thickness_models_to_build(prior)
    if missing:
        names = [f"{f:g}" for f in missing]
        at = ", ".join(names[:-1]) + " and " + names[-1] if len(names) > 1 else names[0]
        _say(f"building the prior block's fem model at {at} of its thickness (the localizer fits the thickness; "
             f"once, then cached)")
    P, dP = prior_and_thickness_slope3d(prior, [p.x_m for p in plan0.probes], [p.y_m for p in plan0.probes],
                                        [p.depth_m for p in plan0.probes])
    det = detectability3d(plan0, sur, P, sensor_spec=sensor_spec(sensor), thickness_slope_n=dP,
                          thickness_sigma=th_sigma)
    return _said(det, sensor, th_sigma)


def _said(det: dict, sensor: str, th_sigma: float) -> dict:
    """The detectability said on one line; its dict for result.json."""
    smallest = det["smallest_detectable"]
    sizes = [r["diameter_m"] for r in det["rows"] if r["p_detect"] is not None]
    text = (describe_smallest(smallest)
            or (f"no stone of {min(sizes) * 1e3:g}-{max(sizes) * 1e3:g} mm at any depth the table covers: a NO STONE "
                f"answer will mean little" if sizes else "nothing the table covers")) if det["usable"] else det["reason"]
    known = f"thickness known to {th_sigma * 100:.3g} %" if th_sigma > 0 else "thickness known exactly"
    _say(f"detectable before probing (coarse grid, sensor {sensor}; a stone under the grid's middle; {known}): "
         f"{text}")
    return {"sensor": sensor, "usable": det["usable"], "reason": det["reason"], "probe_sigma_n": det["sigma_n"],
            "smallest_detectable": smallest, "thickness_prior_sigma": th_sigma}


def run_block(args, ctx: RunContext) -> int:
    prior, out = ctx.prior, ctx.out
    plan0 = ctx.plan0
    if plan0 is None:
        nx, ny = args.grid
        _say(f"planning a {nx} x {ny} raster over the probed area of {prior.name}")
        try:
            full = plan_raster(prior, grid=(nx, ny), limits=run_limits(args, prior.indenter.radius_m))
            plan0 = replan(full, [(p.x_m, p.y_m) for p in full.probes],
                           depth_m=coarse_depths([p.depth_m for p in full.probes]))
        except PlanError as e:
            raise UsageError(f"--grid {nx}x{ny}: {plan_options_hint(str(e), args)}") from None
        except ValueError as e:          # fem refuses the scene or the planned indentation
            hint = (f" (the depth limit is {full_limit_m(args, prior):g} m; scene field indenter.radius_m must exceed it)"
                    if "radius" in str(e) and "depth" in str(e) else "")
            raise UsageError(f"{args.scene}: the coarse raster cannot be planned on its prior: {e}{hint}") from None
        refuse_unfelt(plan0, args)
    if warning := below_contact_threshold(plan0, RUN_THRESHOLD_HINT):
        _say("warning: " + warning)
    where_prior = f"--plan {args.plan}: its prior scene" if args.plan else f"scene {args.scene}: its prior"
    t0 = time.perf_counter()
    sur = _table(prior, where_prior)
    table_s = time.perf_counter() - t0
    th_sigma = thickness_sigma(args, prior)
    det = _detectable(prior, plan0, sur, args.sensor, th_sigma)
    near = near_side_fraction(prior, SIDE_REACH3D_M)
    if near > 0.0:                  # (session 53's review: a stone there came out 6-8 sigma off, unwarned)
        _say(f"note: {near:.0%} of the probed area lies within {SIDE_REACH3D_M * 1e3:g} mm of the block's sides, where "
             f"the 3D table's stones are biased (its stone is taken as one away from the sides): a stone found there "
             + ("is warned about (--no-fem-correction)" if getattr(args, "no_fem_correction", False) else
                "is fitted again with fem's contrast at the fitted stone before the run stops (a stone model on the "
                "prior's mesh per pass, a minute or more each)"))
    stats = new_stats()
    sim_arm: dict = {}
    cleanup = contextlib.ExitStack()
    execute, where, truth = choose_executor(args, out, ctx.scene, ctx.cond, plan0, ctx.resume, stats, cleanup, sim_arm,
                                            _say)
    (ctx.on_exit if ctx.on_exit is not None else cleanup).enter_context(holding(out))   # one process in OUT
    open_out(args, out, ctx.opts, _say)
    if ctx.resume:
        for line in resuming_note(out).splitlines():
            _say(line)
    _say(f"probing on the {where}")
    t_first: dict = {}
    plan_round = round_planner(plan0, out)

    def execute_timed(plan, k):
        t_first.setdefault("probing_started_s", time.perf_counter() - ctx.t_wall)
        return execute(plan, k)

    status, fault, res = "ok", None, None
    try:
        res = adaptive3d(prior, execute_timed, coarse_xy_m=[(p.x_m, p.y_m) for p in plan0.probes],
                         plan_round=plan_round, surrogate=sur, region=probe_bounds(prior),
                         budget_probes=args.budget_probes, n_refine=args.refine_waypoints,
                         target_m=args.target_uncertainty_m, progress=_say,
                         workers=workers_for_fits(args), thickness_sigma=th_sigma,
                         fem_correction=not getattr(args, "no_fem_correction", False))
        stats["clean_end"] = True
    except RunAborted as e:
        status = "interrupted" if e.report.status == "interrupted" else "fault"
        fault = e.report.to_dict()
        stats["n_probes"] = measured_on_disk(out)       # (an interrupted round's too: kept, resumed)
        _say(str(e))
    except KeyboardInterrupt:       # between rounds (a fit, a plan, fem): the arm is at rest; 130 follows
        _say(f"{INTERRUPTED_AT_REST} ({measured_on_disk(out)} probes in {out})")
        raise
    finally:
        cleanup.close()
    result = {"scene": args.scene, "prior": prior.name, "where": where, "status": status, "dimension": 3}
    if res is not None:
        loc = res.localization
        result.update(loc.to_dict())
        result.update({"probes_used": res.probes_used, "stop_reason": res.stop_reason,
                       "rounds": [{"index": r.index, "n_probes": r.n_probes, "xy_m": r.x_m, "depth_m": r.depth_m,
                                   "localization": r.localization, "elapsed_s": r.elapsed_s} for r in res.rounds]})
    else:
        loc = Localization3D(detected=False, lr=float("nan"), lr_threshold=float("nan"))
        result.update(loc.to_dict())
        result.update({"probes_used": stats["n_probes"], "fault": fault})
    result["time"] = {"wall_s": time.perf_counter() - ctx.t_wall, "surrogate_s": table_s, **t_first,
                      "robot_s": stats["controller_s"], "planned_s": stats["planned_s"]}
    result["detectability"] = det
    result["surrogate"] = {"build_s": getattr(sur, "build_s", None),
                           "bounds": {k: list(v) for k, v in _bounds(sur).items()},
                           "rel_err": getattr(sur, "rel_err", None), "abs_err_n": getattr(sur, "abs_err_n", None)}
    if truth is not None:        # comparison only, after the fact
        st = [{"x_m": s.x_m, "y_m": s.y_m, "depth_m": s.depth_m, "diameter_m": s.diameter_m} for s in truth.stones]
        result["sim"] = {"sensor": args.sensor, "seed": args.seed, "truth_stones": st,
                         "truth_tissue": {"youngs_pa": truth.tissue.youngs_pa, "poisson": truth.tissue.poisson,
                                          "height_m": truth.tissue.height_m,
                                          "youngs_scale_to_prior": truth.tissue.youngs_pa / prior.tissue.youngs_pa},
                         "truth_conditions": ctx.cond.to_dict() if ctx.cond is not None else None}
        if st and res is not None and loc.detected:
            e = {"x_m": loc.x_m - st[0]["x_m"], "y_m": loc.y_m - st[0]["y_m"],
                 "depth_m": loc.depth_m - st[0]["depth_m"], "diameter_m": loc.diameter_m - st[0]["diameter_m"]}
            e["lateral_m"] = math.hypot(e["x_m"], e["y_m"])
            result["sim"]["error"] = e
    if sim_arm.get("arm") is not None:
        rr = sim_range_report(sim_arm["arm"])
        if rr is not None:
            result.setdefault("sim", {})["force_beyond_model_range"] = rr
            _say(f"warning: {rr['note']} ({rr['samples_beyond_model_range']} samples, deepest "
                 f"{rr['deepest_m'] * 1e3:.2f} mm)")
    reach = probe_reach(plan0, prior_force(plan0))   # what a depth limit a warning suggests may be
    head = conclude(result, out, loc, res, describe3d(loc, reach) if res is not None else "", status, fault, _say,
                    three_d=True, tissue=prior.tissue)
    (out / "result.json").write_text(json.dumps(result, indent=1, allow_nan=False))
    write_json(args.json, result)
    if res is not None and localized(loc) and not args.no_figure and res.measurements is not None:
        from planner.plots_run3d import run_figure3d
        fig = run_figure3d(prior, loc, res.measurements, surrogate=sur,
                           truth_stones=truth.stones if truth is not None else (), region=probe_bounds(prior),
                           title=f"palpate run {args.scene}:\n" + describe3d(loc, reach).replace("; warning: ", "\nwarning: "))
        if ctx.fig_child is not None:
            ctx.fig_child.draw(out / "fig_run.png", fig, _say)
        else:
            draw_run3d(out / "fig_run.png", fig)
    print(head
          + f"; {result['probes_used']} probes; results in {out}",
          file=sys.stderr if args.json == "-" else sys.stdout)
    return exit_code(status)


def full_limit_m(args, prior) -> float:
    return run_limits(args, prior.indenter.radius_m).depth_limit_m


def _table(prior, where_prior: str):
    """The prior's 3D surrogate (planner.surrogate3d): shipped or cached, else built now (with progress)."""
    try:
        try:
            return load_surrogate3d(prior, build=False)
        except FileNotFoundError:
            _say("no 3D surrogate table for this tissue yet (planner/surrogate3d.py says which scene fields select "
                 "one): building it now (one fem model per candidate stone: minutes)")
            return load_surrogate3d(prior, build=True, progress=lambda n, total, s, what: _say(
                f"surrogate table: {n} of {total} {what}, {s:.0f} s"))
    except (RuntimeError, ArithmeticError, ValueError) as e:
        raise UsageError(f"{where_prior} cannot be modelled: {e} (check the tissue and indenter moduli and "
                         f"sizes)") from None


def _bounds(sur) -> dict:
    return surrogate_bounds(sur)
