"""`palpate run [SCENE] [--plan plan.json] [--sim | --host IP] --out DIR`: plan, probe, localize, refine.

Truth and belief (docs/architecture.md): SCENE is the truth only for a simulated arm. This command builds two separate things:
an *executor* (``sim_executor``: the simulated arm, created from the true scene inside a closure; or ``arm_executor``
on a real arm, where there is no truth) that turns a plan into probe records, and the *belief side*
(planner.refine.adaptive -> planner.localize.localize) that gets the prior scene (stones removed) and those records
and nothing else. The truth is written into result.json only after localization, for comparison (``sim`` key).
"""
from __future__ import annotations

import contextlib
import json
import sys
import time
from pathlib import Path

from app.cell import print_preflight
from app.commands.output import write_json
from core.contracts import Plan
from fem.scene import load
from planner.detectability import detectability
from planner.localize import Localization, localize
from planner.plan import plan_prior, plan_raster, replan
from planner.refine import adaptive, describe, renumber
from planner.surrogate import load_surrogate
from robot.driver import preflight, run_plan
from robot.link import connect, end_session
from robot.sim import SimRTDEControl, SimRTDEReceive
from robot.simarm import build_truth_arm
from robot.simlaunch import start_controller


def add_parser(sub) -> None:
    p = sub.add_parser("run", help="plan, probe (simulated arm by default), locate the stone, refine",
                       description=__doc__.splitlines()[0])
    p.add_argument("scene", nargs="?", default="paper",
                   help="scene: built-in name or TOML (the TRUTH for --sim; only its prior is used for planning)")
    p.add_argument("--plan", help="use this plan.json as the coarse raster (default: plan one)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--sim", nargs="?", const="inmemory", choices=["inmemory", "controller"],
                     help="simulated arm (default): inmemory, or controller (the loopback UR controller)")
    src.add_argument("--host", help="a real UR controller's IP (ur_rtde)")
    p.add_argument("--yes", action="store_true", help="do not ask before moving a real arm")
    p.add_argument("--sensor", default="nano17", help="simulated sensor: nano17 | ur5e-builtin (default nano17)")
    p.add_argument("--seed", type=int, default=0, help="simulated sensor noise seed")
    p.add_argument("--waypoints", type=int, default=15, help="coarse raster waypoints (default 15)")
    p.add_argument("--refine-waypoints", type=int, default=10, help="waypoints per refinement round (default 10)")
    p.add_argument("--budget-probes", type=int, default=45, help="probe budget over all rounds (default 45)")
    p.add_argument("--target-uncertainty-m", type=float, default=5e-4,
                   help="stop refining when the 1-sigma x and depth uncertainties are below this (default 0.5 mm)")
    p.add_argument("--strategy", choices=["design", "raster"], default="design",
                   help="refinement: design (probes where they shrink the x/depth variance most; default) or raster "
                        "(an even finer raster around the candidate)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--no-figure", action="store_true")
    p.add_argument("--json", metavar="PATH", help="also write result.json here ('-': standard output)")
    p.set_defaults(func=run)


def _say(msg: str) -> None:
    print(f"palpate run: {msg}", file=sys.stderr, flush=True)


class RunAborted(RuntimeError):
    def __init__(self, report):
        super().__init__(f"the arm run ended with status {report.status}: {report.fault or report.problems}")
        self.report = report


def _runner(get_interfaces, out: Path, stats: dict):
    """execute(plan, round) over interfaces from ``get_interfaces(plan)``: renumbered probes, one probes.jsonl."""

    def execute(plan, k):
        renumber(plan, stats["next_index"])
        plan.save(out / f"plan_round{k}.json")
        c, r = get_interfaces(plan)
        rep = run_plan(plan, c, r, out, resume=True, progress=lambda rec, i, n: None)
        stats["next_index"] += len(plan.probes)
        stats["n_probes"] += sum(1 for rec in rep.records if rec.status in ("ok", "force_limit"))
        stats["planned_s"] += plan.total_time_s
        stats["controller_s"] += sum(rec.duration_s or 0.0 for rec in rep.records)   # arm time probing
        stats["reports"].append(rep.to_dict())
        if rep.status != "ok":
            raise RunAborted(rep)
        return rep.records
    return execute


