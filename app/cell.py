"""The robot-cell script: ``palpate-cell --host IP --plan plan.json --out DIR`` (also ``python -m app.cell``).

Prints a pre-flight summary (workspace box, force limit, probes, estimated time), then runs the plan with
robot.driver, printing one line per probe; records go to DIR (probes.jsonl, raw/, run.json; see robot/records.py).
A second run with the same DIR resumes: probes already "ok" are skipped (a "force_limit" one is probed again); ``--fresh``
moves the old files into DIR/previous-<UTC time>/ (never deletes) and probes everything again. Everything (options,
plan, output paths) is checked before DIR is touched or anything moves.

``--sim`` (= ``--sim inmemory``) runs against the in-memory simulated arm (robot/sim.py) instead of a real arm;
``--sim controller`` starts the simulated UR controller (robot/simcontroller.py) on a loopback address of its own
(127.a.b.1, so parallel runs do not collide) and connects the real ur_rtde client to it. Both hold the TRUE scene
(``--truth``; without it, the built-in scene whose prior the plan holds, else exit 2) with fem's force; the driver only
sees the plan. ``--inject`` faults use one syntax for both (robot.simfaults).

Exit codes: 0 ok, 1 fault, 2 bad input: usage, a plan file that fails ``Plan.check`` (core.contracts: types,
limits, depth below the tip radius) or the driver's own pre-flight safety checks (robot.safety: workspace, poses,
speeds against the hard caps; nothing moves), not confirmed, cannot connect; 4 the simulated controller's ports are
taken on every loopback address tried, 130 interrupted.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

from app.commands.output import json_alone, write_json
from app.errors import RunFailed, UsageError, guarded
from app.ftoptions import add_ft_options, check_ft, controller_pose, inmemory_source, linked_source
from app.isolate import ChildDied, ChildError, ChildTimeout, run_in_child
from app.options import (
    check_output_dir,
    check_output_file,
    check_same_extent,
    check_simulated_sensor,
    float_range,
    host_name,
    int_range,
    load_plan_option,
    load_scene,
    positive_float,
)
from app.outlock import holding
from app.parser import Parser
from core.contracts import SENSORS, FaultKind, Plan, RunStatus
from fem.scene import BUILTIN, SceneError, load
from fem.scene_mesh import check_mesh_budget, check_surface_budget
from planner.plan import plan_prior
from robot.driver import DriverConfig, RunReport, preflight, run_plan, unfelt_probes
from robot.link import LOCAL_CONTROL, connect, dashboard_stop, end_session, remote_control
from robot.records import damaged_note, done_indices, foreign_record, move_aside
from robot.safety import MAX_PAYLOAD_KG
from robot.sim import SimRTDEControl, SimRTDEReceive
from robot.simarm import build_truth_arm
from robot.simfaults import never_fires, past_the_limit
from robot.simfaults import parse as parse_fault
from robot.simlaunch import PortsUnavailable, start_controller

EXIT_OK, EXIT_FAULT, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
CONNECT_TIMEOUT_S = 20.0        # ur_rtde connects in well under a second; its constructors wait for good on a
                                # controller that accepts connections but never answers (frozen)
EXIT_REJECTED = EXIT_USAGE     # a plan the driver's safety checks refuse is bad input too: nothing was sent
EXIT_PORTS_UNAVAILABLE = 4     # --sim controller: ur_rtde's fixed ports are taken on every loopback address tried


class ControllerPortsUnavailable(Exception):
    """--sim controller could not bind its ports (robot.simlaunch.PortsUnavailable); not a RuntimeError, so it is
    not mistaken for a failed connection."""


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="palpate-cell", description="Run a palpation plan on a UR arm (or a simulated "
                                "one) over ur_rtde.", formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="examples:\n  palpate-cell --host 192.168.1.10 --plan plan.json --out run/\n"
                                       "  palpate-cell --sim --plan plan.json --out run/ --truth paper")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--host", type=host_name, help="robot controller IP (ur_rtde)")
    src.add_argument("--sim", nargs="?", const="inmemory", choices=["inmemory", "controller"],
                     help="simulated arm: inmemory (default) or controller (loopback UR controller + real ur_rtde)")
    p.add_argument("--plan", required=True, help="plan.json from `palpate plan`")
    p.add_argument("--out", required=True, help="output directory (resumes if it holds a run)")
    p.add_argument("--fresh", action="store_true", help="do not resume: move the old files into "
                   "OUT/previous-<UTC time>/ and probe everything again")
    p.add_argument("--yes", action="store_true", help="do not ask for confirmation before moving a real arm")
    p.add_argument("--skip-invalid", action="store_true", help="skip probes that fail the safety checks "
                   "instead of refusing the plan")
    p.add_argument("--connect-timeout-s", type=float_range(1.0, 600.0, lo_open=False, unit="s"),
                   default=CONNECT_TIMEOUT_S, help="give up connecting after this long (default %(default)g s): "
                   "ur_rtde waits for good on a controller that accepts connections but never answers")
    p.add_argument("--payload-kg", type=float_range(0.0, MAX_PAYLOAD_KG, lo_open=False, unit="kg"), default=0.1,
                   help=f"tool payload, 0..{MAX_PAYLOAD_KG:g} kg (default 0.1)")
    add_ft_options(p)
    p.add_argument("--json", metavar="PATH", help="also write the run report here")
    p.add_argument("--debug", action="store_true", help="show a traceback on errors")
    g = p.add_argument_group("simulation (--sim)")
    g.add_argument("--truth", help="TRUE scene for the simulator: built-in name or TOML")
    g.add_argument("--sensor", choices=list(SENSORS), help="sensor preset (default nano17)")
    g.add_argument("--seed", type=int_range(0, 2 ** 32 - 1), help="the sensor's noise seed (default 0)")
    g.add_argument("--force-model", choices=["fem", "standin"],
                   help="tissue force: fem for the true scene (default) or a Hertz-like stand-in")
    g.add_argument("--sim-mesh-m", type=positive_float, default=None,
                   help="coarser fem mesh (element size, m) for a faster simulator")
    g.add_argument("--inject", action="append", default=[], metavar="SPEC",
                   help="fault (repeatable), same syntax for both simulators: KIND-at-s=T[:X] (at simulated time T "
                        "s), KIND-at-depth-m=D[:X] (when the tip first reaches D m below the surface), "
                        "KIND-leaving-depth-m=D[:X] (when the tip, on its way out, is back at D m: in a retract) or "
                        "KIND-after-probes=N[:X] (at rest after N probes); the short KIND:T[:X] means KIND-at-s=T[:X]. "
                        "KIND: protective-stop | disconnect (link lost for good) | drop (link lost, reconnecting "
                        "allowed) | force-spike (X N for 10 ms) | side-push (X N across the normal for 0.2 s) | nan (readings NaN for X s, default 0.01) | stall "
                        "(the motion freezes); with --sim controller also partition (no traffic for X s; none: for "
                        "good) | freeze (controller process stopped) | program-stop | remote-off (local control; X=1 "
                        "also stops the program); '_' may replace '-' in KIND. Examples: protective_stop:12.5, "
                        "force-spike-at-depth-m=0.002:5, force-spike-leaving-depth-m=0.0015:-10, partition-at-depth-m=0.0015, "
                        "remote-off-after-probes=1:1")
    return p


def truth_scene(plan: Plan, arg: str | None) -> str:
    """The TRUE scene for a simulated arm: ``--truth``, or the built-in scene whose prior the plan holds (a plan made
    from a built-in scene names its prior "<name>-prior"). Anything else needs ``--truth``: the plan holds only the
    prior, and the simulator must not guess the truth."""
    if arg:
        return arg
    name = str(plan.scene.get("name", ""))
    base = name[:-len("-prior")] if name.endswith("-prior") else None
    if base in BUILTIN:
        if load(base).prior().key() == plan_prior(plan).key():
            return base
    raise UsageError(f"--truth: needed with --sim for this plan (its prior scene {name!r} is not the prior of a "
                     f"built-in scene); give the TRUE scene as a built-in name or a TOML file")


def inmemory_arm(plan: Plan, args):
    """The in-memory simulated arm (robot.simarm), its ur_rtde-like interfaces and the force source (None: the
    wrist sensor; else a Net F/T source reading a simulated box stepped with the arm)."""
    truth = truth_scene(plan, args.truth) if args.force_model == "fem" else None
    arm = build_truth_arm(truth, force=args.force_model, sensor=args.sensor, seed=args.seed,
                          tissue_pose=plan.frames.tissue_pose_base, tcp_offset=plan.frames.tcp_offset,
                          start_above_pose=plan.probes[0].approach_pose if plan.probes else None,
                          mesh_m=args.sim_mesh_m, inject=args.inject)
    c, r = SimRTDEControl(arm), SimRTDEReceive(arm)
    fs = None
    if args.ft.kind == "netft":
        fs, _ = inmemory_source(args, arm, c, plan.frames.tcp_offset, [parse_fault(f) for f in args.inject])
    return arm, c, r, fs


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


def grouped_problems(problems: list[str]) -> list[str]:
    """The driver's refusals with the probes that share a reason on one line ("probes 0-14: ..."), in order."""
    out: list[str] = []
    by_why: dict[str, list[int]] = {}
    for pr in problems:
        head, sep, why = pr.partition(": ")
        if sep and head.startswith("probe ") and head[6:].isdigit():
            if why not in by_why:
                by_why[why] = []
                out.append(why)
            by_why[why].append(int(head[6:]))
        else:
            out.append(pr)
    return [f"{_indices(by_why[x])}: {x}" if x in by_why else x for x in out]


