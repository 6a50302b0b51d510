"""`palpate plan SCENE --out plan.json [--plots DIR]`: the CasADi raster plan for a UR5e."""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from app.commands.output import write_json
from app.errors import UsageError
from app.figure_names import PLAN_FIGURES
from app.options import (
    MAX_WAYPOINTS,
    check_output_dir,
    check_output_file,
    finite_float,
    float_list,
    float_range,
    grid_counts,
    int_range,
    load_scene,
    polygon_vertices,
    positive_float,
    refuse_figures,
)
from core import ur5e
from core.contracts import (
    HARD_FORCE_LIMIT_N,
    HARD_PROBE_SPEED_M_S,
    HARD_TOOL_SPEED_M_S,
    MAX_APPROACH_HEIGHT_M,
    MAX_DWELL_S,
    MIN_APPROACH_HEIGHT_M,
    MIN_PROBE_SPACING_M,
    MIN_PROBE_SPEED_M_S,
    MIN_TOOL_SPEED_M_S,
    TIP_DEPTH_FRACTION,
    Frames,
    Limits,
    Motion,
    PlanError,
    PlanOptions,
    default_depth_limit_m,
    default_depth_said,
)
from planner.area import Region, default_block_pose, default_region, grid_positions
from planner.plan import DEFAULT_GRID, plan_raster
from planner.raster import default_tissue_pose, interval_positions
from robot.safety import HARD_BOX_MAX_M, HARD_BOX_MIN_M, MAX_TCP_OFFSET_M, check_plan

LIM, MOT, OPT = Limits(), Motion(), PlanOptions()      # the defaults, defined once in core.contracts

DESCRIPTION = """Plan a probing raster over the tissue's top surface for a UR5e and write a plan file.

The planner sees only the prior scene (the tissue without its stones). For every waypoint it picks the
indentation depth from fem's force prediction for that prior tissue: as deep as the limits allow, i.e. where the
predicted force reaches --force-fraction x --force-limit-n (head-room for stiffer-than-predicted tissue), never
deeper than --depth-limit-m. Then one IPOPT problem over the whole raster finds UR5e joint targets for the
approach and indent poses: tip on target, tool axis within --tilt-tol-deg of the inward surface normal, joint
limits, one IK branch throughout (no elbow/wrist flips), a margin from the singularities, minimal joint travel.
Finally every move is timed under the UR joint and tool speed/acceleration limits.

Frames: poses are ur_rtde's [x, y, z, rx, ry, rz] (m, rotation vector) of the TCP in the base frame. The tissue
frame has its origin at the top-left corner of the section, x along the width, z the outward normal of the top
surface; --tissue-pose gives it in the base frame (default: the section lying on the arm's table, width along
base y, centred 0.40 m in front of the base: 0.40 -W/2 H 0 0 pi/2).

A 3D block (a scene with tissue.length_m) is probed over an area of its top face: a grid (--grid NXxNY, default
7x7, or --spacing-m) over a rectangle (--region x0,y0,x1,y1; default fem's probed patch, analysis.patch_m, minus
--margin-m, default the tip radius) or any polygon (--polygon "x,y;x,y;..."), in the tissue frame (y along the
block's length), visited in serpentine rows. Every probe's footprint must stay on the probed patch. Default pose:
the block's middle 0.40 m in front of the base (0.40+L/2 -W/2 H 0 0 pi/2; tissue y along base -x)."""

