"""What `palpate run` is made of besides its belief side: the executors that turn a plan into probe records (the
simulated arm holding the TRUE scene inside a closure, the simulated controller, a real UR controller), the options
that decide a run's rounds and the resume rules over an output directory. Shared by the 2D flow
(app.commands.run) and the 3D one (app.commands.run3d).
"""
from __future__ import annotations

import contextlib
import fnmatch
import hashlib
import json
import math
import re
from pathlib import Path

from app.cell import CONNECT_TIMEOUT_S, print_preflight, read_confirmation
from app.errors import UsageError
from app.figchild import usable_cores
from app.ftoptions import controller_pose, inmemory_source, linked_source
from app.isolate import ChildDied, ChildError, ChildTimeout, run_in_child
from core.contracts import MEASURED, Limits, Plan, default_depth_limit_m
from fem.scene import BUILTIN
from planner.plan import replan
from planner.refine import CONTACT_MARGIN, contact_floor_m, prior_force, renumber
from robot.driver import preflight, run_plan, unfelt_probes
from robot.link import connect, end_session, receive_once
from robot.records import DONE, damaged_note, done_indices, latest_by_index, move_aside, raw_damaged_note
from robot.sim import SimRTDEControl, SimRTDEReceive
from robot.simarm import build_truth_arm
from robot.simlaunch import start_controller
from robot.truth import TruthConditions, TruthError, conditions_of


class RunAborted(RuntimeError):
    def __init__(self, report):
        f = report.fault
        what = (str(f.get("message") or getattr(f.get("kind"), "value", f.get("kind")))
                + (f" (probe {f['probe_index']})" if f.get("probe_index") is not None else "")
                + (f"; motion stopped by {f['stopped_by']}" if f.get("stopped_by") else "")) if f else \
            "; ".join(map(str, report.problems))
        super().__init__(f"the arm run ended with status {report.status}: {what}")
        self.report = report


def _runner(get_interfaces, out: Path, stats: dict):
    """execute(plan, round) over interfaces from ``get_interfaces(plan)``: renumbered probes, one probes.jsonl. A
    round's plan is saved once (OUT/plan_round<k>.json, reused on resume); its records are the last record of each of
    its indices in probes.jsonl, the ones measured by an earlier (interrupted) run of the same options included."""

    def execute(plan, k):
        renumber(plan, stats["next_index"])
        path = out / f"plan_round{k}.json"
        if not path.exists():
            plan.save(path)
        stats["next_index"] += len(plan.probes)
        latest = latest_by_index(out)
        if all(p.index in latest and latest[p.index].status in MEASURED for p in plan.probes):
            recs = [latest[p.index] for p in plan.probes]      # measured before: replay, the arm is not needed
        else:
            # the plan's time of the probes pressed now (robot_s counts those only: a resumed run's earlier ones
            # are neither; before session 48 every round's whole plan was counted, a resume's robot_s far below it)
            stats["planned_s"] += sum(p.duration_s for p in plan.probes
                                      if not (p.index in latest and latest[p.index].status in DONE))
            c, r, fs = get_interfaces(plan)
            rep = run_plan(plan, c, r, out, resume=True, progress=lambda rec, i, n: None, force_source=fs)
            stats["controller_s"] += sum(rec.duration_s or 0.0 for rec in rep.records)   # arm time probing
            stats["reports"].append(rep.to_dict())
            if rep.status != "ok":
                raise RunAborted(rep)
            latest = latest_by_index(out)
            recs = [latest[p.index] for p in plan.probes if p.index in latest]
        stats["n_probes"] += sum(1 for rec in recs if rec.status in MEASURED)
        return recs
    return execute


def sim_executor(truth, *, sensor: str, seed: int, out: Path, stats: dict, holder: dict | None = None,
                 conditions: TruthConditions | None = None, ft=None, cleanup: contextlib.ExitStack | None = None):
    """The simulated arm holding the TRUE scene and its conditions (in this closure only); created at the first
    plan. ``holder["arm"]`` gets the arm (for its force-model range report, never its truth). ``ft``: the run's
    options when the force comes from a simulated Net F/T box (app.ftoptions; None: the wrist sensor); its source
    is closed by ``cleanup``."""
    arm = {}

    def interfaces(plan):
        if "c" not in arm:
            a = build_truth_arm(truth, sensor=sensor, seed=seed, tissue_pose=plan.frames.tissue_pose_base,
                                tcp_offset=plan.frames.tcp_offset, start_above_pose=plan.probes[0].approach_pose,
                                conditions=conditions)
            arm.update(c=SimRTDEControl(a), r=SimRTDEReceive(a), fs=None)
            if ft is not None:
                arm["fs"], _ = inmemory_source(ft, a, arm["c"], plan.frames.tcp_offset)
                if cleanup is not None:
                    cleanup.callback(arm["fs"].close)
            if holder is not None:
                holder["arm"] = a
        return arm["c"], arm["r"], arm["fs"]
    return _runner(interfaces, out, stats)