def _indices(ks: list[int]) -> str:
    """'probe 3', or 'probes 0-4, 7' (runs of consecutive indices)."""
    if len(ks) == 1:
        return f"probe {ks[0]}"
    runs, start = [], ks[0]
    for a, b in zip(ks, ks[1:] + [None]):
        if b != a + 1:
            runs.append(f"{start}" if start == a else f"{start}-{a}")
            start = b
    return "probes " + ", ".join(runs)


def read_confirmation() -> bool:
    """Ask before a real arm moves; a closed standard input (EOF) is a no."""
    try:
        return input("type 'yes' to move the arm: ").strip().lower() == "yes"
    except EOFError:
        return False


def sim_range_report(arm) -> dict | None:
    """What the simulated arm's force model extrapolated beyond its range (robot.simforce.CachedForce), or None."""
    report = getattr(getattr(arm, "force_model", None), "range_report", None)
    return report() if report is not None else None


def _progress(rec, i, n):
    fs = "-" if rec.force_mean_n is None else f"{rec.force_mean_n:.3f} +- {rec.force_std_n or 0:.3f} N"
    ds = "-" if rec.depth_reached_m is None else f"{rec.depth_reached_m * 1e3:.2f} mm"
    print(f"  probe {rec.index:3d} ({i}/{n}) x={rec.x_m * 1e3:6.1f} mm  depth {ds}  F {fs}  {rec.status}", flush=True)


