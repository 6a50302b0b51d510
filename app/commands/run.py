"""`palpate run [SCENE] [--plan plan.json] [--sim | --host IP] --out DIR`: plan, probe, localize, refine.

Truth and belief (docs/architecture.md): SCENE is the truth only for a simulated arm. This command builds two separate things:
an *executor* (``sim_executor``: the simulated arm, created from the true scene inside a closure; or ``arm_executor``
on a real arm, where there is no truth) that turns a plan into probe records, and the *belief side*
(planner.refine.adaptive -> planner.localize.localize) that gets the prior scene (stones removed) and those records
and nothing else. The truth is written into result.json only after localization, for comparison (``sim`` key).
The truth may differ from the belief beyond its stones (issue 14): ``--prior PRIOR`` plans and localizes on another
scene's prior (a ``--plan`` carries its own), and the truth scene file's ``[truth]`` table or the ``--truth-*``
options (robot/truth.py: registration error, relaxation, sensor bias and drift) reach only the simulated arm.
The force comes from the UR's wrist sensor (``--ft rtde``) or an ATI Net F/T box (``--ft netft:HOST``; with a
simulated arm ``--ft netft``, a simulated box): app/ftoptions.py, issue 18.

Data safety (issue 13): every input (options, scene, plan file, output paths) is checked before OUT is touched, and
no record is ever deleted. OUT/run_options.json holds what decides the run's rounds (scene, plan file, arm, sensor,
seed, raster, budget, target, strategy). A re-run with the same --out and the same options RESUMES: each round's
saved plan (OUT/plan_round<k>.json) is reused, probes already measured (ok/depth_limit in probes.jsonl; a force_limit
stop, which may have been a sensor's spike, is pressed again unless its whole round was measured) are not pressed again, and the localization replays from the records. A re-run with other options is refused; ``--fresh``
moves the old files into OUT/previous-<UTC time>/ first. ``--json`` may not point at a measured file.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

from app.cell import sim_range_report
from app.commands.output import write_json
from app.commands.plan import RUN_THRESHOLD_HINT, below_contact_threshold
from app.errors import UsageError
from app.figchild import FigureChild
from app.ftoptions import add_ft_options, check_ft
from app.options import (
    MAX_TOTAL_PROBES,
    MAX_WAYPOINTS,
    check_output_dir,
    check_output_file,
    check_same_extent,
    check_simulated_sensor,
    finite_float,
    float_range,
    grid_counts,
    host_name,
    int_range,
    load_plan_option,
    load_scene,
    positive_float,
)
from app.outlock import holding
from app.runexec import (
    INTERRUPTED_AT_REST,
    RUN_FILES,
    RunAborted,
    check_fresh_inputs,
    check_resume,
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
    run_options,
    truth_conditions,
    workers_for_fits,
)
from core.contracts import (
    HARD_DEPTH_LIMIT_M,
    SENSORS,
    TIP_DEPTH_FRACTION,
    Limits,
    Plan,
    PlanError,
    PlanOptions,
    default_depth_said,
)
from fem.scene import BUILTIN
from planner.detectability import describe_smallest, detectability, smallest_detectable
from planner.draw_run import draw_run
from planner.finite_strain_response import prior_finite_strain, unsupported, x_nodes
from planner.localize import (
    MAX_THICKNESS_SIGMA,
    MIN_MEASUREMENTS,
    MIN_MEASUREMENTS3D,
    MIN_THICKNESS_SIGMA,
    SIDE_REACH3D_M,
    SIGMA_BOUND_TOL,
    Localization,
    localize,
)
from planner.pending import PendingSurrogate, TableBuildError
from planner.plan import plan_prior, plan_raster
from planner.refine import adaptive, describe, prior_force, probe_reach
from planner.surrogate import check_table_fits, load_surrogate
from robot.driver import unfelt_probes
from robot.safety import check_plan
from robot.truth import DEFAULT_RELAXATION, conditions_of

DEFAULT_GRID3D = (6, 6)        # 3D: the coarse grid, refinement rounds and budget
DEFAULT_REFINE3D = 12
DEFAULT_BUDGET3D = 84


EPILOG = """examples:
  palpate run paper --sim --out runs/paper                  the paper's section, simulated arm and sensor
  palpate run block3d --sim --out runs/block                a 3D block: a 6 x 6 grid, then refinement rounds
  palpate run mine.toml --prior belief.toml --sim --out R   the truth is mine.toml, the planner believes belief.toml
  palpate run paper --sim --truth-surface-offset-m 0.002 --out R   a surface 2 mm higher than registered
  palpate run paper --host 192.168.1.10 --out R             a real UR arm (asks to confirm; --yes does not)