def sim_executor(truth, *, sensor: str, seed: int, out: Path, stats: dict):
    """The simulated arm holding the TRUE scene (in this closure only); created at the first plan."""
    arm = {}

    def interfaces(plan):
        if "c" not in arm:
            a = build_truth_arm(truth, sensor=sensor, seed=seed, tissue_pose=plan.frames.tissue_pose_base,
                                tcp_offset=plan.frames.tcp_offset, start_above_pose=plan.probes[0].approach_pose)
            arm.update(c=SimRTDEControl(a), r=SimRTDEReceive(a))
        return arm["c"], arm["r"]
    return _runner(interfaces, out, stats)


def arm_executor(host: str, out: Path, stats: dict, cleanup: contextlib.ExitStack):
    """A real UR controller at ``host``, over ur_rtde (no truth: only the prior scene exists)."""
    link = {}

    def interfaces(plan):
        if "c" not in link:
            link["c"], link["r"] = connect(host)
            cleanup.callback(lambda: end_session(link["c"], link["r"], clean=cleanup.clean_end))
        return link["c"], link["r"]
    return _runner(interfaces, out, stats)


def controller_executor(scene_spec: str, *, sensor: str, seed: int, out: Path, stats: dict,
                        cleanup: contextlib.ExitStack):
    """The simulated UR controller (robot.simcontroller, a child process holding the TRUE scene), driven through the
    real ur_rtde client; started at the first plan, stopped when the run ends."""
    link = {}

    def interfaces(plan):
        if "c" not in link:
            ctl = cleanup.enter_context(start_controller(
                scene=scene_spec, sensor=sensor, seed=seed, tissue_pose=plan.frames.tissue_pose_base,
                host="auto", log_path=out / "simcontroller.log"))
            link["c"], link["r"] = connect(ctl.host)
            cleanup.callback(lambda: end_session(link["c"], link["r"], clean=cleanup.clean_end))
        return link["c"], link["r"]
    return _runner(interfaces, out, stats)