CELL_WORLD = "cell_world.json"     # what a cell run in OUT probed: a real arm, or a simulated one's world


SIM_DEFAULTS = {"sensor": "nano17", "seed": 0, "force_model": "fem"}     # the simulation group's (--sim-mesh-m: None)


def sim_only(args) -> None:
    """Refuse an option of the simulated arm without --sim (it did nothing next to a real arm, silently: session 56's
    review), then put in the simulation group's defaults."""
    if not args.sim:
        given = [k for k in (*SIM_DEFAULTS, "sim_mesh_m") if getattr(args, k) is not None]
        if given:
            opt = "--" + given[0].replace("_", "-")
            raise UsageError(f"{opt} {getattr(args, given[0])}: an option of the simulated arm (--sim); a real arm "
                             f"(--host) has its own sensor and tissue: drop it")
    for k, v in SIM_DEFAULTS.items():
        if getattr(args, k) is None:
            setattr(args, k, v)


def cell_world(args, truth) -> dict:
    """What the records in OUT come from: a real arm, or a simulated arm's truth (its content's key), force model,
    sensor preset, seed, mesh and force source. A resume must probe the same (session 56's review: a run resumed with
    another --truth or --sensor put 57 and 243 records of two worlds in one probes.jsonl, exit 0)."""
    if not args.sim:
        return {"arm": "real"}
    return {"arm": f"simulated ({args.sim})", "truth": truth.key() if truth is not None else None,
            "force_model": args.force_model, "sensor": args.sensor, "seed": args.seed,
            "sim_mesh_m": args.sim_mesh_m, "force_source": args.ft.kind}