EPILOG = """examples:
  palpate plan paper --out plan.json --plots out/                 15 waypoints, 5 mm margins, fem depths
  palpate plan paper --out plan.json --spacing-m 0.002 --margin-m 0.008
  palpate plan paper --out fine.json --x-min-m 0.030 --x-max-m 0.040 --waypoints 11   refine an interval
  palpate plan paper --out plan.json --force-limit-n 0.5 --depth-limit-m 0.0045
  palpate plan scene.toml --out plan.json --tissue-pose 0.45 -0.035 0.08 0 0 1.5708 --tcp-offset 0 0 0.12 0 0 0
  palpate plan block3d --out plan.json --grid 10x10 --plots out/  3D: 100 probes over the probed patch
  palpate plan block3d --out plan.json --grid 8x8 --region 0.02,0.02,0.05,0.04
  palpate plan block3d --out plan.json --spacing-m 0.004 --polygon "0.02,0.02;0.05,0.02;0.035,0.05"
exit status: 0 planned, 2 infeasible request (the message names the option to change)."""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("plan", help="CasADi raster plan for a UR5e (plan.json)", description=DESCRIPTION,
                              epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", help="built-in scene name or TOML file (stones are ignored: the planner sees the prior)")
    p.add_argument("--out", required=True, metavar="PATH", help="plan file to write (JSON, versioned)")
    p.add_argument("--plots", metavar="DIR", help="write plan_raster.png (3D: plan_area.png) and plan_joints.png here")
    p.add_argument("--json", metavar="PATH", help="machine-readable summary (timings, solver status, ranges)")
    r = p.add_argument_group("raster (tissue frame x, along the top surface)")
    g = r.add_mutually_exclusive_group()
    g.add_argument("--waypoints", type=int_range(2, MAX_WAYPOINTS), metavar="N",
                   help=f"number of waypoints, ends included, 2..{MAX_WAYPOINTS} (default 15)")
    g.add_argument("--spacing-m", type=positive_float, metavar="S", help="waypoint spacing instead of a count")
    g.add_argument("--grid", type=grid_counts, metavar="NXxNY",
                   help=f"3D: an NX x NY grid over the region, ends included (default {DEFAULT_GRID[0]}x{DEFAULT_GRID[1]})")
    r.add_argument("--margin-m", type=finite_float, default=None,
                   help="keep this far from the side edges (default 0.005; 3D: from the probed patch's edges, "
                        "default the tip radius)")
    a3 = r.add_mutually_exclusive_group()
    a3.add_argument("--region", type=float_list(4, "x0,y0,x1,y1 in m"), metavar="X0,Y0,X1,Y1",
                    help="3D: raster this rectangle of the top face (tissue frame, m)")
    a3.add_argument("--polygon", type=polygon_vertices, metavar="\"X,Y;X,Y;...\"",
                    help="3D: raster this polygon of the top face (tissue-frame vertices, m)")
    r.add_argument("--x-min-m", type=finite_float, help="raster only [x-min, x-max] (adaptive refinement); overrides margins")
    r.add_argument("--x-max-m", type=finite_float, help="see --x-min-m")
    d = p.add_argument_group("depth and force")
    d.add_argument("--force-limit-n", type=float_range(0, HARD_FORCE_LIMIT_N, unit="N (the hard cap)"), default=LIM.force_limit_n,
                   help=f"never plan above this contact force (default {LIM.force_limit_n})")
    d.add_argument("--depth-limit-m", type=positive_float,
                   help=f"never deeper than this (default {Limits().depth_limit_m}, or {TIP_DEPTH_FRACTION:g} of the "
                        f"tip's radius when that is less; keep it below the tip radius)")
    d.add_argument("--force-fraction", type=float_range(0, 1), default=OPT.force_fraction,
                   help="plan to at most this fraction of the force limit on the prior tissue (default 0.5)")
    d.add_argument("--min-depth-m", type=positive_float, default=OPT.min_depth_m,
                   help="shallowest useful probe; refused if even this exceeds the force budget (default 0.001)")
    d.add_argument("--depth-m", type=positive_float, help="fixed depth for every probe instead of the force-based choice")
    a = p.add_argument_group("arm and motion")
    a.add_argument("--tissue-pose", type=finite_float, nargs=6, metavar=("X", "Y", "Z", "RX", "RY", "RZ"),
                   help="tissue frame in the base frame (m, rotation vector rad)")
    a.add_argument("--tcp-offset", type=finite_float, nargs=6, metavar=("X", "Y", "Z", "RX", "RY", "RZ"),
                   help="probe tip in the flange frame, as for setTcp (default 0 0 0.10 0 0 0)")
    a.add_argument("--approach-height-m", type=float_range(MIN_APPROACH_HEIGHT_M, MAX_APPROACH_HEIGHT_M, lo_open=False, unit="m"),
                   default=MOT.approach_height_m,
                   help="tip above the surface before descending")
    a.add_argument("--approach-speed-m-s", type=float_range(MIN_TOOL_SPEED_M_S, HARD_TOOL_SPEED_M_S, lo_open=False, unit="m/s"),
                   default=MOT.approach_speed_m_s,
                   help="tool speed between probes")
    a.add_argument("--probe-speed-m-s", type=float_range(MIN_PROBE_SPEED_M_S, HARD_PROBE_SPEED_M_S, lo_open=False, unit="m/s"),
                   default=MOT.probe_speed_m_s,
                   help="tool speed of the descent")
    a.add_argument("--dwell-s", type=float_range(0, MAX_DWELL_S, unit="s"), default=MOT.dwell_s, help="hold at depth while sampling")
    a.add_argument("--tilt-tol-deg", type=float_range(0, 90, hi_open=True, unit="deg"), default=math.degrees(OPT.tilt_tol_rad),
                   help="tool axis within this of the normal (default 0.5)")
    a.add_argument("--branch", default=",".join(map(str, OPT.branch)), metavar="S,E,W",
                   help="IK branch signs (shoulder, elbow, wrist); default 1,1,-1 = elbow up, tool down (a plan whose "
                        "joints go below the base's plane is said: only the tool is checked against the workspace)")
    p.set_defaults(func=run)


def run(args) -> int:
    check_output_file(args.out, "--out", replaced=True, inputs={"SCENE": args.scene})
    check_output_dir(args.plots, "--plots")
    check_output_file(args.json, "--json", inputs={"SCENE": args.scene})
    refuse_figures(args.plots, PLAN_FIGURES, {"--out": args.out, "--json": args.json})
    if args.json and args.out and args.json != "-" and Path(args.json).absolute() == Path(args.out).absolute():
        raise UsageError(f"--json {args.json}: is the plan's own file (--out); give another path or '-'")
    scene = load_scene(args.scene)
    tip = scene.indenter.radius_m
    by_default = args.depth_limit_m is None
    if by_default:                 # (said once the options are checked: bad input gets one line)
        args.depth_limit_m = default_depth_limit_m(tip)
        if args.depth_limit_m < args.min_depth_m and default_depth_said(tip):    # (else: the checks below)
            of = f"{TIP_DEPTH_FRACTION:g} of it, " if default_depth_said(tip) else ""
            raise UsageError(f"scene {args.scene}: indenter.radius_m = {tip:g} m: the default depth limit "
                             f"({of}{args.depth_limit_m:g} m) is below --min-depth-m "
                             f"{args.min_depth_m:g} m (the shallowest useful probe): "
                             + (f"give --depth-limit-m D with {args.min_depth_m:g} <= D < {tip:g}"
                                if args.min_depth_m < tip else
                                "no depth below the tip's radius reaches it (a lower --min-depth-m may)"))
    lim_said = (f"--depth-limit-m {args.depth_limit_m:g} m" if not by_default else
                f"the default depth limit {args.depth_limit_m:g} m ("
                + (f"{TIP_DEPTH_FRACTION:g} of the tip's radius" if default_depth_said(tip) else "the 4 mm default")
                + "; --depth-limit-m to choose one below the radius)")
    if not args.depth_limit_m < tip:
        raise UsageError(f"--depth-limit-m {args.depth_limit_m:g} must be below the tip radius {tip:g} m "
                         f"(scene indenter.radius_m)")
    if args.depth_m is not None and not args.depth_m <= args.depth_limit_m:
        raise UsageError(f"--depth-m {args.depth_m:g} must be at most {lim_said}")
    if args.depth_m is not None and not args.depth_m >= args.min_depth_m:
        raise UsageError(f"--depth-m {args.depth_m:g} is below --min-depth-m {args.min_depth_m:g} m (the shallowest "
                         f"useful probe{'' if args.min_depth_m != OPT.min_depth_m else ', by default'}): give a depth "
                         f"at least that, or lower --min-depth-m too")
    if not args.min_depth_m <= args.depth_limit_m:
        raise UsageError(f"--min-depth-m {args.min_depth_m:g} must be at most {lim_said}")
    is_3d = scene.is_3d
    if is_3d:
        for opt, v in (("--waypoints", args.waypoints), ("--x-min-m", args.x_min_m), ("--x-max-m", args.x_max_m)):
            if v is not None:
                raise UsageError(f"{opt} is for a 2D section; {scene.name!r} is a 3D block: give --grid NXxNY or "
                                 f"--spacing-m, and --region or --polygon")
    else:
        for opt, v in (("--grid", args.grid), ("--region", args.region), ("--polygon", args.polygon)):
            if v is not None:
                raise UsageError(f"{opt} is for a 3D block; {scene.name!r} is a 2D section (no tissue.length_m): "
                                 f"give --waypoints or --spacing-m")
    margin_m = 0.005 if (args.margin_m is None and not is_3d) else args.margin_m
    if not is_3d and (args.x_min_m is not None or args.x_max_m is not None):
        lo = args.x_min_m if args.x_min_m is not None else margin_m
        hi = args.x_max_m if args.x_max_m is not None else scene.tissue.width_m - margin_m
        for opt, v in (("--x-min-m", args.x_min_m), ("--x-max-m", args.x_max_m)):
            if v is not None and not 0.0 <= v <= scene.tissue.width_m:
                raise UsageError(f"{opt} {v:g}: must lie on the surface, 0 to {scene.tissue.width_m:g} m "
                                 f"(tissue.width_m of {scene.name!r})")
        if not lo < hi:
            raise UsageError(f"--x-min-m {lo:g} must be below --x-max-m {hi:g} (the raster's interval, m; the end "
                             f"not given is the margin's, {margin_m:g} m from the side)")
        n = args.waypoints or (2 if args.spacing_m else 11)
        if not hi - lo >= MIN_PROBE_SPACING_M * (n - 1):
            given = " and ".join(o for o, v in (("--x-min-m", args.x_min_m), ("--x-max-m", args.x_max_m))
                                 if v is not None)
            raise UsageError(f"{given}: the raster's interval [{lo:g}, {hi:g}] m (the other end from the margin "
                             f"{margin_m:g} m when not given) is too short for {n} waypoints"
                             f"{'' if args.waypoints else ' (the default with --x-min-m or --x-max-m)'} at least "
                             f"{MIN_PROBE_SPACING_M:g} m apart (one spot for the arm)")
    if args.spacing_m is not None and not is_3d:
        lo = args.x_min_m if args.x_min_m is not None else margin_m
        hi = args.x_max_m if args.x_max_m is not None else scene.tissue.width_m - margin_m
        n = int(math.floor((hi - lo) / args.spacing_m + 1e-9)) + 1 if hi > lo else 0
        if not 2 <= n <= MAX_WAYPOINTS:
            raise UsageError(f"--spacing-m {args.spacing_m:g} gives {n} waypoints over [{lo:g}, {hi:g}] m; "
                             f"allowed: 2..{MAX_WAYPOINTS}")
    if args.spacing_m is not None and is_3d:
        t = scene.tissue
        n_max = (math.floor(t.width_m / args.spacing_m + 1e-9) + 1) * (math.floor(t.length_m / args.spacing_m + 1e-9) + 1)
        if n_max > 4 * MAX_WAYPOINTS:      # a cheap bound before the grid is made; the exact count is checked below
            raise UsageError(f"--spacing-m {args.spacing_m:g} gives up to {n_max} waypoints over the top face; "
                             f"allowed: at most {MAX_WAYPOINTS}")
    limits = Limits(force_limit_n=args.force_limit_n, depth_limit_m=args.depth_limit_m)
    motion = Motion(approach_height_m=args.approach_height_m, approach_speed_m_s=args.approach_speed_m_s,
                    probe_speed_m_s=args.probe_speed_m_s, dwell_s=args.dwell_s)
    frames = None
    check_frames(args)
    if args.tissue_pose or args.tcp_offset:
        t = scene.tissue
        pose = (default_block_pose(t.width_m, t.length_m, t.height_m) if is_3d
                else default_tissue_pose(t.width_m, t.height_m))
        frames = Frames(tissue_pose_base=list(args.tissue_pose or pose),
                        tcp_offset=list(args.tcp_offset or Frames().tcp_offset))
    try:
        branch = tuple(int(s) for s in args.branch.split(","))
        if len(branch) != 3 or any(s not in (-1, 1) for s in branch):
            raise ValueError
    except ValueError:
        raise UsageError(f"--branch must be three signs like 1,1,-1, got {args.branch!r}") from None
    options = PlanOptions(branch=list(branch), tilt_tol_rad=math.radians(args.tilt_tol_deg),
                          force_fraction=args.force_fraction, min_depth_m=args.min_depth_m)
    if by_default and (said := default_depth_said(tip)):
        print(f"palpate plan: depth limit {said}; --depth-limit-m to choose", file=sys.stderr)
    try:
        if is_3d:
            plan = _plan_area(scene, args, margin_m, limits, motion, frames, options)
        else:
            x = None
            if args.x_min_m is not None or args.x_max_m is not None:
                lo = args.x_min_m if args.x_min_m is not None else margin_m
                hi = args.x_max_m if args.x_max_m is not None else scene.tissue.width_m - margin_m
                n = args.waypoints if (args.waypoints or args.spacing_m) else 11
                x = interval_positions(lo, hi, n=None if args.spacing_m else n, spacing_m=args.spacing_m)
            plan = plan_raster(scene, n_waypoints=args.waypoints, spacing_m=args.spacing_m, margin_m=margin_m,
                               x_positions_m=x, depth_m=args.depth_m, limits=limits, motion=motion, frames=frames,
                               options=options)
    except (PlanError, ValueError) as e:
        raise UsageError(f"cannot plan: {e}") from None
    problems, bad = check_plan(plan)           # what the driver would refuse (the arm's own clearance, say)
    if problems or bad:
        first = problems[0] if problems else f"probe {min(bad)}: {bad[min(bad)]}"
        raise UsageError(f"cannot plan: the driver would refuse this plan ({len(bad)} of {len(plan.probes)} probes"
                         f"{' and the plan' if problems else ''}): {first}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    plan.save(out)
    figs = []
    if args.plots:
        from planner.plots_plan import plot_plan
        figs = [str(f) for f in plot_plan(plan, args.plots)]
    s = summary(plan, out, figs)
    write_json(args.json, s)
    sv = plan.notes["solver"]
    stream = sys.stderr if args.json == "-" else sys.stdout      # --json -: standard output holds the JSON alone
    print(f"planned {s['n_probes']} probes on {plan.scene['name']}: depth {s['depth_m']['min'] * 1e3:.2f}-"
          f"{s['depth_m']['max'] * 1e3:.2f} mm, predicted force {s['predicted_force_n']['min']:.3g}-"
          f"{s['predicted_force_n']['max']:.3g} N (limit {limits.force_limit_n:g} N), "
          f"execution ~{plan.total_time_s:.1f} s; IPOPT {sv['status']} in {sv['iterations']} iterations, "
          f"{sv['solve_s'] * 1e3:.0f} ms -> {out}", file=stream)
    if is_3d:
        r = plan.notes["raster"]
        print(f"raster: {r['order']}, tool travel between probes {r['travel_m'] * 1e3:.0f} mm (row-major "
              f"{r['travel_row_major_m'] * 1e3:.0f} mm, no order below {r['travel_lower_bound_m'] * 1e3:.0f} mm); "
              f"planning took {plan.notes['times_s']['total']:.2f} s", file=stream)
    for f in figs:
        print(f"figure: {f}", file=stream)
    for warning in (below_contact_threshold(plan), joints_below_base(plan)):
        if warning:
            print(f"palpate plan: warning: {warning}", file=sys.stderr)
    return 0


def check_frames(args) -> None:
    """--tcp-offset and --tissue-pose within what the driver's safety check takes (robot.safety: the tip within
    MAX_TCP_OFFSET_M of the flange and beyond it, the tissue inside the arm's hard box), and rotation vectors no
    longer than 2 pi: one line naming the option (1e308 overflowed inside the planner, "math domain error")."""
    for opt, v in (("--tcp-offset", args.tcp_offset), ("--tissue-pose", args.tissue_pose)):
        if v is None:
            continue
        given = " ".join(f"{a:g}" for a in v)
        if math.hypot(*v[3:]) > 2 * math.pi:
            raise UsageError(f"{opt} {given}: the rotation vector (rx, ry, rz) is {math.hypot(*v[3:]):.3g} rad long; "
                             f"allowed: at most 2 pi (its length is the angle)")
        if opt == "--tcp-offset" and not (v[2] > 0 and math.hypot(*v[:3]) <= MAX_TCP_OFFSET_M):
            raise UsageError(f"{opt} {given}: the tip must lie beyond the flange (z > 0) and within "
                             f"{MAX_TCP_OFFSET_M:g} m of it")
        if opt == "--tissue-pose" and not all(lo <= a <= hi for a, lo, hi in zip(v[:3], HARD_BOX_MIN_M,
                                                                                 HARD_BOX_MAX_M)):
            box = " x ".join(f"[{lo:g}, {hi:g}]" for lo, hi in zip(HARD_BOX_MIN_M, HARD_BOX_MAX_M))
            raise UsageError(f"{opt} {given}: out of reach: the tissue's origin must lie in the arm's workspace box "
                             f"{box} m (base frame)")


# what a run's warning suggests (a run refuses --depth-limit-m beside --plan)
RUN_THRESHOLD_HINT = ("plan with `palpate plan`, lower motion.contact_threshold_n in the plan file and pass it with "
                      "--plan")


JOINT_NAMES = ("shoulder", "elbow", "wrist 1", "wrist 2", "wrist 3")


def joints_below_base(plan) -> str:
    """A warning when a planned configuration puts a joint of the arm below the base's plane (z < 0 in the base
    frame; "" otherwise): only the tool is checked against the workspace box, and with the tissue on the table the
    arm stands on (the default tissue pose) such a joint is in the table. A session-59 review planned `--branch
    1,-1,-1` without a word: the elbow 0.17 m below the base."""
    low, where = 0.0, None
    for p in plan.probes:
        for q in (p.q_approach_rad, p.q_indent_rad):
            z = ur5e.joint_origins(q)[:, 2]
            k = int(np.argmin(z))
            if z[k] < low:
                low, where = float(z[k]), (JOINT_NAMES[k], p.index)
    if where is None:
        return ""
    return (f"the {where[0]} joint sits {-low:.3f} m below the base's plane at probe {where[1]} (branch "
            f"{','.join(map(str, plan.options.branch))}): only the tool is checked against the workspace, so on the "
            f"table the arm stands on that is a collision; the default branch 1,1,-1 keeps the elbow up")


def below_contact_threshold(plan, how: str = "lower motion.contact_threshold_n in the plan file") -> str:
    """A warning when no probe's predicted force reaches the contact threshold ("" otherwise): the probes then feel
    no contact on the prior tissue (no contact onsets: the surface cannot be registered from them), and a run's
    forces are close to the sensor's noise (a session-45 review's 200 Pa tissue: 5-8 mN against 20 mN, planned
    without a word)."""
    top = max((p.predicted_force_n for p in plan.probes), default=0.0)
    thr = plan.motion.contact_threshold_n
    if top >= thr:
        return ""
    return (f"every probe's predicted force (at most {top:.3g} N) is below the contact threshold "
            f"({thr:g} N, motion.contact_threshold_n): no probe will feel contact on the prior tissue, so the "
            f"surface is not registered from the contact onsets; if the sensor's noise allows, {how}, or probe deeper "
            f"(`palpate plan --depth-limit-m`)")


def _plan_area(scene, args, margin_m, limits, motion, frames, options):
    """A 3D block's area raster; the waypoint count is checked before fem is asked anything."""
    region = (Region.rectangle(*args.region) if args.region is not None else
              Region.polygon(args.polygon) if args.polygon is not None else None)
    grid = args.grid if (args.grid is not None or args.spacing_m is not None) else DEFAULT_GRID
    prior = scene.prior()
    n = len(grid_positions(region or default_region(prior, margin_m), grid=grid if args.spacing_m is None else None,
                           spacing_m=args.spacing_m)[0])
    if n > MAX_WAYPOINTS:
        raise UsageError(f"--spacing-m {args.spacing_m:g} gives {n} waypoints over the region; allowed: at most "
                         f"{MAX_WAYPOINTS}")
    return plan_raster(prior, grid=grid if args.spacing_m is None else None, spacing_m=args.spacing_m,
                       margin_m=margin_m, region=args.region, polygon=args.polygon, depth_m=args.depth_m,
                       limits=limits, motion=motion, frames=frames, options=options)


def summary(plan, out, figs) -> dict:
    d = np.array([p.depth_m for p in plan.probes])
    f = np.array([p.predicted_force_n for p in plan.probes], dtype=float)
    sv = plan.notes["solver"]
    return {"plan": str(out), "version": plan.version, "scene": plan.scene["name"], "n_probes": len(plan.probes),
            "x_m": [p.x_m for p in plan.probes],
            **({"y_m": [p.y_m for p in plan.probes], "raster": plan.notes["raster"]} if "raster" in plan.notes else {}),
            "depth_m": {"min": float(d.min()), "max": float(d.max())},
            "predicted_force_n": {"min": float(np.nanmin(f)), "max": float(np.nanmax(f))},
            "force_limit_n": plan.limits.force_limit_n, "depth_limit_m": plan.limits.depth_limit_m,
            "total_time_s": plan.total_time_s,
            "solver": {k: sv[k] for k in ("status", "success", "iterations", "solve_s", "build_s", "used")},
            "check": sv["check"], "times_s": plan.notes["times_s"], "figures": figs}
