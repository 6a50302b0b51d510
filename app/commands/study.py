"""`palpate study accuracy --out DIR [--quick] [--workers N | --scheduler ADDRESS]`: the studies, on dask.

Each study is a list of independent pieces (planner.tasks) run serially (``--workers 1``), on a dask LocalCluster of
this machine (``--workers N``; the default: one worker per CPU) or on an existing dask cluster (``--scheduler
ADDRESS``). The results equal a serial run's (every piece carries its own seed). Finished pieces are kept in
``DIR/pieces/<study>-<options hash>/`` and never overwritten: the same command resumes an interrupted study; other
options start another set beside it. Each invocation appends a line to ``DIR/runs.jsonl`` (when, how long, where).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import sys
import time
from pathlib import Path

from app.commands.output import json_alone, write_json
from app.errors import UsageError
from app.mismatch import Shared, make_plan
from app.mismatch import run_trial as run_mismatch_trial
from app.mismatch import study_trials as mismatch_trials
from app.mismatch_report import write_report as write_mismatch
from app.options import check_output_dir, check_output_file, int_range, is_measured, load_scene, positive_float
from fem.sweep import sweep_piece
from fem.sweep import write_results as write_sweep
from planner.accuracy import run_accuracy, study_trials
from planner.accuracy3d import COARSE, run_accuracy3d, study_trials3d
from planner.accuracy3d_report import write_report as write_accuracy3d
from planner.accuracy_report import write_report
from planner.detect_study import run_detect, study_cases
from planner.detect_study import write_report as write_detect
from planner.finite_strain_response import prior_finite_strain
from planner.surrogate import load_surrogate
from planner.surrogate3d import load_surrogate3d
from planner.tasks import Runner, record_with, run_pieces

STUDIES = {
    "accuracy": "localization and adaptive refinement over random stones against even rasters (planner.accuracy)",
    "mismatch": "whole simulated runs on truths unlike the prior: modulus, Poisson, thickness, surface, relaxation "
                "(app.mismatch)",
    "detect": "predicted detection rate against Monte-Carlo rasters, stones near the margin (planner.detect_study)",
    "sweep": "random valid scenes under load A and B: no NaN, residuals, contact checks (fem.sweep)",
    "accuracy3d": "3D: random spherical stones and healthy blocks, adaptive refinement against even grids "
                  "(planner.accuracy3d; scene block3d)",
}

HELP = """Studies of the localizer, on dask.distributed. Outputs (JSON, CSV, markdown, figures) go into --out.

studies:
""" + "\n".join(f"  {k:10s} {v}" for k, v in STUDIES.items()) + """

  accuracy writes accuracy.csv (one row per trial and method), accuracy.json (summary by method),
  accuracy_ratio.json (equal-accuracy ratios), accuracy.md (the tables) and accuracy.png.
  mismatch writes mismatch.csv (one row per trial), mismatch.json (summary), mismatch.md and mismatch.png; every
           run's files in pieces/mismatch-*/runs/ (100 stones + 40 healthy, --quick 20 + 10; budget 25 probes; the
           truths' one-off models are cached under DIR/cache unless $PALPATE_CACHE_DIR says otherwise).
  detect   writes detect.json, detect.csv, detect.md and detect.png (9 stones x 150 rasters; --quick 4 x 40).
  sweep    writes sweep.json, sweep.csv and sweep.md (300 scenes, --quick 40); exit 1 if any scene fails.
  accuracy3d writes accuracy3d.csv, accuracy3d.json, accuracy3d.md and accuracy3d.png (50 stones + 20 healthy
           blocks, --quick 10 + 5; budget 84 probes: a 6 x 6 grid and rounds of 12).

where it runs: --workers 1 (serial, this process), --workers N (a dask LocalCluster of N processes on this machine;
default: one per CPU) or --scheduler tcp://HOST:8786 (an existing cluster: `dask scheduler` on one machine, `dask
worker tcp://HOST:8786 --nthreads 1` on each machine, palpate installed on all; see docs/scale_out.md).