def check_same_world(out: Path, world: dict) -> None:
    """UsageError when OUT's earlier cell run probed another world (``cell_world``); nothing when there is none."""
    try:
        prev = json.loads((out / CELL_WORLD).read_text(encoding="utf-8"))
    except FileNotFoundError:
        return
    except (OSError, ValueError) as e:
        raise UsageError(f"--out {out}: cannot read {CELL_WORLD} of the run there ({e}); use --fresh (moves the old "
                         f"files aside) or another --out") from None
    diff = [f"{k} was {prev.get(k)!r}, now {v!r}" for k, v in world.items() if prev.get(k) != v]
    if diff:
        raise UsageError(f"--out {out}: holds a run of another arm or simulated world ({'; '.join(diff)}): its "
                         f"records and this run's would mix; resume with the same options, or --fresh (moves them "
                         f"aside) or another --out")


def write_world(out: Path, world: dict) -> None:
    """OUT's ``cell_world`` (written once: a resume found it equal)."""
    path = out / CELL_WORLD
    if not path.exists():
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(world, indent=1, allow_nan=False))
        tmp.replace(path)


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:           # argparse's usage errors (a bad option value): its message, exit 2
        return e.code if isinstance(e.code, int) else EXIT_USAGE
    def main_json():
        with json_alone(args.json), contextlib.ExitStack() as held:   # --json -: standard output: the JSON alone
            return _main(args, held)
    return guarded("palpate-cell", main_json, debug=args.debug)


