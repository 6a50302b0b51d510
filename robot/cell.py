"""The robot-cell script: ``palpate-cell --host IP --plan plan.json --out DIR`` (also ``python -m robot.cell``).

Prints a pre-flight summary (workspace box, force limit, probes, estimated time), then runs the plan with
robot.driver, printing one line per probe; records go to DIR (probes.jsonl, raw/, run.json; see robot/records.py).
A second run with the same DIR resumes: probes already "ok" are skipped (``--fresh`` ignores the log).

``--sim`` (= ``--sim inmemory``) runs against the in-memory simulated arm (robot/sim.py) instead of a real arm;
``--sim controller`` starts the simulated UR controller (robot/simcontroller.py) on a loopback address of its own
(127.a.b.1, so parallel runs do not collide) and connects the real ur_rtde client to it. Both hold the TRUE scene
(``--truth``, default: the plan's prior scene name without its "-prior" suffix) with fem's force; the driver only
sees the plan. ``--inject`` faults use one syntax for both (robot.urscript_cmds.parse_inject).

Exit codes: 0 ok, 1 fault, 2 usage / cannot connect, 3 plan rejected, 4 the simulated controller's ports are taken
on every loopback address tried, 130 interrupted.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from planner.planfile import Plan, PlanError
from robot.driver import DriverConfig, preflight, run_plan
from robot.records import done_indices

EXIT_OK, EXIT_FAULT, EXIT_USAGE, EXIT_REJECTED, EXIT_INTERRUPTED = 0, 1, 2, 3, 130
EXIT_PORTS_UNAVAILABLE = 4     # --sim controller: ur_rtde's fixed ports are taken on every loopback address tried


class ControllerPortsUnavailable(Exception):
    """--sim controller could not bind its ports (robot.simlaunch.PortsUnavailable); not a RuntimeError, so it is
    not mistaken for a failed connection."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="palpate-cell", description="Run a palpation plan on a UR arm (or a simulated "
                                "one) over ur_rtde.", formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="examples:\n  palpate-cell --host 192.168.1.10 --plan plan.json --out run/\n"
                                       "  palpate-cell --sim --plan plan.json --out run/ --truth paper")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--host", help="robot controller IP (ur_rtde)")
    src.add_argument("--sim", nargs="?", const="inmemory", choices=["inmemory", "controller"],
                     help="simulated arm: inmemory (default) or controller (loopback UR controller + real ur_rtde)")
    p.add_argument("--plan", required=True, help="plan.json from `palpate plan`")
    p.add_argument("--out", required=True, help="output directory (resumes if it holds a run)")
    p.add_argument("--fresh", action="store_true", help="do not resume: probe everything again")
    p.add_argument("--yes", action="store_true", help="do not ask for confirmation before moving a real arm")
    p.add_argument("--skip-invalid", action="store_true", help="skip probes that fail the safety checks "
                   "instead of refusing the plan")
    p.add_argument("--payload-kg", type=float, default=0.1)
    p.add_argument("--json", metavar="PATH", help="also write the run report here")
    g = p.add_argument_group("simulation (--sim)")
    g.add_argument("--truth", help="TRUE scene for the simulator: built-in name or TOML")
    g.add_argument("--sensor", default="nano17", help="sensor preset: nano17 | ur5e-builtin (default nano17)")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--force-model", choices=["fem", "standin"], default="fem",
                   help="tissue force: fem for the true scene (default) or a Hertz-like stand-in")
    g.add_argument("--sim-mesh-m", type=float, default=None, help="coarser fem mesh for a faster simulator")
    g.add_argument("--inject", action="append", default=[], metavar="SPEC",
                   help="fault (repeatable), same syntax for both simulators: KIND-at-s=T[:X] (at simulated time T "
                        "s) or KIND-at-depth-m=D[:X] (when the tip first reaches D m below the surface); the short "
                        "KIND:T[:X] means KIND-at-s=T[:X]. KIND: protective-stop | disconnect (link lost for good) | "
                        "drop (link lost, reconnecting allowed) | force-spike (X N for 10 ms) | nan (readings NaN "
                        "for X s, default 0.01) | stall (the motion freezes); '_' may replace '-' in KIND. "
                        "Examples: protective_stop:12.5, force-spike-at-depth-m=0.002:5")
    return p