examples:
  palpate study accuracy --out study/ --quick              20 stones + 10 healthy scenes, LocalCluster
  palpate study accuracy --out study/ --workers 1          serial (same numbers)
  palpate study accuracy --out study/ --scheduler tcp://10.0.0.5:8786
  palpate study mismatch --out mm/ --quick --workers 2     the truth is not the belief: 30 whole runs
  palpate study accuracy3d --out s3d/ --workers 2          the 3D loop over 50 stones and 20 healthy blocks"""

ADDRESS = re.compile(r"^(tcp|tls)://[A-Za-z0-9_.\-\[\]:]+:\d{1,5}$")


def scheduler_address(s: str) -> str:
    """``tcp://HOST:PORT`` (or ``HOST:PORT``, taken as tcp)."""
    a = s if "://" in s else f"tcp://{s}"
    if not ADDRESS.match(a) or not 0 < int(a.rsplit(":", 1)[1]) < 65536:
        raise argparse.ArgumentTypeError(f"must be a dask scheduler address tcp://HOST:PORT (port 1-65535), "
                                         f"got {s!r}")
    return a


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("study", help="accuracy and detectability studies on dask.distributed",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("study", choices=list(STUDIES), help="which study")
    p.add_argument("--out", metavar="DIR", required=True, help="output directory (a re-run resumes)")
    p.add_argument("--quick", action="store_true", help="a smaller study (accuracy: 20 stones, 10 healthy)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int_range(1, 1024), metavar="N",
                       help="1: serial; N > 1: a LocalCluster of N processes (default: one per CPU)")
    where.add_argument("--scheduler", type=scheduler_address, metavar="ADDRESS",
                       help="an existing dask scheduler, tcp://HOST:PORT")
    p.add_argument("--scene", help="the tissue (its prior is used; default paper, block3d for accuracy3d)")
    p.add_argument("--trials", type=int_range(1, 100000),
                   help="accuracy, mismatch, accuracy3d: random stones (default 100, --quick 20; accuracy3d 50, "
                        "--quick 10)")
    p.add_argument("--runs", type=int_range(1, 100000), help="detect: rasters per stone (default 150, --quick 40)")
    p.add_argument("--scenes", type=int_range(1, 100000), help="sweep: random scenes (default 300, --quick 40)")
    p.add_argument("--healthy", type=int_range(0, 100000),
                   help="accuracy, mismatch, accuracy3d: healthy scenes (default 40, --quick 10; accuracy3d 20, "
                        "--quick 5)")
    p.add_argument("--seed", type=int_range(0, 2 ** 31), default=1, help="the study's seed (default 1)")
    p.add_argument("--sensor", choices=["nano17", "ur5e-builtin"],
                   help="accuracy, detect, accuracy3d: the simulated sensor (default nano17; mismatch and sweep use "
                        "none of their own and refuse it)")
    p.add_argument("--budget-probes", type=int_range(15, 10000),
                   help="accuracy, mismatch, accuracy3d: probes per trial (default: accuracy 45, mismatch 25, "
                        "accuracy3d 84)")
    p.add_argument("--hyperelastic", action="store_true",
                   help="mismatch: a finite-strain neo-Hookean truth in half the trials (such a run took 1-3.3x a "
                        "linear one's time)")
    p.add_argument("--target-uncertainty-m", type=positive_float,
                   help="accuracy, accuracy3d: the adaptive runs stop once x, depth (and y) are known to this, 1 "
                        "sigma in m (default 0.0005)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--json", metavar="PATH", help="also write the summary here ('-': standard output)")
    p.set_defaults(func=run)
    return p


# the options each study reads (the rest of its options are every study's); --sensor has its own refusal below
OPTION_STUDIES = {"scene": ("accuracy", "detect", "mismatch", "accuracy3d"),
                  "trials": ("accuracy", "mismatch", "accuracy3d"), "healthy": ("accuracy", "mismatch", "accuracy3d"),
                  "budget_probes": ("accuracy", "mismatch", "accuracy3d"), "runs": ("detect",), "scenes": ("sweep",),
                  "hyperelastic": ("mismatch",), "target_uncertainty_m": ("accuracy", "accuracy3d")}


def runner_of(args) -> Runner:
    if args.scheduler:
        return Runner(scheduler=args.scheduler, progress=not args.no_progress)
    return Runner(workers=args.workers or (os.cpu_count() or 1), progress=not args.no_progress)


def pieces_dir(out: Path, study: str, options: dict) -> Path:
    h = hashlib.sha256(json.dumps(options, sort_keys=True).encode()).hexdigest()[:12]
    return out / "pieces" / f"{study}-{h}"


def _say(msg: str) -> None:
    print(f"palpate study: {msg}", file=sys.stderr, flush=True)


def run(args) -> int:
    check_output_dir(args.out, "--out")
    if is_measured(args.out) or is_measured(os.path.realpath(args.out)):
        raise UsageError(f"--out {args.out}: a run's directory (its probes.jsonl, raw/); a study's pieces go into a "
                         f"directory of their own")
    check_output_file(args.json, "--json")
    out = Path(args.out)
    for opt, studies in OPTION_STUDIES.items():     # an option the chosen study would not read: refused, not ignored
        v = getattr(args, opt)
        if v is not None and v is not False and args.study not in studies:     # (0 is given: 0 == False)
            flag = "--" + opt.replace("_", "-")
            raise UsageError(f"{flag}{'' if v is True else f' {v}'}: the {args.study} study does not take it (it is for "
                             f"{', '.join(studies)})")
    three_d = args.study == "accuracy3d"
    scene = load_scene(args.scene or ("block3d" if three_d else "paper"), "--scene")
    if scene.is_3d != three_d:
        raise UsageError(f"--scene {args.scene}: the {args.study} study needs a "
                         f"{'3D block (tissue.length_m)' if three_d else '2D section'}, this is "
                         f"{'a 3D block' if scene.is_3d else 'a 2D section'}")
    args.target_uncertainty_m = args.target_uncertainty_m or 5e-4
    if args.sensor is not None and args.study in ("mismatch", "sweep"):
        raise UsageError(f"--sensor {args.sensor}: the {args.study} study does not take a sensor ("
                         + ("its trials run with nano17's noise, bias and drift" if args.study == "mismatch" else
                            "it checks fem's solutions, no probing") + "); --sensor is for accuracy, detect and "
                         "accuracy3d")
    args.sensor = args.sensor or "nano17"
    runner = runner_of(args)
    study = {"accuracy": run_accuracy_study, "mismatch": run_mismatch_study, "detect": run_detect_study,
             "sweep": run_sweep_study, "accuracy3d": run_accuracy3d_study}[args.study]
    t0 = time.time()
    with json_alone(args.json):                 # --json -: standard output holds the JSON alone
        summary = study(args, scene, runner, out)
    _log_invocation(out, args, t0, summary)
    write_json(args.json, summary)
    return 1 if summary.get("failures") else 0


def _log_invocation(out: Path, args, t0: float, summary: dict) -> None:
    """One line per invocation appended to DIR/runs.jsonl (start time, wall time, where, the options): the
    reports are rewritten by every invocation (a resumed study's says only how long the resumption took), the log
    keeps each run's."""
    options = {k: v for k, v in vars(args).items() if isinstance(v, (str, int, float, bool, type(None)))}
    line = {"study": args.study, "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t0)),
            "wall_s": round(time.time() - t0, 3), "elapsed_s": summary.get("elapsed_s"), "where": summary.get("where"),
            "options": options}
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "runs.jsonl", "a") as fh:
        fh.write(json.dumps(line) + "\n")