def _main(args, held: contextlib.ExitStack) -> int:
    # ---- everything checked before the output directory is touched or anything moves
    check_output_dir(args.out, "--out")
    check_output_file(args.json, "--json", inputs={"--plan": args.plan, "--truth": getattr(args, "truth", None)})
    out = Path(args.out)
    if args.json and Path(args.json).absolute().parent == out.absolute() and Path(args.json).name in (
            "probes.jsonl", "run.json"):
        raise UsageError(f"--json {args.json}: would overwrite the run's own {Path(args.json).name}")
    plan = load_plan_option(args.plan)
    sim_only(args)
    if args.sim:               # the simulated sensor is this preset: a run the driver would stop is refused first
        check_simulated_sensor(args.sensor, plan.limits.force_limit_n)
    if args.inject and not args.sim:
        raise UsageError("--inject needs --sim")
    try:
        faults = [parse_fault(s) for s in args.inject]
    except ValueError as e:
        raise UsageError(f"--inject: {e}") from None
    on_ctl = [f.text() for f in faults if f.on_controller]
    if on_ctl and args.sim != "controller":
        raise UsageError(f"--inject {on_ctl[0]}: a controller fault, only with --sim controller")
    check_ft(args, sim=bool(args.sim), real_host=bool(args.host))
    on_ft = [f.text() for f in faults if f.on_ft]
    if on_ft and args.ft.kind != "netft":
        raise UsageError(f"--inject {on_ft[0]}: a fault of the simulated Net F/T box, only with --ft netft")
    args.inject = [f.text() for f in faults]
    if args.truth and not (args.sim and args.force_model == "fem"):
        raise UsageError(f"--truth {args.truth}: the true scene is for a simulated arm with fem's force (--sim, "
                         f"--force-model fem); " + ("a real arm has none" if not args.sim else
                                                     "the stand-in force has no scene"))
    if args.sim and args.force_model == "fem":
        truth = load_scene(truth_scene(plan, args.truth), "--truth" if args.truth else "scene")   # before anything moves: the simulator needs its truth
        check_same_extent(truth, plan_prior(plan), f"--plan {args.plan}: its prior scene",
                          args.truth or truth.name)
        if args.sim_mesh_m is not None:
            try:                                # a usage error now, not after the pre-flight
                coarse = truth.with_analysis(mesh_size_m=args.sim_mesh_m)
                if coarse.is_3d:                # (the 3D path, imported only for a block: a 2D run never loads it)
                    from fem.scene_mesh3d import check_mesh_budget3d
                    check_mesh_budget3d(coarse)
                else:                           # (a mesh too fine was refused only after the pre-flight)
                    check_surface_budget(coarse)
                    check_mesh_budget(coarse)
            except SceneError as e:             # said as the option the user gave, not as the scene's field
                raise UsageError(f"--sim-mesh-m {args.sim_mesh_m:g}: not a mesh for {truth.name} "
                                 f"(the simulator's analysis.mesh_size_m): {e}") from None
    unfelt = unfelt_probes(plan)            # the driver would stop at the first of them (contact_unfelt), at once
    if unfelt:
        k = min(unfelt)
        more = f" (and {len(unfelt) - 1} more)" if len(unfelt) > 1 else ""
        raise UsageError(f"--plan {args.plan}: refused before any motion: probe {k}: {unfelt[k]}{more}")
    world = cell_world(args, truth if args.sim and args.force_model == "fem" else None)
    if not args.fresh:
        check_same_world(out, world)
    done = set() if args.fresh else done_indices(out)
    for f in faults:            # (a fault that cannot fire passed silently: the drill it was for never ran)
        why = never_fires(f, len({p.index for p in plan.probes} - done))
        if why:
            raise UsageError(f"--inject {f.text()}: {why}")
        note = past_the_limit(f, plan.limits.depth_limit_m)
        if note:
            print(f"palpate-cell: --inject {f.text()}: {note}", file=sys.stderr)
    damaged = None if args.fresh else damaged_note(out)
    if damaged:                             # (said by palpate run's resume too; the cell dropped them silently)
        print(f"palpate-cell: {damaged}", file=sys.stderr)
    other = None if args.fresh else foreign_record(out, plan)
    if other is not None:
        raise UsageError(f"--out {out}: holds records of another plan ({other}; --plan {args.plan}): a resumed run "
                         f"would take them for its own; give a new --out, or --fresh to move them aside")
    where = f"simulated arm ({args.sim})" if args.sim else f"UR controller at {args.host}"
    if args.ft.kind == "netft":
        where += f", force from the Net F/T box ({args.ft.host or 'simulated'}: the UR's own force protection does " \
                 f"not see it, the driver's force limit is the only guard on it)"
    pre = preflight(plan, done)
    print_preflight(pre, where)
    cfg = DriverConfig(payload_kg=args.payload_kg, skip_invalid=args.skip_invalid)
    if args.host and not args.yes and not read_confirmation():
        raise UsageError("not confirmed (type 'yes' to move the arm, or give --yes); nothing sent, nothing moved")
    held.enter_context(holding(out))       # one process at a time in OUT (app.outlock)
    if args.fresh:
        moved = move_aside(out, keep=[args.plan, args.truth])    # (the command's input files kept in OUT stay)
        if moved is not None:
            print(f"--fresh: the previous run's files are in {moved}")
    write_world(out, world)
    arm = None
    try:
        if args.sim == "controller":
            rep = _run_controller(plan, args, out, cfg)
        else:
            if args.sim:
                arm, c, r, fs = inmemory_arm(plan, args)
                try:
                    rep = run_plan(plan, c, r, out, config=cfg, resume=not args.fresh, progress=_progress,
                                   force_source=fs)
                finally:
                    if fs is not None:
                        fs.close()
            else:
                rep = _run_host(plan, args, out, cfg, args.host)
    except ControllerPortsUnavailable as e:
        print(f"palpate-cell: simulated controller not started: {e}", file=sys.stderr)
        return EXIT_PORTS_UNAVAILABLE
    except NotConnected as e:
        print(f"palpate-cell: cannot connect: {e}", file=sys.stderr)
        return EXIT_USAGE
    depth = (f", {rep.n_depth_limit} at the depth limit (the surface higher than planned? check "
             f"the registration)") if rep.n_depth_limit else ""
    print(f"run {rep.status}: {rep.n_ok} ok, {rep.n_force_limit} at the force limit{depth}, {rep.n_rejected} rejected, "
          f"{rep.n_skipped} from the log; controller time {rep.controller_time_s:.1f} s, wall {rep.wall_s:.1f} s")
    if rep.problems:
        refused = grouped_problems(rep.problems)
        print("refused:\n  " + "\n  ".join(refused))
        if rep.status == "rejected":    # bad input: one line on stderr (the list above, on stdout)
            more = f" (and {len(refused) - 1} more, above)" if len(refused) > 1 else ""
            print(f"palpate-cell: --plan {args.plan}: refused before any motion: {refused[0]}{more}",
                  file=sys.stderr)
    if rep.fault:
        print(f"FAULT {rep.fault['kind']}: {rep.fault['message']}")
        print(f"  stopped={rep.fault['stopped']} retracted={rep.fault['retracted']}; "
              + "; ".join(rep.fault.get("notes", [])))
        first = ("free the tip first (freedrive on the pendant, out of the tissue: a resume does not pull it out "
                 "through the force that stopped the retract), then " if rep.fault.get("retract_blocked") else "")
        then = (f"{first}run again with the same --out to resume" if rep.fault["kind"] != "force_limit" else
                "a resume would press the probes that stopped at the force limit again and stop the same way: the "
                "tissue is stiffer than the plan expects, or the sensor reads high; plan shallower or with a higher "
                "force limit if the tissue allows, into another --out")
        print(f"  completed probes are in {out / 'probes.jsonl'}; {then}")
    report = rep.to_dict()
    rr = sim_range_report(arm) if arm is not None else None
    if rr is not None:         # the simulated force left the model's range: recorded in run.json, never silent
        report["sim_force_beyond_model_range"] = rr
        run_json = out / "run.json"
        d = json.loads(run_json.read_text(encoding="utf-8"))
        d["sim_force_beyond_model_range"] = rr
        tmp = run_json.with_name("run.json.tmp")
        tmp.write_text(json.dumps(d, indent=1))
        tmp.replace(run_json)
        print(f"WARNING: {rr['note']} ({rr['samples_beyond_model_range']} samples, deepest "
              f"{rr['deepest_m'] * 1e3:.2f} mm)")
    if args.json:
        write_json(args.json, report)
    return {"ok": EXIT_OK, "rejected": EXIT_REJECTED, "interrupted": EXIT_INTERRUPTED}.get(rep.status, EXIT_FAULT)