def answers(host: str) -> None:
    """Whether the controller at ``host`` answers, within CONNECT_TIMEOUT_S: UsageError (one line) if not. ur_rtde's
    constructors wait for good on a controller that accepts connections but never answers, holding the interpreter,
    so the first contact is made in a child process that is killed at the deadline (as palpate-cell does)."""
    try:
        # (a fresh interpreter: the table may be building on other threads here, whose locks a fork would copy)
        run_in_child(receive_once, host, start_timeout_s=CONNECT_TIMEOUT_S, start_method="spawn")
    except ChildTimeout:
        raise UsageError(f"--host {host}: no answer from the controller within {CONNECT_TIMEOUT_S:g} s while "
                         f"connecting (frozen, overloaded, or not a UR controller); nothing was sent") from None
    except (ChildError, ChildDied) as e:
        raise UsageError(f"--host {host}: cannot connect: {' '.join(str(e).split())}") from None


def _link(link: dict, host: str, plan, stats: dict, cleanup: contextlib.ExitStack, ft, ft_host=None) -> tuple:
    """Connect ur_rtde to ``host`` once (and the force source: ``ft`` the run's options, app.ftoptions); closed by
    ``cleanup``."""
    if "c" not in link:
        answers(host)
        try:
            link["c"], link["r"] = connect(host)
        except RuntimeError as e:        # refused, unreachable, or the arm not ready (ArmNotReady says what to do)
            raise UsageError(f"--host {host}: cannot connect: {' '.join(str(e).split())}") from None
        cleanup.callback(lambda: end_session(link["c"], link["r"], clean=stats["clean_end"]))
        link["fs"] = linked_source(ft, link["c"], link["r"], plan.frames.tcp_offset, ft_host)
        cleanup.callback(link["fs"].close)
    return link["c"], link["r"], link["fs"]


def arm_executor(host: str, out: Path, stats: dict, cleanup: contextlib.ExitStack, ft=None):
    """A real UR controller at ``host``, over ur_rtde (no truth: only the prior scene exists)."""
    link = {}
    return _runner(lambda plan: _link(link, host, plan, stats, cleanup, ft), out, stats)


def controller_executor(scene_spec: str, *, sensor: str, seed: int, out: Path, stats: dict,
                        cleanup: contextlib.ExitStack, ft=None):
    """The simulated UR controller (robot.simcontroller, a child process holding the TRUE scene; with ``--ft netft``
    serving a simulated Net F/T box too), driven through the real ur_rtde client; started at the first plan, stopped
    when the run ends."""
    link = {}

    def interfaces(plan):
        if "ctl" not in link:
            link["ctl"] = cleanup.enter_context(start_controller(
                scene=scene_spec, sensor=sensor, seed=seed, tissue_pose=plan.frames.tissue_pose_base,
                tool=plan.frames.tcp_offset, host="auto", log_path=out / "simcontroller.log",
                netft_sensor_pose=controller_pose(ft)))
        return _link(link, link["ctl"].host, plan, stats, cleanup, ft, link["ctl"].host)
    return _runner(interfaces, out, stats)


RUN_FILES = ("probes.jsonl", "raw", "run.json", "run_history.jsonl", "result.json", "run_options.json",
             "fig_run.png", "simcontroller.log")


def holds_run(out: Path) -> bool:
    return out.is_dir() and any((out / n).exists() for n in RUN_FILES) or any(out.glob("plan_round*.json"))


TRUTH_OPTIONS = {"truth_surface_offset_m": "surface_offset_m", "truth_surface_tilt_rad": "surface_tilt_rad",
                 "truth_relaxation": "relaxation_fraction", "truth_relaxation_tau_s": "relaxation_tau_s",
                 "truth_sensor_bias_n": "sensor_bias_n", "truth_sensor_drift_n_per_s": "sensor_drift_n_per_s",
                 "truth_hyperelastic": "hyperelastic"}