the last line says:
  STONE ...           a stone found: x (and y in 3D), depth, diameter with 1-sigma uncertainties, warnings after
  NO STONE ...        the likelihood ratio stays below its threshold (the detectability line before probing says
                      which stones the run could have found)
  NOT LOCALIZED ...   too few usable probes, or most read forces no tissue gives, or a fit that cannot place it
  NOT DETECTABLE ...  no probe felt the tissue
  NO RESULT ...       the arm run ended with a fault or was interrupted: its probes are kept, the command resumes

OUT holds probes.jsonl and raw/ (every reading, never overwritten), result.json (SI units), fig_run.png, run.json.
exit status: 0 the arm run ended well (whatever the verdict), 1 a fault or a failure (a full disk), 2 bad input
(nothing moved), 130 interrupted."""


def add_parser(sub) -> None:
    p = sub.add_parser("run", help="plan, probe (simulated arm by default), locate the stone, refine",
                       description=__doc__.splitlines()[0], epilog=EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", nargs="?", default="paper",
                   help="scene: built-in name or TOML (the TRUTH for --sim; only its prior is used for planning)")
    p.add_argument("--plan", help="use this plan.json as the coarse raster (default: plan one)")
    p.add_argument("--prior", metavar="PRIOR",
                   help="the belief: plan and localize on this scene's prior (built-in name or TOML) instead of "
                        "SCENE's; SCENE stays the simulated truth (default: SCENE's prior, or the --plan's)")
    tr = p.add_argument_group("simulated truth beyond its scene (--sim only; override the scene file's [truth] "
                              "table; see robot/truth.py)")
    tr.add_argument("--truth-surface-offset-m", type=finite_float, metavar="M",
                    help="true surface this far above the nominal tissue pose (registration error), |M| <= 0.005")
    tr.add_argument("--truth-surface-tilt-rad", type=finite_float, metavar="RAD",
                    help="true surface tilted about the tissue's y axis through its middle, |RAD| <= 0.175")
    tr.add_argument("--truth-relaxation", type=finite_float, nargs="?", const=DEFAULT_RELAXATION[0],
                    metavar="FRACTION", help="viscoelastic tissue (standard linear solid): the force at constant "
                                             f"depth relaxes by FRACTION (default {DEFAULT_RELAXATION[0]:g}), 0..0.9")
    tr.add_argument("--truth-relaxation-tau-s", type=finite_float, metavar="S",
                    help=f"its time constant (default {DEFAULT_RELAXATION[1]:g} s)")
    tr.add_argument("--truth-hyperelastic", action="store_const", const=True, default=None,
                    help="finite-strain tissue: a compressible neo-Hookean solid with the scene's E and nu instead "
                         "of the linear model (2D plane strain; one sweep in depth per probe position, 2-10 s each, "
                         "kept in the disk cache)")
    tr.add_argument("--truth-sensor-bias-n", type=finite_float, metavar="N",
                    help="a sensor force bias along the tissue normal (on top of the preset's random one)")
    tr.add_argument("--truth-sensor-drift-n-per-s", type=finite_float, metavar="N_PER_S",
                    help="a sensor drift along the tissue normal, |N_PER_S| <= 0.01")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--sim", nargs="?", const="inmemory", choices=["inmemory", "controller"],
                     help="simulated arm (default): inmemory, or controller (the loopback UR controller)")
    src.add_argument("--host", type=host_name, help="a real UR controller's IP (ur_rtde)")
    p.add_argument("--yes", action="store_true", help="do not ask before moving a real arm")
    p.add_argument("--sensor", default="nano17", choices=list(SENSORS),
                   help="sensor preset: the simulated sensor, and the noise the detectability forecast assumes (with "
                        "--host too) (default nano17; ideal: noise-free; ur5e-builtin: the UR's wrist sensor, refused "
                        "on a simulated arm: its noise is too large for any force limit up to the 10 N cap)")
    p.add_argument("--seed", type=int_range(0, 2 ** 32 - 1),
                   help="simulated sensor noise seed, 0..4294967295 (default 0; not with --host)")
    p.add_argument("--waypoints", type=int_range(MIN_MEASUREMENTS, MAX_WAYPOINTS),
                   help=f"2D: coarse raster waypoints, {MIN_MEASUREMENTS}..{MAX_WAYPOINTS} (default 15; a fit needs "
                        f"{MIN_MEASUREMENTS} probes)")
    p.add_argument("--depth-limit-m", type=float_range(0, HARD_DEPTH_LIMIT_M, unit="m (the hard cap)"),
                   help=f"never plan deeper than this (default {Limits().depth_limit_m}, or {TIP_DEPTH_FRACTION:g} of the "
                        f"tip's radius when that is less; below the tip radius, at least "
                        f"the shallowest useful probe {PlanOptions().min_depth_m:g} m; with --plan the plan's own)")
    p.add_argument("--grid", type=grid_counts, metavar="NXxNY",
                   help="3D block: the coarse raster, an NX x NY grid over the probed area (default "
                        f"{DEFAULT_GRID3D[0]}x{DEFAULT_GRID3D[1]})")
    p.add_argument("--thickness-sigma-m", type=float_range(0, 1.0, lo_open=False, unit="m"), metavar="M",
                   help="3D block: how well the block's thickness is known, 1 sigma in m (default 6 %% of the "
                        "prior's height, what the 2D section assumes: a thickness known to +-10 %%; 0: known exactly, "
                        "not fitted; else between 0.1 and 10 %% of the height). The localizer fits the thickness with "
                        "this prior: a broad, deep stone and a thinner block look alike, so a looser prior costs "
                        "precision and a tighter one than the truth can raise a false stone (docs/localize.md)")
    p.add_argument("--no-fem-correction", action="store_true",
                   help=f"3D block: a stone found within {SIDE_REACH3D_M * 1e3:g} mm of a side is not fitted again with "
                        "fem's contrast at the fitted stone (the 3D table takes every stone as one away from the sides "
                        "and is biased there by several sigma; the correction costs a stone model on the prior's mesh "
                        "per pass, about a minute on a 50 mm block, and runs when the loop would stop): it is flagged "
                        "instead, and its sigmas are not called converged")
    p.add_argument("--refine-waypoints", type=int_range(3, MAX_WAYPOINTS),
                   help=f"waypoints per refinement round, at least 3 (a 3D block: 4; default 2D 10, 3D "
                        f"{DEFAULT_REFINE3D})")
    p.add_argument("--budget-probes", type=int_range(2, MAX_TOTAL_PROBES),
                   help="probe budget over all rounds, at least the coarse raster's waypoints (default 2D 45, 3D "
                        f"{DEFAULT_BUDGET3D})")
    p.add_argument("--target-uncertainty-m", type=positive_float, default=5e-4,
                   help="stop refining when the 1-sigma x and depth uncertainties are below this (default 0.5 mm)")
    p.add_argument("--strategy", choices=["design", "raster"], default="design",
                   help="refinement: design (probes where they shrink the x/depth variance most; default) or raster "
                        "(an even finer raster around the candidate)")
    p.add_argument("--out", required=True, help="output directory (a re-run with the same options resumes)")
    p.add_argument("--fresh", action="store_true",
                   help="start afresh: move the files of a previous run in --out into OUT/previous-<UTC time>/")
    add_ft_options(p, sim_help="with the simulated arm")
    p.add_argument("--no-figure", action="store_true",
                   help="write no fig_run.png (a simulated run otherwise draws it in a child process that loads "
                        "matplotlib on another core while the run works; next to a real arm it is drawn at the end, "
                        "in this process)")
    p.add_argument("--fit-workers", type=int_range(1, 64), metavar="N",
                   help="processes for the localizer's independent fits, forked from this one (the same estimates "
                        "with any N; default: 2 in a simulated run on two or more cores, else 1; next to a real arm "
                        "(--host) only 1: a fork would copy ur_rtde's threads and sockets)")
    p.add_argument("--json", metavar="PATH", help="also write result.json here ('-': standard output)")
    p.set_defaults(func=run)


def _dimension_defaults(args, scene, prior) -> bool:
    """Fill the raster options a user left out with the defaults of the scene's dimension; refuse the other
    dimension's options. True for a 3D block."""
    three_d = bool(prior.is_3d)
    if scene.is_3d != three_d:
        raise UsageError(f"--prior/--plan: the belief ({prior.name}) is "
                         f"{'a 3D block' if three_d else 'a 2D section'} but the scene {args.scene} is not")
    if three_d and args.waypoints is not None:
        raise UsageError(f"--waypoints {args.waypoints}: a 3D block's coarse raster is a grid: give --grid NXxNY")
    if not three_d and args.grid is not None:
        raise UsageError(f"--grid {args.grid[0]}x{args.grid[1]}: a grid is for a 3D block; {args.scene} is a 2D "
                         f"section: give --waypoints N")
    if not three_d and getattr(args, "no_fem_correction", False):
        raise UsageError("--no-fem-correction: an option of a 3D block (a stone near its side is corrected with fem); "
                         "the 2D section's table holds the stone's place near the sides")
    if not three_d and getattr(args, "thickness_sigma_m", None) is not None:
        raise UsageError(f"--thickness-sigma-m {args.thickness_sigma_m:g}: an option of a 3D block; the 2D section's "
                         f"localizer takes the tissue's thickness as known to 6 %")
    if three_d and getattr(args, "thickness_sigma_m", None) is not None:
        top = MAX_THICKNESS_SIGMA * prior.tissue.height_m
        # (run3d.thickness_sigma's ratio, with the localizer's tolerance: the bounds printed here are accepted)
        if args.thickness_sigma_m / prior.tissue.height_m > MAX_THICKNESS_SIGMA * (1 + SIGMA_BOUND_TOL):
            raise UsageError(f"--thickness-sigma-m {args.thickness_sigma_m:g}: at most {top:g} m (10 % of the prior "
                             f"block's height, {prior.tissue.height_m:g} m: the localizer tabulates the block at 0.9 "
                             f"and 1.1 of it)")
        low = MIN_THICKNESS_SIGMA * prior.tissue.height_m
        if 0 < args.thickness_sigma_m / prior.tissue.height_m < MIN_THICKNESS_SIGMA * (1 - SIGMA_BOUND_TOL):
            raise UsageError(f"--thickness-sigma-m {args.thickness_sigma_m:g}: give 0 (the thickness known) or at "
                             f"least {low:g} m (0.1 % of the prior block's height, {prior.tissue.height_m:g} m)")
    if three_d:
        args.grid = args.grid or DEFAULT_GRID3D
    else:
        args.waypoints = args.waypoints or 15
    if three_d and args.refine_waypoints is not None and args.refine_waypoints < 4:
        raise UsageError(f"--refine-waypoints {args.refine_waypoints}: a 3D block's refinement round needs at least 4 "
                         f"waypoints (its design fits x, y, depth and size)")
    args.refine_waypoints = args.refine_waypoints or (DEFAULT_REFINE3D if three_d else 10)
    args.budget_probes = args.budget_probes or (DEFAULT_BUDGET3D if three_d else 45)
    return three_d