def _run_controller(plan: Plan, args, out: Path, cfg: DriverConfig):
    """Start the simulated controller (child process, a loopback address of its own), connect real ur_rtde, run."""
    out.mkdir(parents=True, exist_ok=True)
    try:
        truth = truth_scene(plan, args.truth) if args.force_model == "fem" else None
        ctl = start_controller(scene=truth, sensor=args.sensor, seed=args.seed,
                               inject=args.inject, force=args.force_model, tissue_pose=plan.frames.tissue_pose_base,
                               mesh_m=args.sim_mesh_m, tool=plan.frames.tcp_offset, host="auto",
                               log_path=out / "simcontroller.log", netft_sensor_pose=controller_pose(args))
    except PortsUnavailable as e:
        raise ControllerPortsUnavailable(str(e)) from None
    with ctl:
        return _run_host(plan, args, out, cfg, ctl.host)


class NotConnected(RuntimeError):
    """The link could not be made, or the arm is not ready (the message says what the operator must do)."""


def _run_host(plan: Plan, args, out: Path, cfg: DriverConfig, host: str) -> RunReport:
    """Connect ur_rtde and run, in a child process (app.isolate): if the vendor client crashes, the records are on
    disk and this process still reports the fault."""
    try:
        tag, value = run_in_child(_linked_session, plan, args, out, cfg, host,
                                  start_timeout_s=args.connect_timeout_s)
    except ChildTimeout:
        raise NotConnected(f"no answer from the controller at {host} within {args.connect_timeout_s:g} s while "
                           f"connecting (frozen, overloaded, or not a UR controller); nothing was sent") from None
    except ChildDied as e:
        # the client is gone; what it left on the controller may be a program ur_rtde uploaded on its own (no
        # watchdog): stop it through the dashboard (always safe)
        stopped = dashboard_stop(host)
        return _crash_report(out, e, program_stopped=stopped)
    except ChildError as e:
        # the link's process raised what is not a probe fault (a full disk, a bug): the driver's run stops the arm
        # before it re-raises, but it may not have managed, and the error may come from before or after the run; the
        # program is stopped through the dashboard too (always safe), as after a crash (session 54's reviews: a
        # traceback, then a line that said the arm stopped whether or not it had)
        stopped = dashboard_stop(host)
        disk = any(m in str(e) for m in ("No space left", "Disk quota", "Read-only file system"))
        raise RunFailed(f"the process holding the arm's link failed: {e.type_name}: {e}; the control program "
                        + ("was stopped through the dashboard" if stopped else
                           "could not be stopped through the dashboard: check the arm on the pendant")
                        + f"; the records written before are kept in {out} (run.json says whether the driver stopped "
                          f"and retracted)" + ("; free space, then run again: it resumes" if disk else "")) from None
    if tag == "not_connected":
        raise NotConnected(value)
    return value