def truth_conditions(args, scene=None) -> TruthConditions | None:
    """The simulated world's conditions: the truth scene file's [truth] table, overridden by --truth-* options.
    None for a real arm. Refused (UsageError): --truth-* options without the in-memory simulated arm; conditions
    that cannot apply to the truth ``scene`` (TruthConditions.check_scene)."""
    given = {f: getattr(args, o) for o, f in TRUTH_OPTIONS.items() if getattr(args, o, None) is not None}
    if given and (args.host or args.sim == "controller"):
        opt = "--" + next(o for o, f in TRUTH_OPTIONS.items() if f in given).replace("_", "-")
        raise UsageError(f"{opt}: the simulated truth's conditions are options of the in-memory simulated arm "
                         f"(--sim); {'a real arm has no simulated truth' if args.host else 'for --sim controller put them in the scene file [truth] table'}")
    if args.host:
        return None
    try:
        cond = (TruthConditions() if args.scene in BUILTIN else conditions_of(args.scene)).replace(**given)
        if "relaxation_tau_s" in given and not cond.relaxation_fraction:
            raise UsageError(f"--truth-relaxation-tau-s {given['relaxation_tau_s']:g}: the truth does not relax (give "
                             f"--truth-relaxation [FRACTION], or relaxation_fraction in the scene's [truth] table)")
        if scene is not None:
            cond.check_scene(scene)
        return cond
    except TruthError as e:
        opt = next((o for o, f in TRUTH_OPTIONS.items() if f in given and f in str(e)), None)
        raise UsageError(f"--{opt.replace('_', '-')} {given[TRUTH_OPTIONS[opt]]}: {e}" if opt else str(e)) from None


def workers_for_fits(args) -> int:
    """The processes the localizer's fits may use (planner.forkmap: the same estimates with any number):
    ``--fit-workers``, else 2 in a simulated run on two or more cores and 1 next to a real arm (``--host``: its
    process holds ur_rtde's threads and sockets, which a fork would copy; a larger --fit-workers is refused there)."""
    if args.fit_workers is not None:
        return args.fit_workers
    return 2 if not args.host and usable_cores() >= 2 else 1


OPTIONAL_RUN_OPTIONS = ("ft", "depth_limit_m", "thickness_sigma_m")     # in run_options only when given (the
#                                                                          depth limit: or planned to by default)


def run_options(args, scene, cond: TruthConditions | None = None, belief=None) -> dict:
    """What decides the rounds of a run: a re-run resumes only with all of these equal. ``belief``: the --prior
    scene's prior (its content key is kept, as the scene's: an edited prior file is another run)."""
    plan_sha = hashlib.sha256(Path(args.plan).read_bytes()).hexdigest() if args.plan else None
    return {"scene": args.scene, "scene_key": scene.key(), "plan_sha256": plan_sha,
            "prior": args.prior, **({"prior_key": belief.key()} if belief is not None else {}),
            "truth_conditions": None if cond is None or cond.ideal else cond.to_dict(),
            "arm": f"host {args.host}" if args.host else f"sim {args.sim or 'inmemory'}",
            "sensor": args.sensor, "seed": args.seed, "waypoints": None if args.plan else args.waypoints,
            **({"grid": list(args.grid)} if getattr(args, "grid", None) and not args.plan else {}),
            "refine_waypoints": args.refine_waypoints, "budget_probes": args.budget_probes,
            "target_uncertainty_m": args.target_uncertainty_m, "strategy": args.strategy,
            **({"ft": args.ft.text} if args.ft.kind != "rtde" else {}),     # absent for the wrist sensor: older
            #                                                                 runs resume
            **_depth_limit_option(args, scene, belief),
            **({"thickness_sigma_m": args.thickness_sigma_m}
               if getattr(args, "thickness_sigma_m", None) is not None else {})}


def _depth_limit_option(args, scene, belief) -> dict:
    """run_options' depth limit: as given, else (without --plan) the default the run plans to on its prior's tip
    (``default_depth_limit_m``: 0.8 of a radius below 5 mm, since session 52), so a resume compares what was
    planned: given at that value or left out, the same run (a review's 3 mm tip: left out, then given at the 2.4 mm
    it had planned to, was refused as "not given (default 0.004)")."""
    given = getattr(args, "depth_limit_m", None)
    if given is not None:
        return {"depth_limit_m": given}
    if args.plan:
        return {}
    prior = belief if belief is not None else scene.prior()
    return {"depth_limit_m": default_depth_limit_m(prior.indenter.radius_m)}


def run_limits(args, tip_radius_m: float) -> Limits:
    """The limits a run plans its coarse raster to (without --plan): the defaults, and ``--depth-limit-m`` (when not
    given, ``default_depth_limit_m`` of the tip's radius)."""
    lim = Limits()
    given = getattr(args, "depth_limit_m", None)
    lim.depth_limit_m = float(given) if given is not None else default_depth_limit_m(tip_radius_m)
    return lim