def _run(runner: Runner, compute):
    try:
        return compute()
    except OSError as e:            # a scheduler that cannot be reached
        if runner.scheduler:
            raise UsageError(f"--scheduler {runner.scheduler}: cannot use it: {e}") from None
        raise


def run_sweep_study(args, scene, runner: Runner, out: Path) -> dict:
    n = args.scenes or (40 if args.quick else 300)
    store = pieces_dir(out, "sweep", {"scenes": n, "seed": args.seed})
    _say(f"sweep: {n} random scenes on {runner.describe()}; pieces in {store}")
    t0 = time.perf_counter()
    rows = _run(runner, lambda: run_pieces(sweep_piece, args.seed, list(range(n)), [f"scene-{i:04d}" for i in range(n)],
                                           runner=runner, store=store, desc="sweep scenes",
                                           shape=record_with("name", "status", "detail", "warnings")))
    elapsed = time.perf_counter() - t0
    md = write_sweep(rows, out)
    (out / "sweep.json").write_text(json.dumps(rows, indent=1))
    print(md)
    failures = sum(r["status"] == "FAIL" for r in rows)
    _say(f"sweep: {n} scenes in {elapsed:.0f} s, {failures} failures; results in {out}")
    return {"study": "sweep", "scenes": n, "elapsed_s": elapsed, "where": runner.describe(), "failures": failures}