def prepare_finite_strain(prior, where_prior: str) -> None:
    """The localizer's finite-strain shape (planner.finite_strain_response) for a prior that has none yet: built
    here, said before and after (a dozen fem sweeps of the prior, some 2 s each), not silently inside the first fit."""
    if unsupported(prior) or prior_finite_strain(prior, build=False) is not None:
        return
    t = time.perf_counter()
    _say(f"no finite-strain shape for this tissue yet: building it before probing ({len(x_nodes(prior))} fem "
         f"sweeps of the prior, about 2 s each on one core; kept in the disk cache when it is on)")
    try:
        shape = prior_finite_strain(prior)
    except (RuntimeError, ArithmeticError, ValueError) as e:
        raise UsageError(f"{where_prior} cannot be modelled: {e} (check the tissue and indenter moduli and "
                         f"sizes)") from None
    if shape is not None:
        _say(f"finite-strain shape built in {time.perf_counter() - t:.0f} s")


def _say(msg: str) -> None:
    print(f"palpate run: {msg}", file=sys.stderr, flush=True)


def run(args) -> int:
    with contextlib.ExitStack() as on_exit:     # ends a figure child not asked to draw (an error, a fault)
        return _run(args, on_exit)


def _run(args, on_exit: contextlib.ExitStack) -> int:
    t_wall = time.perf_counter()
    # ---- everything checked before OUT is touched
    out = Path(args.out)
    check_output_dir(args.out, "--out")
    if (out / "pieces").is_dir():       # as a study refuses a run's directory (its pieces beside probes would block it)
        raise UsageError(f"--out {args.out}: a study's directory (its pieces/); a run goes into a directory of its own")
    check_output_file(args.json, "--json", inputs={"SCENE": args.scene, "--plan": args.plan,
                                                        "--prior": args.prior})
    if args.host and args.seed is not None:     # (it did nothing next to a real arm, silently)
        raise UsageError(f"--seed {args.seed}: the simulated sensor's noise seed; a real arm (--host) has real noise: "
                         f"drop it")
    args.seed = 0 if args.seed is None else args.seed
    if args.json and args.json != "-":
        j = Path(args.json).absolute()
        if j.parent == out.absolute() and (j.name in RUN_FILES or j.name.startswith(("plan_round", "previous-"))):
            raise UsageError(f"--json {args.json}: would overwrite the run's own {j.name}; choose another path")
    scene = load_scene(args.scene)
    belief = load_scene(args.prior, "--prior").prior() if args.prior else None
    if args.prior and args.prior not in BUILTIN and not conditions_of(args.prior).ideal:
        _say(f"note: --prior {args.prior}: its [truth] table is not used (the belief is the scene's prior; the "
             f"simulated world's conditions come from SCENE's file or the --truth-* options)")
    cond = truth_conditions(args, scene)
    check_ft(args, sim=not args.host, real_host=bool(args.host))
    if args.host and args.fit_workers not in (None, 1):
        raise UsageError(f"--fit-workers {args.fit_workers}: next to a real arm (--host) the fits run in the driver's "
                         f"own process (a fork would copy ur_rtde's threads and sockets): give 1 or leave it out")
    if args.plan and (args.waypoints is not None or args.grid is not None or args.depth_limit_m is not None):
        drop = ("--waypoints" if args.waypoints is not None else "--grid" if args.grid is not None
                else "--depth-limit-m")
        raise UsageError(f"--plan {args.plan}: the plan holds the coarse raster and its limits; drop {drop}")
    if args.plan:
        plan0 = load_plan_option(args.plan)
        problems, bad = check_plan(plan0)       # what the driver would refuse: before anything starts
        bad = {**unfelt_probes(plan0), **bad}   # (and the probes it would stop at once: contact_unfelt)
        refused = problems + [f"probe {k}: {v}" for k, v in sorted(bad.items())]
        if refused:
            more = f" (and {len(refused) - 1} more)" if len(refused) > 1 else ""
            raise UsageError(f"--plan {args.plan}: refused before any motion: {refused[0]}{more}")
        prior = plan_prior(plan0)
        if prior.stones:
            raise UsageError(f"--plan {args.plan}: the plan's scene has stones; a plan holds the prior scene only")
        if belief is not None and belief.key() != prior.key():
            raise UsageError(f"--prior {args.prior}: differs from the prior scene of --plan {args.plan}; give one "
                             f"of them (the plan was made on its own prior)")
        if belief is None and prior.key() != scene.prior().key():
            _say(f"the plan's prior scene differs from {args.scene}'s: the simulated truth is not the belief")
    else:
        prior = belief if belief is not None else scene.prior()
        plan0 = None
    where_prior = (f"--prior {args.prior}" if belief is not None else
                   f"--plan {args.plan}: its prior scene" if args.plan else f"scene {args.scene}")
    if not args.host:
        check_same_extent(scene, prior, where_prior, args.scene)
    three_d = _dimension_defaults(args, scene, prior)
    n_coarse = len(plan0.probes) if plan0 is not None else (
        args.grid[0] * args.grid[1] if three_d else args.waypoints)
    R = prior.indenter.radius_m
    lim = run_limits(args, R).depth_limit_m
    if plan0 is None and not lim < R:     # the run plans to this depth limit
        raise UsageError(f"{where_prior}: indenter.radius_m = {R:g} m is not above --depth-limit-m ({lim:g} m; the "
                         f"tissue would wrap the tip's sides): give --depth-limit-m D with D below the radius")
    shallowest = PlanOptions().min_depth_m
    if plan0 is None and lim < shallowest:
        if args.depth_limit_m is None:
            raise UsageError(f"{where_prior}: indenter.radius_m = {R:g} m: a run's default depth limit, "
                             f"{TIP_DEPTH_FRACTION:g} of it ({lim:g} m), is below the shallowest useful probe, "
                             f"{shallowest:g} m: " + (f"give --depth-limit-m D with {shallowest:g} <= D < {R:g}"
                                                     if shallowest < R else
                                                     "no depth below the tip's radius reaches it"))
        raise UsageError(f"--depth-limit-m {lim:g}: below the shallowest useful probe, {shallowest:g} m")
    if plan0 is None and args.depth_limit_m is None and (said := default_depth_said(R)):
        _say(f"depth limit {said}; --depth-limit-m to choose")
    need = MIN_MEASUREMENTS3D if three_d else MIN_MEASUREMENTS
    if n_coarse < need:        # a --plan or --grid too small for the first round's fit
        what = f"--plan {args.plan}" if plan0 is not None else f"--grid {args.grid[0]}x{args.grid[1]}"
        raise UsageError(f"{what}: the coarse raster has {n_coarse} waypoints; the first round's fit needs at least "
                         f"{need} probes")
    if args.budget_probes < n_coarse:
        raise UsageError(f"--budget-probes {args.budget_probes} must be at least the coarse raster's {n_coarse} "
                         f"waypoints")
    if not args.host:          # the simulated sensor is this preset: a run the driver would stop is refused first
        check_simulated_sensor(args.sensor, plan0.limits.force_limit_n if plan0 is not None else
                               Limits().force_limit_n)
    opts = run_options(args, scene, cond, belief)
    check_fresh_inputs(args, out)
    resume = check_resume(out, opts, args.fresh)
    if resume and (out / "plan_round0.json").exists():
        try:
            saved = Plan.load(out / "plan_round0.json")
        except (UsageError, ValueError) as e:
            raise UsageError(f"--out {out}: cannot resume: {e}; use --fresh or another --out") from None
        plan0 = saved
        if not three_d:
            for line in resuming_note(out).splitlines():
                _say(line)
    fig_child = None
    if not args.no_figure and not args.host:    # simulated: matplotlib loads in a child meanwhile (app.figchild)
        fig_child = FigureChild.start(_say)
        if fig_child is not None:
            on_exit.callback(fig_child.close)
    if three_d:       # the 3D flow (loaded for a block only: the 2D commands never import the 3D path)
        from app.commands.run3d import RunContext, run_block
        return run_block(args, RunContext(t_wall=t_wall, out=out, scene=scene, prior=prior, plan0=plan0, cond=cond,
                                          opts=opts, resume=resume, fig_child=fig_child, on_exit=on_exit))
    if plan0 is None:
        _say(f"planning a {args.waypoints}-waypoint raster on {prior.name}")
        try:
            plan0 = plan_raster(prior, n_waypoints=args.waypoints, limits=run_limits(args, prior.indenter.radius_m))
        except PlanError as e:
            raise PlanError(plan_options_hint(str(e), args)) from None
        refuse_unfelt(plan0, args)
    if warning := below_contact_threshold(plan0, RUN_THRESHOLD_HINT):
        _say("warning: " + warning)
    try:
        sur = load_surrogate(prior, build=False)
    except FileNotFoundError:       # no table for this tissue: built beside the coarse raster (planner.pending)
        try:
            check_table_fits(prior)
        except ValueError as e:
            raise UsageError(f"{where_prior} cannot be modelled: {e}") from None
        _say("no fem surrogate table for this tissue yet (planner/surrogate.py says which scene fields select one): "
             "building it in the background (a few hundred fem models: 2-15 minutes on 2 cores, by the section's "
             "size and mesh) while the coarse raster is probed")
        sur = PendingSurrogate(prior, _say)
    except (RuntimeError, ArithmeticError, ValueError) as e:   # e.g. fem's contact solve on an implausible prior
        raise UsageError(f"{where_prior} cannot be modelled: {e} (check the tissue and indenter moduli and "
                         f"sizes)") from None

    def detectable(table, when: str = "before probing") -> tuple[dict, list]:
        try:
            det = detectability(prior, sensor=args.sensor, force_limit_n=plan0.limits.force_limit_n,
                                depth_limit_m=plan0.limits.depth_limit_m,
                                x_positions_m=[p.x_m for p in plan0.probes], surrogate=table, motion=plan0.motion,
                                force_fraction=plan0.options.force_fraction, min_depth_m=plan0.options.min_depth_m)
        except (RuntimeError, ArithmeticError, ValueError) as e:
            raise UsageError(f"{where_prior} cannot be modelled: {e} (check the tissue and indenter moduli and "
                             f"sizes)") from None
        smallest = smallest_detectable(det["rows"])
        nothing = (f"no stone the table covers (diameters up to {max(r['diameter_m'] for r in det['rows']) * 1e3:g} "
                   f"mm) at any depth: the coarse raster's probes are too few or too weak for the sensor's noise "
                   f"(more waypoints, a deeper depth limit or a quieter sensor may help); a NO STONE answer will mean "
                   f"little") if det["rows"] else "nothing"
        _say(f"detectable {when} (coarse raster, sensor {args.sensor}): " + (
            (describe_smallest(smallest) or nothing)
            if det["usable"] else det["reason"]))
        return det, smallest

    if not isinstance(sur, PendingSurrogate):
        det, smallest = detectable(sur)
    prepare_finite_strain(prior, where_prior)
    stats = new_stats()
    sim_arm: dict = {}
    cleanup = contextlib.ExitStack()       # controller process and ur_rtde links, closed when probing ends
    execute, where, truth = choose_executor(args, out, scene, cond, plan0, resume, stats, cleanup, sim_arm, _say)
    on_exit.enter_context(holding(out))      # one process at a time in OUT (app.outlock)
    open_out(args, out, opts, _say)         # from here on files are written (never deleted: --fresh moves them aside)
    _say(f"probing on the {where}")
    t_first: dict = {}

    def execute_timed(plan_or_x, k):
        t_first.setdefault("probing_started_s", time.perf_counter() - t_wall)
        return execute(plan_or_x, k)

    plan_round = round_planner(plan0, out)
    # (not while the table is built in the background: both cores are the build's)
    fit_workers = 1 if isinstance(sur, PendingSurrogate) else workers_for_fits(args)

    status, fault = "ok", None
    try:
        res = adaptive(prior, execute_timed, coarse_x_m=[p.x_m for p in plan0.probes], plan_round=plan_round,
                       budget_probes=args.budget_probes, n_refine=args.refine_waypoints,
                       target_m=args.target_uncertainty_m, surrogate=sur, progress=_say,
                       strategy=args.strategy, workers=fit_workers)
        stats["clean_end"] = True      # probing ended without a fault: the control script is stopped at the end
    except RunAborted as e:
        status = "interrupted" if e.report.status == "interrupted" else "fault"
        fault, res = e.report.to_dict(), None
        stats["n_probes"] = measured_on_disk(out)       # (an interrupted round's too: kept, resumed)
        _say(str(e))
    except KeyboardInterrupt:       # between rounds (a fit, a plan, fem): the arm is at rest; 130 follows
        _say(f"{INTERRUPTED_AT_REST} ({measured_on_disk(out)} probes in {out})")
        raise
    except TableBuildError as e:    # the measured probes are on disk; a re-run resumes them
        raise UsageError(f"{where_prior} cannot be modelled: {e} (check the tissue and indenter moduli and "
                         f"sizes)") from None
    finally:
        cleanup.close()
    if isinstance(sur, PendingSurrogate):       # built beside the coarse raster: what it could detect, stated now
        try:
            sur = sur.result()
        except TableBuildError as e:
            raise UsageError(f"{where_prior} cannot be modelled: {e}") from None
        det, smallest = detectable(sur, "once the table was built")
    result = {"scene": args.scene, "prior": prior.name, "where": where, "status": status,
              "strategy": args.strategy}
    if res is not None:
        # the final estimate once more, with the depth's profile-likelihood interval (prior + measurements only)
        if res.measurements is not None and len(res.measurements) >= MIN_MEASUREMENTS:
            loc = res.localization = localize(prior, res.measurements, sur, profile=True, workers=fit_workers)
        else:
            loc = res.localization
        result.update(loc.to_dict())
        result.update({"probes_used": res.probes_used, "stop_reason": res.stop_reason,
                       "rounds": [{"index": r.index, "n_probes": r.n_probes, "x_m": r.x_m, "depth_m": r.depth_m,
                                   "localization": r.localization, "elapsed_s": r.elapsed_s} for r in res.rounds]})
    else:
        loc = Localization(detected=False, lr=float("nan"), lr_threshold=float("nan"))
        result.update(loc.to_dict())
        result.update({"probes_used": stats["n_probes"], "fault": fault})
    result["time"] = {"wall_s": time.perf_counter() - t_wall, **t_first, "robot_s": stats["controller_s"],
                      "planned_s": stats["planned_s"]}
    result["detectability"] = {"sensor": det["sensor"], "usable": det["usable"], "reason": det["reason"],
                               "probe_sigma_n": det["sigma_n"],
                               "smallest_detectable": smallest}
    result["surrogate"] = {"build_s": sur.build_s, "bounds": {k: list(v) for k, v in sur.bounds.items()}}
    if truth is not None:        # comparison only, after the fact
        st = [{"x_m": s.x_m, "depth_m": s.depth_m, "diameter_m": s.diameter_m} for s in truth.stones]
        result["sim"] = {"sensor": args.sensor, "seed": args.seed, "truth_stones": st,
                         "truth_tissue": {"youngs_pa": truth.tissue.youngs_pa, "poisson": truth.tissue.poisson,
                                          "height_m": truth.tissue.height_m,
                                          "youngs_scale_to_prior": truth.tissue.youngs_pa / prior.tissue.youngs_pa},
                         "truth_conditions": cond.to_dict() if cond is not None else None}
        if st and res is not None and loc.detected:
            result["sim"]["error"] = {"x_m": loc.x_m - st[0]["x_m"], "depth_m": loc.depth_m - st[0]["depth_m"],
                                      "diameter_m": loc.diameter_m - st[0]["diameter_m"]}
    if sim_arm.get("arm") is not None:
        rr = sim_range_report(sim_arm["arm"])
        if rr is not None:
            result.setdefault("sim", {})["force_beyond_model_range"] = rr
            _say(f"warning: {rr['note']} ({rr['samples_beyond_model_range']} samples, deepest "
                 f"{rr['deepest_m'] * 1e3:.2f} mm)")
    reach = probe_reach(plan0, prior_force(plan0))   # what a depth limit a warning suggests may be
    head = conclude(result, out, loc, res, describe(loc, reach) if res is not None else "", status, fault, _say,
                    three_d=False, tissue=prior.tissue)
    (out / "result.json").write_text(json.dumps(result, indent=1))
    write_json(args.json, result)
    if res is not None and localized(loc) and not args.no_figure:   # nothing to draw unless a fit was made
        from planner.plots_run import run_figure
        fig = run_figure(prior, loc, res.measurements, surrogate=sur,
                         truth_stones=truth.stones if truth is not None else (), rounds=res.rounds,
                         title=f"palpate run {args.scene}:\n" + describe(loc, reach).replace("; warning: ", "\nwarning: "))
        if fig_child is not None:
            fig_child.draw(out / "fig_run.png", fig, _say)
        else:
            draw_run(out / "fig_run.png", fig)
    print(head
          + f"; {result['probes_used']} probes; results in {out}",
          file=sys.stderr if args.json == "-" else sys.stdout)
    return exit_code(status)