def run(args) -> int:

    t_wall = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if (out / "probes.jsonl").exists():
        (out / "probes.jsonl").unlink()      # a run starts afresh (probe indices restart at 0)
    scene = load(args.scene)
    if args.plan:
        plan0 = Plan.load(args.plan)
        prior = plan_prior(plan0)
        if prior.stones:
            raise SystemExit("palpate run: the plan's scene has stones; a plan holds the prior scene only")
        if prior.key() != scene.prior().key():
            _say(f"warning: the plan's prior scene differs from {args.scene}'s prior")
    else:
        prior = scene.prior()
        _say(f"planning a {args.waypoints}-waypoint raster on {prior.name}")
        plan0 = plan_raster(prior, n_waypoints=args.waypoints)
    _say("loading the fem surrogate (first use on a scene: built with fem and cached, a few minutes)")
    sur = load_surrogate(prior, progress=lambda i, n, t: _say(f"surrogate: {i}/{n} stones ({t:.0f} s)"))

    det = detectability(prior, sensor=args.sensor, force_limit_n=plan0.limits.force_limit_n,
                        depth_limit_m=plan0.limits.depth_limit_m, x_positions_m=[p.x_m for p in plan0.probes],
                        surrogate=sur, motion=plan0.motion)
    smallest = {}
    for r in det["rows"]:
        if r["detectable"]:
            k = f"{r['depth_m'] * 1e3:g}"
            smallest[k] = min(smallest.get(k, 1.0), r["diameter_m"])
    _say("detectable before probing (coarse raster, sensor " + args.sensor + "): " + (
        ", ".join(f"depth {k} mm: >= {v * 1e3:g} mm" for k, v in smallest.items()) if det["usable"]
        else det["reason"]))
    stats = {"n_probes": 0, "next_index": 0, "planned_s": 0.0, "controller_s": 0.0, "reports": []}
    cleanup = contextlib.ExitStack()       # controller process and ur_rtde links, closed when probing ends
    if args.host:
        where = f"UR controller at {args.host}"
        print("WARNING: this moves a real arm into tissue. Check the tissue pose, TCP, force limit "
              f"{plan0.limits.force_limit_n} N and the emergency stop first.", file=sys.stderr)
        print_preflight(preflight(plan0, set()), where)
        if not args.yes and input("type 'yes' to move the arm: ").strip().lower() != "yes":
            print("not confirmed; nothing sent", file=sys.stderr)
            return 2
        execute = arm_executor(args.host, out, stats, cleanup)
        truth = None
    elif args.sim == "controller":
        where = f"simulated UR controller over ur_rtde (sensor {args.sensor}, seed {args.seed}; real time)"
        truth = scene
        execute = controller_executor(args.scene, sensor=args.sensor, seed=args.seed, out=out, stats=stats,
                                      cleanup=cleanup)
    else:
        where = f"simulated arm (sensor {args.sensor}, seed {args.seed})"
        truth = scene
        execute = sim_executor(truth, sensor=args.sensor, seed=args.seed, out=out, stats=stats)
    _say(f"probing on the {where}")

    rounds_planned = {"n": 0}

    def plan_round(x):
        rounds_planned["n"] += 1
        return plan0 if rounds_planned["n"] == 1 else replan(plan0, x)

    status, fault = "ok", None
    cleanup.clean_end = False          # set once the probing ended without a fault: the script is then stopped
    try:
        res = adaptive(prior, execute, coarse_x_m=[p.x_m for p in plan0.probes], plan_round=plan_round,
                       budget_probes=args.budget_probes, n_refine=args.refine_waypoints,
                       target_m=args.target_uncertainty_m, surrogate=sur, progress=_say,
                       strategy=args.strategy)
        cleanup.clean_end = True
    except RunAborted as e:
        status, fault, res = "fault", e.report.to_dict(), None
        _say(str(e))
    finally:
        cleanup.close()
    result = {"scene": args.scene, "prior": prior.name, "where": where, "status": status,
              "strategy": args.strategy}
    if res is not None:
        # the final estimate once more, with the depth's profile-likelihood interval (prior + measurements only)
        loc = res.localization = localize(prior, res.measurements, sur, profile=True)
        result.update(loc.to_dict())
        result.update({"probes_used": res.probes_used, "stop_reason": res.stop_reason,
                       "rounds": [{"index": r.index, "n_probes": r.n_probes, "x_m": r.x_m, "depth_m": r.depth_m,
                                   "localization": r.localization, "elapsed_s": r.elapsed_s} for r in res.rounds]})
    else:
        loc = Localization(detected=False, lr=float("nan"), lr_threshold=float("nan"))
        result.update(loc.to_dict())
        result.update({"probes_used": stats["n_probes"], "fault": fault})
    result["time"] = {"wall_s": time.perf_counter() - t_wall, "robot_s": stats["controller_s"],
                      "planned_s": stats["planned_s"]}
    result["detectability"] = {"sensor": det["sensor"], "usable": det["usable"], "reason": det["reason"],
                               "probe_sigma_n": det["sigma_n"],
                               "smallest_detectable_diameter_m_by_depth_mm": smallest}
    result["surrogate"] = {"build_s": sur.build_s, "bounds": {k: list(v) for k, v in sur.bounds.items()}}
    if truth is not None:        # comparison only, after the fact
        st = [{"x_m": s.x_m, "depth_m": s.depth_m, "diameter_m": s.diameter_m} for s in truth.stones]
        result["sim"] = {"sensor": args.sensor, "seed": args.seed, "truth_stones": st}
        if st and res is not None and loc.detected:
            result["sim"]["error"] = {"x_m": loc.x_m - st[0]["x_m"], "depth_m": loc.depth_m - st[0]["depth_m"],
                                      "diameter_m": loc.diameter_m - st[0]["diameter_m"]}
    (out / "result.json").write_text(json.dumps(result, indent=1))
    write_json(args.json, result)
    if res is not None and not args.no_figure:
        from planner.plots_run import plot_run
        plot_run(out / "fig_run.png", prior, loc, res.measurements, surrogate=sur,
                 truth_stones=truth.stones if truth is not None else (), rounds=res.rounds,
                 title=f"palpate run {args.scene}:\n{describe(loc)}")
    print((("STONE " if loc.detected else "NO STONE ") + describe(loc) if res is not None else
           f"NO RESULT: the arm run ended with a fault ({fault['fault']['kind'] if fault and fault.get('fault') else status})")
          + f"; {result['probes_used']} probes; results in {out}",
          file=sys.stderr if args.json == "-" else sys.stdout)
    return 0 if status == "ok" else 1