def run_detect_study(args, scene, runner: Runner, out: Path) -> dict:
    prior = scene.prior()
    cases = study_cases(args.quick, runs=args.runs, seed=args.seed, sensor=args.sensor)
    options = {"scene": prior.key(), "cases": [c.name for c in cases], "runs": cases[0].runs, "seed": args.seed,
               "sensor": args.sensor}
    store = pieces_dir(out, "detect", options)
    _say(f"detect: {len(cases)} stones x {cases[0].runs} rasters on {runner.describe()}; pieces in {store}")
    t0 = time.perf_counter()
    rows = _run(runner, lambda: run_detect(load_surrogate(prior, runner=runner), cases, runner, store))
    elapsed = time.perf_counter() - t0
    lines = write_detect(out, rows, elapsed, where=runner.describe())
    print("\n".join(lines))
    _say(f"detect: {len(cases)} stones in {elapsed:.0f} s; results in {out}")
    return {"study": "detect", "elapsed_s": elapsed, "where": runner.describe(), "cases": rows}


def run_mismatch_study(args, scene, runner: Runner, out: Path) -> dict:
    stones = args.trials if args.trials is not None else (20 if args.quick else 100)
    healthy = args.healthy if args.healthy is not None else (10 if args.quick else 40)
    budget = args.budget_probes or 25
    prior = scene.prior()
    options = {"scene": prior.key(), "stones": stones, "healthy": healthy, "seed": args.seed, "budget": budget,
               **({"hyperelastic": True} if args.hyperelastic else {})}     # absent when off: older pieces stay valid
    store = pieces_dir(out, "mismatch", options)
    store.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("PALPATE_CACHE_DIR", str(out / "cache"))   # the truths' one-off models stay out of ~
    sur = load_surrogate(prior, runner=runner)
    prior_finite_strain(prior)        # the localizer's finite-strain table: built (or read) once, here, not per trial
    coarse_x = make_plan(prior, store / "plan.json")
    shared = Shared(prior=prior, sur=sur, plan_path=str(store / "plan.json"), runs_dir=str(store / "runs"),
                    coarse_x_m=coarse_x)
    trials = mismatch_trials(prior, sur, stones, healthy, budget, args.seed, hyperelastic=args.hyperelastic)
    _say(f"mismatch: {stones} stones + {healthy} healthy truths on {runner.describe()}; pieces and runs in {store}")
    t0 = time.perf_counter()
    rows = _run(runner, lambda: run_pieces(run_mismatch_trial, shared, trials, [t.name for t in trials],
                                           runner=runner, store=store, desc="mismatch trials",
                                           shape=record_with("trial", "seed", "rc", "stone")))
    elapsed = time.perf_counter() - t0
    cmd = (f"palpate study mismatch --trials {stones} --healthy {healthy} --budget-probes {budget} "
           f"--seed {args.seed}{' --hyperelastic' if args.hyperelastic else ''}")
    print(write_mismatch(out, rows, cmd))
    _say(f"mismatch: {len(trials)} trials in {elapsed:.0f} s; results in {out}")
    return {"study": "mismatch", "stones": stones, "healthy": healthy, "elapsed_s": elapsed,
            "where": runner.describe(), "summary": json.loads((out / "mismatch.json").read_text())}