def refuse_unfelt(plan, args) -> None:
    """UsageError, before any motion, when the run's own coarse plan has probes the driver would stop at at once
    (robot.driver.unfelt_probes: the prior's force at the depth limit not FEEL_MARGIN x the contact threshold), as
    a given --plan's are: the run would end at its first such probe with contact_unfelt, and the same command could
    never resume (session 59's review: a run told `--depth-limit-m 0.002` by the previous one's hint). Names the
    shallowest limit at which every probe feels the tissue by fem's force (planner.refine.contact_floor_m)."""
    bad = unfelt_probes(plan)
    if not bad:
        return
    k, why = min(bad.items())
    limit = plan.limits.depth_limit_m
    floor = contact_floor_m(plan, prior_force(plan), upto_m=plan.tip_radius_m())
    given = getattr(args, "depth_limit_m", None) is not None
    better = (f"; every probe presses the tissue {CONTACT_MARGIN:g}x the threshold from --depth-limit-m {floor:g}"
              if math.isfinite(floor) and floor > limit else "")
    more = f" (and {len(bad) - 1} more probes)" if len(bad) > 1 else ""
    raise UsageError(f"--depth-limit-m {limit:g}{'' if given else ' (the default)'}: refused before any motion: "
                     f"probe {k}{more}: {why}{better}")