def _truth_name(plan: Plan, arg: str | None) -> str:
    if arg:
        return arg
    name = str(plan.scene.get("name", "")) if isinstance(plan.scene, dict) else ""
    return name[:-len("-prior")] if name.endswith("-prior") else (name or "paper")


def fem_force_model(truth: str, mesh_m: float | None = None):
    """(force_model, width_m) from fem for the TRUE scene (imported here only: the driver never sees fem)."""
    from fem import contact, scene as fem_scene
    sc = fem_scene.load(truth)
    if mesh_m:
        sc = sc.with_analysis(mesh_size_m=mesh_m)
    m = contact.surface_model(sc)
    w, h = sc.tissue.width_m, sc.tissue.height_m
    return (lambda x, d: m.force_n(x, d) if 0.0 <= x <= w and 0.0 < d < h else 0.0), w


def inmemory_arm(plan: Plan, args):
    from robot import ur5e
    from robot.sim import ArmModel, SimRTDEControl, SimRTDEReceive
    from robot.simforce import standin_force_model
    from robot.urscript_cmds import parse_inject
    if args.force_model == "fem":
        f, width = fem_force_model(_truth_name(plan, args.truth), args.sim_mesh_m)
    else:
        f, width = standin_force_model(), 0.07
    tcp = plan.frames.tcp_offset
    start = plan.probes[0].approach_pose if plan.probes else ur5e.fk(ur5e.Q_HOME, tcp)
    start = list(start[:2]) + [start[2] + 0.02] + list(start[3:])   # 2 cm above the first approach pose
    q0 = ur5e.ik(start, [math.pi, -1.4, 1.6, -1.77, -1.57, 0.0], tcp)
    arm = ArmModel(f, tissue_pose_base=plan.frames.tissue_pose_base, width_m=width, sensor=args.sensor,
                   seed=args.seed, q0=q0, tcp_offset=tcp)
    for spec in args.inject:
        parse_inject(arm, spec)           # validated in main()
    return arm, SimRTDEControl(arm), SimRTDEReceive(arm)


def connect(host: str):
    """The real ur_rtde interfaces (receive first: it does not upload a program)."""
    import rtde_control
    import rtde_receive
    r = rtde_receive.RTDEReceiveInterface(host)
    try:
        c = rtde_control.RTDEControlInterface(host)
    except RuntimeError:
        r.disconnect()
        raise
    return c, r


def disconnect(*interfaces) -> None:
    """Close ur_rtde interfaces that are still connected (ur_rtde 1.6.5: a call after a failed reconnect may block,
    so a lost link is left alone)."""
    for iface in interfaces:
        try:
            if iface.isConnected():
                iface.disconnect()
        except RuntimeError:
            pass


def print_preflight(pre: dict, where: str) -> None:
    print(f"pre-flight ({where}):")
    print(f"  workspace box    {pre['workspace_min_m']} .. {pre['workspace_max_m']} m (TCP, base frame)")
    print(f"  force limit      {pre['force_limit_n']} N, depth limit {pre['depth_limit_m'] * 1e3:.1f} mm, "
          f"probe speed {pre['probe_speed_m_s'] * 1e3:.1f} mm/s")
    print(f"  probes           {pre['n_probes']} planned, {pre['n_done']} already done, {pre['n_to_run']} to run")
    print(f"  estimated time   {pre['estimated_time_s']:.0f} s")
    for pr in pre["problems"]:
        print(f"  PROBLEM          {pr}")
    for k, v in pre["rejected_probes"].items():
        print(f"  UNSAFE probe {k}: {v}")