def run_accuracy_study(args, scene, runner: Runner, out: Path) -> dict:
    trials = args.trials if args.trials is not None else (20 if args.quick else 100)
    healthy = args.healthy if args.healthy is not None else (10 if args.quick else 40)
    args.budget_probes = args.budget_probes or 45
    prior = scene.prior()
    options = {"scene": prior.key(), "trials": trials, "healthy": healthy, "seed": args.seed, "sensor": args.sensor,
               "budget": args.budget_probes, "target_m": args.target_uncertainty_m}
    sur = load_surrogate(prior, runner=runner)
    plan = study_trials(prior.tissue.width_m, trials, healthy, sensor=args.sensor, budget=args.budget_probes,
                        target_m=args.target_uncertainty_m, seed=args.seed)
    store = pieces_dir(out, "accuracy", options)
    _say(f"accuracy: {trials} stones + {healthy} healthy scenes on {runner.describe()}; pieces in {store}")
    t0 = time.perf_counter()
    rows = _run(runner, lambda: run_accuracy(sur, plan, runner=runner, store=store))
    elapsed = time.perf_counter() - t0
    lines = write_report(out, rows, args.sensor, args.budget_probes, args.target_uncertainty_m, elapsed,
                         where=runner.describe())
    print("\n".join(lines))
    _say(f"accuracy: {len(plan)} trials in {elapsed:.0f} s; results in {out}")
    return {"study": "accuracy", "trials": trials, "healthy": healthy, "elapsed_s": elapsed,
            "where": runner.describe(), "summary": json.loads((out / "accuracy.json").read_text())}


def run_accuracy3d_study(args, scene, runner: Runner, out: Path) -> dict:
    stones = args.trials if args.trials is not None else (10 if args.quick else 50)
    healthy = args.healthy if args.healthy is not None else (5 if args.quick else 20)
    budget = args.budget_probes or 84
    n_coarse = COARSE[0] * COARSE[1]
    if budget < n_coarse:        # (the coarse grid is probed whole before the budget is looked at)
        raise UsageError(f"--budget-probes {budget}: the accuracy3d study's coarse grid alone is {COARSE[0]} x "
                         f"{COARSE[1]} = {n_coarse} probes; allowed: {n_coarse} to 10000")
    prior = scene.prior()
    options = {"scene": prior.key(), "stones": stones, "healthy": healthy, "seed": args.seed, "sensor": args.sensor,
               "budget": budget, "target_m": args.target_uncertainty_m}
    store = pieces_dir(out, "accuracy3d", options)
    sur = load_surrogate3d(prior, runner=runner)
    trials = study_trials3d(prior, stones, healthy, sensor=args.sensor, budget=budget,
                            target_m=args.target_uncertainty_m, seed=args.seed)
    _say(f"accuracy3d: {stones} stones + {healthy} healthy blocks on {runner.describe()}; pieces in {store}")
    t0 = time.perf_counter()
    rows = _run(runner, lambda: run_accuracy3d(sur, prior, trials, runner=runner, store=store))
    elapsed = time.perf_counter() - t0
    cmd = (f"palpate study accuracy3d --scene {args.scene or 'block3d'} --trials {stones} --healthy {healthy} "
           f"--budget-probes {budget} --seed {args.seed}")
    lines = write_accuracy3d(out, rows, cmd, elapsed, runner.describe())
    print("\n".join(lines))
    _say(f"accuracy3d: {len(trials)} trials in {elapsed:.0f} s; results in {out}")
    return {"study": "accuracy3d", "stones": stones, "healthy": healthy, "elapsed_s": elapsed,
            "where": runner.describe(), "summary": json.loads((out / "accuracy3d.json").read_text())}