def _previous_options(out: Path) -> dict | None:
    try:
        d = json.loads((out / "run_options.json").read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as e:
        raise UsageError(f"--out {out}: cannot read run_options.json of the run there ({e}); use --fresh (moves the "
                         f"old files aside) or another --out") from None
    return d if isinstance(d, dict) else {}


# an optional option left out is its default: given at that value, or left out where it was given at it, it is the
# same run (a review's resume with --depth-limit-m 0.004, the default, was refused as other options)
OPTIONAL_DEFAULTS = {"depth_limit_m": Limits().depth_limit_m}


def _same_option(k: str, prev: dict, now: dict) -> bool:
    """Do two runs' option ``k`` differ only in how it was written? The scene or the prior by another path or name
    to the same content (its key), an optional option at its default."""
    if k == "scene":
        return prev.get("scene_key") == now.get("scene_key")       # (the content decides; the key is compared too)
    if k == "prior":            # the content decides; a run before session 49 kept no prior_key: the same file
        if "prior_key" in prev and "prior_key" in now:
            return prev["prior_key"] == now["prior_key"]
        return _same_file(prev.get(k), now.get(k))
    if k == "prior_key":
        return k not in prev
    if k in OPTIONAL_DEFAULTS:
        return prev.get(k, OPTIONAL_DEFAULTS[k]) == now.get(k, OPTIONAL_DEFAULTS[k])
    return False


def _same_file(a, b) -> bool:
    """Two spellings of one existing file (a built-in scene's name is not a file: names must be equal)."""
    if not (isinstance(a, str) and isinstance(b, str)):
        return a == b
    try:
        return Path(a).is_file() and Path(b).is_file() and Path(a).resolve() == Path(b).resolve()
    except OSError:
        return False


def check_resume(out: Path, opts: dict, fresh: bool) -> bool:
    """True if this run resumes the one in ``out``; raises UsageError if it may neither resume nor start."""
    if fresh or not holds_run(out):
        return False
    prev = _previous_options(out)
    if prev is None:
        raise UsageError(f"--out {out} holds a run without run_options.json (an older palpate?): it cannot be "
                         f"resumed safely; use --fresh (moves the old files to {out}/previous-<time>/) or another --out")
    def said(k, d):
        return repr(d[k]) if k in d else f"not given (default {OPTIONAL_DEFAULTS[k]!r})"
    diff = [f"{k} was {said(k, prev) if k in OPTIONAL_DEFAULTS else repr(prev.get(k))}, now {v!r}"
            for k, v in opts.items() if prev.get(k) != v and not _same_option(k, prev, opts)]
    # options kept only when given (older runs resume without them): given before, left out now is a change too
    diff += [f"{k} was {prev[k]!r}, now not given" for k in OPTIONAL_RUN_OPTIONS
             if k in prev and k not in opts and not _same_option(k, prev, opts)]
    if diff:
        raise UsageError(f"--out {out} holds a run with other options ({'; '.join(diff)}): re-run with the same "
                         f"options to resume, or use --fresh (moves the old files to {out}/previous-<time>/) or "
                         f"another --out")
    return True


def new_stats() -> dict:
    """What the executors count over a run's rounds."""
    return {"clean_end": False, "n_probes": 0, "next_index": 0, "planned_s": 0.0, "controller_s": 0.0, "reports": []}


def noise_seed(seed: int, out: Path, resume: bool) -> tuple[int, str]:
    """(the simulated sensor's seed for this process, a note for the run's "probing on" line): ``seed`` itself on a
    fresh run; on a resumed run with records on disk, a seed drawn from (``seed``, the number of probes recorded), so
    the probes pressed after a resume draw noise (and the sensor's bias and drift) of their own. Until session 60 a
    resumed process restarted the noise from ``seed``: its first probe's free-air samples repeated the run's first
    probe's, noise the localizer takes as independent. The same interruptions give the same seeds (reproducible), but
    a resumed run's later probes are not those of an uninterrupted run with the same seed."""
    k = len(latest_by_index(out)) if resume else 0
    if k == 0:
        return seed, ""
    resumed = int.from_bytes(hashlib.sha256(f"palpate noise {seed} after {k}".encode()).digest()[:4], "little")
    return resumed, f"; resumed after {k} probe records: noise stream {resumed}"


def choose_executor(args, out: Path, scene, cond, plan0, resume: bool, stats: dict, cleanup: contextlib.ExitStack,
                    sim_arm: dict, say) -> tuple:
    """(execute, where, truth) for the run's arm: a real UR controller (after the pre-flight and the operator's
    confirmation; no truth), the simulated controller or the in-memory simulated arm (the truth: ``scene``)."""
    if args.host:
        where = f"UR controller at {args.host}"
        say("WARNING: this moves a real arm into tissue. Check the tissue pose, TCP, force limit "
            f"{plan0.limits.force_limit_n} N and the emergency stop first.")
        print_preflight(preflight(plan0, done_indices(out) if resume else set()), where)
        if not args.yes and not read_confirmation():
            raise UsageError("not confirmed (type 'yes' to move the arm, or give --yes); nothing sent, nothing moved")
        execute = arm_executor(args.host, out, stats, cleanup, ft=args)
        truth = None
    elif args.sim == "controller":
        seed, said = noise_seed(args.seed, out, resume)
        where = f"simulated UR controller over ur_rtde (sensor {args.sensor}, seed {args.seed}{said}; real time)"
        truth = scene
        execute = controller_executor(args.scene, sensor=args.sensor, seed=seed, out=out, stats=stats,
                                      cleanup=cleanup, ft=args)
    else:
        seed, said = noise_seed(args.seed, out, resume)
        where = f"simulated arm (sensor {args.sensor}, seed {args.seed}{said})"
        truth = scene
        execute = sim_executor(truth, sensor=args.sensor, seed=seed, out=out, stats=stats, holder=sim_arm,
                               conditions=cond, ft=args if args.ft.kind == "netft" else None, cleanup=cleanup)
    if args.ft.kind == "netft":
        where += (f"; force from the Net F/T box ({args.ft.host or 'simulated'}), which the UR's own force "
                  f"protection does not see: the driver's force limit is the only guard on it")
    return execute, where, truth


def check_fresh_inputs(args, out: Path) -> None:
    """UsageError for ``--fresh`` with an input file that is one of OUT's run files (``--plan OUT/plan_round1.json``):
    kept in OUT as the command's input, the new run would take it for its own round's plan or options."""
    if not args.fresh:
        return
    for opt in ("scene", "plan", "prior"):
        given = getattr(args, opt, None)
        if not isinstance(given, str) or not Path(given).is_file():
            continue
        p = Path(given).resolve()
        if p.parent == out.resolve() and (fnmatch.fnmatch(p.name, "plan_round*.json") or p.name in RUN_FILES):
            raise UsageError(f"--{opt} {given}: a file of the run in --out {out}, which --fresh sets aside (kept "
                             f"there, the new run would take it for its own); copy it out of {out} first")


def open_out(args, out: Path, opts: dict, say) -> None:
    """Create OUT (after every check passed): ``--fresh`` moves a previous run's files aside (never deletes them);
    run_options.json is written once."""
    if args.fresh:
        inputs = [getattr(args, k, None) for k in ("scene", "plan", "prior")]     # (a built-in's name is no file)
        moved = move_aside(out, keep=[a for a in inputs if isinstance(a, str)]) if holds_run(out) else None
        if moved is not None:
            say(f"--fresh: the previous run's files are in {moved}")
    out.mkdir(parents=True, exist_ok=True)
    if not (out / "run_options.json").exists():
        tmp = out / "run_options.json.tmp"
        tmp.write_text(json.dumps(opts, indent=1))
        tmp.replace(out / "run_options.json")


def round_planner(plan0: Plan, out: Path):
    """``plan_round(positions)`` for the refinement loop (planner.refine, planner.refine3d): round 0 is the coarse
    plan; a later round's plan is the one saved in OUT (a resumed run repeats its rounds), else the coarse plan
    re-planned over the positions (x, or (x, y) on a block) with its frames, limits, motion and options."""
    count = {"k": 0}

    def plan_round(positions):
        k = count["k"]
        count["k"] += 1
        if k == 0:
            return plan0
        saved = out / f"plan_round{k}.json"
        return Plan.load(saved) if saved.exists() else replan(plan0, positions)
    return plan_round


def plan_options_hint(message: str, args) -> str:
    """A planning error's message for `palpate run`: the options it names that run does not have are `palpate
    plan`'s (run plans with their defaults), so say where to give them."""
    missing = [o for o in dict.fromkeys(re.findall(r"--[a-z][a-z0-9-]*", message))
               if not hasattr(args, o[2:].replace("-", "_"))]
    if not missing:
        return message
    return (f"{message} ({', '.join(missing)}: options of `palpate plan`, which `palpate run` takes at their "
            f"defaults; plan there with them, then `palpate run --plan plan.json`)")


def measured_on_disk(out: Path) -> int:
    """How many probes in OUT's records hold a measurement (their latest record: ok, force_limit, depth_limit)."""
    return sum(1 for r in latest_by_index(out).values() if r.status in MEASURED)


def resuming_note(out: Path) -> str:
    """What a resumed run keeps and what it presses again (a stop at the force limit may have been a spike: pressed
    again)."""
    done, measured = len(done_indices(out)), measured_on_disk(out)
    again = (f" ({measured - done} stopped at the force limit are pressed again: a stop there may have been a "
             f"sensor's spike)" if measured > done else "")
    note = f"resuming the run in {out}: {done} probes measured before are not pressed again{again}"
    for damaged in (damaged_note(out), raw_damaged_note(out)):
        if damaged:
            note += "\n" + damaged
    if not (out / "probes.jsonl").exists() and any((out / "raw").glob("probe_*.npz")):
        note += (f"\nwarning: {out / 'probes.jsonl'} is missing but {out / 'raw'} holds probes' samples: they are "
                 f"kept, and every probe is pressed again (new samples get new file names)")
    return note


def no_contact(out: Path) -> dict | None:
    """The probes in OUT's records whose force was measured (their latest record) but that never felt contact (the
    force stayed below the contact threshold down to the planned depth; those reading far less than the prior
    predicts are also flagged implausible and left out of the fit), or None when every probe felt it. The prior
    says there is tissue there: it is absent, lower or far softer than the prior says, which the localizer's model
    (one surface offset and tilt, one stiffness scale) may not represent."""
    recs = [r for r in latest_by_index(out).values() if r.status in MEASURED]
    nc = sorted((r for r in recs if r.contact_depth_m is None), key=lambda r: (r.x_m, r.y_m))
    if not nc:
        return None
    return {"n": len(nc), "of": len(recs), "x_m": [float(r.x_m) for r in nc], "y_m": [float(r.y_m) for r in nc],
            "index": [int(r.index) for r in nc], "expected_by_prior": [_expected_by_prior(r) for r in nc]}


def _expected_by_prior(rec) -> bool:
    """Does the prior itself predict less than the contact threshold at the probe's planned depth, and is the probe's
    reading used (not flagged implausible)? (A probe near a side, or at a coarse raster's shallower depth, with a
    small tip on soft tissue: session 52's review of a 40 mm block and a 2 mm tip, 24 of 84 probes, every one of them
    predicted below it.)"""
    f, thr = rec.force_predicted_prior_n, rec.contact_threshold_n
    return (rec.implausible is None          # (one left out of the fit is not "as the prior predicts": warned)
            and f is not None and thr is not None and math.isfinite(f) and math.isfinite(thr) and f < thr)


def left_out(out: Path) -> dict | None:
    """The probes whose force was measured (their latest record) but left out of the fit as no tissue's force
    (``implausible``, robot.records.implausibility), or None; ``no_contact`` of them felt no contact either (the
    no-contact warning names those too)."""
    recs = [r for r in latest_by_index(out).values() if r.status in MEASURED]
    odd = sorted((r for r in recs if r.implausible is not None), key=lambda r: r.index)
    if not odd:
        return None
    return {"n": len(odd), "of": len(recs), "index": [int(r.index) for r in odd],
            "no_contact": sum(r.contact_depth_m is None for r in odd), "first_reason": odd[0].implausible}


def left_out_warning(odd: dict) -> str:
    """One line: how many probes the fit left out as reading no tissue's force, and the first one's reason (a
    session-54 review: a sensor drifting 3 mN/s left 9 of 15 probes out, the rest said NO STONE, and nothing said
    why)."""
    most = 2 * odd["n"] >= odd["of"]
    return (f"warning: {odd['n']} of {odd['of']} probes read forces no tissue gives and are left out of the fit "
            f"(probes.jsonl's implausible; probe {odd['index'][0]}: {odd['first_reason']})"
            + ("; with most of them out, the answer rests on the rest: a drifting or spiking sensor, or a collision? "
               "(`palpate ft` shows the sensor's drift in free air)" if most else ""))


def no_contact_warning(nc: dict, three_d: bool = False) -> str:
    """What the probes that felt no contact mean: a warning naming those where the prior predicts contact (the
    tissue there is not as it says); a note only when the prior itself predicts less than the threshold at every one
    of them (their forces are still fitted; the surface is registered from the other probes' onsets)."""
    expected = nc.get("expected_by_prior", [False] * nc["n"])
    odd = [(x, y) for x, y, e in zip(nc["x_m"], nc["y_m"], expected) if not e]
    n_exp = nc["n"] - len(odd)
    if not odd:
        return (f"note: {nc['n']} of {nc['of']} probes felt no contact down to their planned depth, as the prior "
                f"predicts there (its force below the contact threshold: near a side, or at the coarse raster's "
                f"shallower depth); their forces are fitted, the surface is registered from the other probes' onsets"
                if nc["n"] < nc["of"] else
                "warning: no probe felt contact down to its planned depth, as the prior predicts (its force below the "
                "contact threshold at every probe): the surface was not registered from contact onsets")
    where = ", ".join((f"({x * 1e3:.1f}, {y * 1e3:.1f})" if three_d else f"{x * 1e3:.1f}")
                      for x, y in odd[:8]) + (", ..." if len(odd) > 8 else "")
    also = (f"; {n_exp} more felt none where the prior itself predicts less than the contact threshold"
            if n_exp else "")
    return (f"warning: {len(odd)} of {nc['of']} probes felt no contact down to their planned depth (at "
            f"{'(x, y)' if three_d else 'x'} = {where} mm): the tissue there is absent, lower than the prior says, or "
            f"too soft to pass the contact threshold (the probes reading far less than it predicts are left out of "
            f"the fit: probes.jsonl's implausible){also}")


# faults that a resumed run meets again until the cell is changed: what to change first
_REPLAN = ("if the tissue's surface is higher than registered, re-register it or plan a larger approach height "
           "(palpate plan --approach-height-m, given with --plan), then run with --fresh or another --out")
RETRACT_BLOCKED_FIX = ("the arm is held where a retract met a force, the tip perhaps in the tissue: free it first "
                       "(freedrive on the pendant, out of the tissue), then the same command resumes (with the tip "
                       "still in the tissue it refuses to pull it out)")
FORCE_LIMIT_FIX = ("the same command would press those probes again and stop the same way (a stop at the force "
                   "limit is pressed again on a resume: it may have been a sensor's spike): the tissue is stiffer than "
                   "the plan expects, or the sensor reads high; plan shallower (--depth-limit-m) or, if the tissue "
                   "allows, with a higher --force-limit-n, with --fresh or another --out")
FIRST_FIX = {"free_air_force": "the same command resumes once the sensor reads steady in free air with its force "
                               "sign right (until then it ends the same way); " + _REPLAN,
             "surface_high": _REPLAN[len("if the tissue's surface is higher than registered, "):],
             "sensor_noise": "the same command resumes once the sensor's free-air noise is below the force limit's "
                             "allowance (until then it ends the same way)",
             "force_limit": FORCE_LIMIT_FIX}


def unplaced(loc, tissue) -> str | None:
    """Why a detected stone's estimate is no location (None when it is one): its 1-sigma interval across the surface
    wider than a quarter of the tissue (x, or y on a block) or in depth wider than the tissue is thick. A
    session-49 review: a sensor drifting 0.01 N/s (inside the [truth] table's range) gave LR 20 at a threshold of 20
    with chi2 3810 on 32 degrees of freedom, and the line said STONE at x 22.93 +- 69.94 mm, depth 10 +- 276 mm.
    (The studies' widest detected estimate: 5.4 mm across, 21.8 mm deep, a 6.5 mm stone 39 mm down.)"""
    if tissue is None or not (localized(loc) and loc.detected):
        return None
    spans = [("x", loc.sigma_x_m, tissue.width_m / 4, "a quarter of the width")]
    if getattr(loc, "sigma_y_m", None) is not None and tissue.length_m is not None:
        spans.append(("y", loc.sigma_y_m, tissue.length_m / 4, "a quarter of the length"))
    spans.append(("depth", loc.sigma_depth_m, tissue.height_m, "the thickness"))
    for name, sigma, limit, what in spans:
        if not sigma <= limit:          # (nan too)
            return (f"its {name} sigma, {sigma * 1e3:.1f} mm, is wider than {what} ({limit * 1e3:.1f} mm); chi2 "
                    f"{loc.chi2_1:.0f} on {loc.dof_1} degrees of freedom with the stone, {loc.chi2_0:.0f} without")
    return None


def verdict(loc, res, described: str, status: str, fault: dict | None, nc: dict | None = None,
            tissue=None) -> str:
    """The run's last line's head: STONE / NO STONE and the estimate; NOT LOCALIZED when too few probes were usable
    to fit (a localization needs more measurements than a stone's parameters: the reason says how many); NOT
    DETECTABLE when no probe felt contact (``nc``: ``no_contact``) and the fit found no stone (a fit that did found
    it in the forces below the threshold: a session-45 review's 200 Pa tissue, located within its sigmas while the
    line said nothing could be measured; the no-contact warning is said beside it); NO RESULT when the arm run
    ended with a fault."""
    if nc is not None and nc["n"] == nc["of"] and res is not None and not (localized(loc) and loc.detected):
        return ("NOT DETECTABLE: no probe felt contact down to its planned depth (the tissue is absent, lower than "
                "the prior says, or too soft to pass the contact threshold): nothing about a stone could be measured")
    if res is None:
        kind = fault["fault"]["kind"] if fault and fault.get("fault") else status
        if kind == "interrupted":       # the user's Ctrl-C (or a supervisor's SIGTERM): no fault of the cell
            return ("NO RESULT: interrupted (Ctrl-C or a stop signal): the arm was stopped and its probes are kept; "
                    "the same command resumes")
        blocked = bool(fault and fault.get("fault") and fault["fault"].get("retract_blocked"))
        return (f"NO RESULT: the arm run ended with a fault ({kind}): its probes are kept; "
                + (RETRACT_BLOCKED_FIX if blocked else FIRST_FIX.get(kind, "the same command resumes")))
    if not localized(loc):
        return f"NOT LOCALIZED: {res.stop_reason}"
    why = unplaced(loc, tissue)
    if why is not None:
        return (f"NOT LOCALIZED: the likelihood ratio ({loc.lr:.0f}, threshold {loc.lr_threshold:.0f}) says a stone, "
                f"but the fit cannot place it: {why}: the records fit neither model (a drifting sensor, or tissue "
                f"unlike the prior?); " + described)
    if nc is not None and nc["n"] == nc["of"]:         # (found in forces below the contact threshold)
        described += ("; warning: no probe felt contact: the surface was taken as registered (no contact onsets), "
                      "and the forces were below the contact threshold")
    return ("STONE " if loc.detected else "NO STONE ") + described


INTERRUPTED_AT_REST = ("NO RESULT: interrupted (Ctrl-C or a stop signal) while the arm was at rest (a localization, a "
                       "plan or fem between rounds): its probes are kept; the same command resumes")


EXIT_INTERRUPTED = 130         # a run the user interrupted (as the shell reports a SIGINT; palpate-cell's too)


def exit_code(status: str) -> int:
    """A run's exit status: 0 when the arm run ended well, 130 when interrupted, 1 after a fault."""
    return 0 if status == "ok" else EXIT_INTERRUPTED if status == "interrupted" else 1


VERDICTS = (("NOT DETECTABLE", "not_detectable"), ("NOT LOCALIZED", "not_localized"), ("NO RESULT", "no_result"),
            ("NO STONE", "no_stone"), ("STONE", "stone"))


def verdict_kind(line: str) -> str:
    """result.json's ``verdict`` for a last line from ``verdict``: stone, no_stone, not_localized, not_detectable or
    no_result."""
    return next(kind for head, kind in VERDICTS if line.startswith(head))


def conclude(result: dict, out: Path, loc, res, described: str, status: str, fault: dict | None, say,
             three_d: bool = False, tissue=None) -> str:
    """The run's closing findings into ``result``: the probes that felt no contact (said as a warning too) and the
    verdict; returns the last line's head (``verdict``)."""
    nc = no_contact(out) if res is not None else None
    if nc is not None:
        result["no_contact_probes"] = nc
        say(no_contact_warning(nc, three_d=three_d))
    odd = left_out(out) if res is not None else None
    if odd is not None:
        result["implausible_probes"] = odd
        say(left_out_warning(odd))
    head = verdict(loc, res, described, status, fault, nc, tissue)
    if odd is not None and 2 * odd["n"] >= odd["of"] and head.startswith("NO STONE"):
        # most readings out: "no stone" is the rest's answer, not the run's (a session-54 review: a drifting sensor)
        head = (f"NOT LOCALIZED: {odd['n']} of {odd['of']} probes read forces no tissue gives and were left out, so "
                f"the rest cannot rule a stone out (a drifting or spiking sensor, or a collision?); " + described)
    result["verdict"] = verdict_kind(head)
    return head


def localized(loc) -> bool:
    """Was a fit made (its likelihood ratio is a number)? Not when too few probes were usable."""
    return loc.lr == loc.lr