def _linked_session(started, plan: Plan, args, out: Path, cfg: DriverConfig, host: str):
    """(In the child.) Connect, run, and end the session: a clean end stops the control script; the link is always
    closed, every call within its deadline. ``started()`` tells the parent the connection is made."""
    try:
        c, r = connect(host)
    except RuntimeError as e:
        return "not_connected", str(e)
    started()
    clean = False
    fs = linked_source(args, c, r, plan.frames.tcp_offset, host)
    try:
        rep = None
        rep = run_plan(plan, c, r, out, config=cfg, resume=not args.fresh, progress=_progress,
                       diagnose=lambda: LOCAL_CONTROL if remote_control(host) is False else None, force_source=fs)
        clean = rep.status == "ok"
        return "report", rep
    finally:
        # after a silent link nothing more is sent, not even a disconnect (a call may still be pending on it):
        # the child's exit closes the sockets
        fs.close()
        if not (rep is not None and rep.fault and rep.fault.get("silent_link")):
            end_session(c, r, clean)


CRASH_LOST_PROBE_NOTE = ("a probe in progress when the client crashed has no record unless the driver wrote it "
                         "first: its samples were in the crashed process; the completed probes are on disk and a "
                         "resume presses the lost one again")


def _crash_report(out: Path, err: ChildDied, program_stopped: bool | None = None) -> RunReport:
    """The run's report when the link's process died: what its driver wrote to run.json, with the crash as the
    fault (the fault the driver was handling, if any, is kept beside it)."""
    run_json = out / "run.json"
    d = json.loads(run_json.read_text(encoding="utf-8")) if run_json.exists() else {}
    earlier = d.get("fault")
    fault = {"kind": FaultKind.CLIENT_CRASHED, "message": f"{err}: the ur_rtde client crashed",
             "probe_index": (earlier or {}).get("probe_index"), "controller_time_s": d.get("controller_time_s"),
             "detected_unix_s": (earlier or {}).get("detected_unix_s"),
             "stopped": False, "retracted": False,
             "notes": ["no command could be sent after the crash; the last command was a bounded moveL (target no "
                       "deeper than the planned depth) and the controller's RTDE watchdog, no longer kicked, stops "
                       "the program and the motion; check the arm on the pendant before resuming",
                       CRASH_LOST_PROBE_NOTE]
             + ([f"the driver was handling: {earlier.get('kind')}: {earlier.get('message')}"] if earlier else [])
             + ({True: ["the control program was then stopped through the dashboard"],
                 False: ["the dashboard did not answer: stop the program on the pendant"]}.get(program_stopped, []))}
    fault["stopped"] = bool(program_stopped)
    if program_stopped:
        fault["stopped_by"] = "the dashboard's stop"
    d.update(status=RunStatus.FAULT, fault=fault, earlier_fault=earlier)
    out.mkdir(parents=True, exist_ok=True)
    tmp = run_json.with_name("run.json.tmp")
    tmp.write_text(json.dumps(d, indent=1))
    tmp.replace(run_json)
    keys = ("n_planned", "n_ok", "n_force_limit", "n_depth_limit", "n_rejected", "n_skipped", "controller_time_s", "wall_s",
            "program_restarts")
    return RunReport(RunStatus.FAULT, str(out), fault=fault, problems=d.get("problems", []),
                     **{k: d[k] for k in keys if d.get(k) is not None})


if __name__ == "__main__":
    sys.exit(main())