def _progress(rec, i, n):
    f = rec.get("force_mean_n")
    fs = "-" if f is None else f"{f:.3f} +- {rec.get('force_std_n') or 0:.3f} N"
    d = rec.get("depth_reached_m")
    ds = "-" if d is None else f"{d * 1e3:.2f} mm"
    print(f"  probe {rec['index']:3d} ({i}/{n}) x={rec['x_m'] * 1e3:6.1f} mm  depth {ds}  F {fs}  {rec['status']}",
          flush=True)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        plan = Plan.load(args.plan)
    except PlanError as e:
        print(f"palpate-cell: {e}", file=sys.stderr)
        return EXIT_USAGE
    if args.inject and not args.sim:
        print("palpate-cell: --inject needs --sim", file=sys.stderr)
        return EXIT_USAGE
    try:
        if args.inject:
            from robot.urscript_cmds import normalize_inject
            args.inject = [normalize_inject(s) for s in args.inject]
    except ValueError as e:
        print(f"palpate-cell: --inject: {e}", file=sys.stderr)
        return EXIT_USAGE
    out = Path(args.out)
    done = set() if args.fresh else done_indices(out)
    where = f"simulated arm ({args.sim})" if args.sim else f"UR controller at {args.host}"
    pre = preflight(plan, done)
    print_preflight(pre, where)
    cfg = DriverConfig(payload_kg=args.payload_kg, skip_invalid=args.skip_invalid)
    if args.host and not args.yes:
        if input("type 'yes' to move the arm: ").strip().lower() != "yes":
            print("not confirmed; nothing sent")
            return EXIT_USAGE
    try:
        if args.sim == "controller":
            rep = _run_controller(plan, args, out, cfg)
        else:
            if args.sim:
                _, c, r = inmemory_arm(plan, args)
            else:
                c, r = connect(args.host)
            rep = run_plan(plan, c, r, out, config=cfg, resume=not args.fresh, progress=_progress)
    except ControllerPortsUnavailable as e:
        print(f"palpate-cell: simulated controller not started: {e}", file=sys.stderr)
        return EXIT_PORTS_UNAVAILABLE
    except RuntimeError as e:
        print(f"palpate-cell: cannot connect: {e}", file=sys.stderr)
        return EXIT_USAGE
    print(f"run {rep.status}: {rep.n_ok} ok, {rep.n_force_limit} at the force limit, {rep.n_rejected} rejected, "
          f"{rep.n_skipped} from the log; controller time {rep.controller_time_s:.1f} s, wall {rep.wall_s:.1f} s")
    if rep.problems:
        print("refused:\n  " + "\n  ".join(rep.problems))
    if rep.fault:
        print(f"FAULT {rep.fault['kind']}: {rep.fault['message']}")
        print(f"  stopped={rep.fault['stopped']} retracted={rep.fault['retracted']}; "
              + "; ".join(rep.fault.get("notes", [])))
        print(f"  completed probes are in {out / 'probes.jsonl'}; run again with the same --out to resume")
    if args.json:
        Path(args.json).write_text(json.dumps(rep.to_dict(), indent=1))
    return {"ok": EXIT_OK, "rejected": EXIT_REJECTED, "interrupted": EXIT_INTERRUPTED}.get(rep.status, EXIT_FAULT)


def _run_controller(plan: Plan, args, out: Path, cfg: DriverConfig):
    """Start the simulated controller (child process, a loopback address of its own), connect real ur_rtde, run."""
    try:
        from robot.simlaunch import PortsUnavailable, start_controller
    except ImportError as e:
        raise RuntimeError(f"the simulated controller is not available: {e}") from None
    out.mkdir(parents=True, exist_ok=True)
    try:
        ctl = start_controller(scene=_truth_name(plan, args.truth), sensor=args.sensor, seed=args.seed,
                               inject=args.inject, force=args.force_model, tissue_pose=plan.frames.tissue_pose_base,
                               mesh_m=args.sim_mesh_m, host="auto", log_path=out / "simcontroller.log")
    except PortsUnavailable as e:
        raise ControllerPortsUnavailable(str(e)) from None
    with ctl:
        c, r = connect(ctl.host)
        try:
            return run_plan(plan, c, r, out, config=cfg, resume=not args.fresh, progress=_progress)
        finally:
            disconnect(c, r)


if __name__ == "__main__":
    sys.exit(main())
