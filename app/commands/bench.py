"""`palpate bench --out DIR [--quick]`: run time against error, skip savings, locking, scaling, the random-scene
stress sweep, and (when present) the contact, planner and mesh-convergence benchmarks.

The benchmark scripts live in the source checkout's ``bench/`` directory (they are not part of the installed
distribution): this command finds it next to the ``planner`` package (an editable install or a checkout on
sys.path), or at ``--bench-dir`` / ``$PALPATE_BENCH_DIR``, and loads each script by path. Each script also runs
on its own: ``python bench/<name>.py --help``.
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
import traceback
from pathlib import Path

from app.commands.output import json_alone, write_json
from app.options import check_output_dir, check_output_file, refuse_measured

# name -> (script, what it measures); run in this order
PARTS = {
    "runtime": ("bench_runtime_error.py", "run time against error (Pareto), skip savings, locking, scaling"),
    "sweep": ("sweep.py", "several hundred random valid scenes: no NaN, checked residuals and contact"),
    "contact": ("bench_contact.py", "contact fast path against the plain full solve per waypoint"),
    "planner": ("bench_planner.py", "raster planner build and solve times"),
    "convergence": ("convergence.py", "mesh convergence of the load A stress peak"),
}

HELP = """Benchmarks of fem and the planner; results (CSV, markdown tables, figures) go into --out.

parts (--only NAME ...; default all that exist):
""" + "\n".join(f"  {k:12s} bench/{v[0]}: {v[1]}" for k, v in PARTS.items()) + """

figures: pareto.png (error against wall time for mesh sizes, element orders and each skip, the default marked),
scaling.png (cost against waypoints and DOFs). Tables: runtime_error.md, sweep.md (ready for docs/speed.md).
Runs from a source checkout: the scripts are in the repository's bench/ directory, not in the installed package
(give --bench-dir or $PALPATE_BENCH_DIR otherwise). Full run: ~10 minutes on 2 cores; --quick: ~2 minutes.

examples:
  palpate bench --out bench-out/today --quick          every part, small: about 2 minutes
  palpate bench --out bench-out/contact --only contact the contact fast path against the plain full solve
  python bench/bench_process.py --out DIR --repeats 3  whole commands against one naive re-solve (not a part here)"""


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("bench", help="run time against error, skip savings, stress sweep (from a source checkout)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", metavar="DIR", required=True, help="output directory")
    p.add_argument("--quick", action="store_true", help="smaller references, fewer sizes and scenes, one repeat")
    p.add_argument("--only", nargs="+", choices=list(PARTS), metavar="PART", help="run only these parts")
    p.add_argument("--bench-dir", metavar="DIR", help="the repository's bench/ directory (default: found next to "
                                                      "the planner package, or $PALPATE_BENCH_DIR)")
    p.add_argument("--json", metavar="PATH", help="write a summary (parts, status, time, outputs) here ('-': stdout)")
    p.set_defaults(func=run)
    return p


def bench_dir(given: str | None = None) -> Path:
    explicit = given or os.environ.get("PALPATE_BENCH_DIR")
    cands = [explicit] if explicit else [Path(__file__).resolve().parents[2] / "bench", Path.cwd() / "bench"]
    for c in cands:
        if c and (Path(c) / "bench_runtime_error.py").is_file():
            return Path(c).resolve()
    if explicit:
        where = f"--bench-dir {given}" if given else f"PALPATE_BENCH_DIR={explicit}"
        raise FileNotFoundError(f"{where}: no bench_runtime_error.py there; palpate bench runs from a source "
                                f"checkout: give its bench/ directory")
    raise FileNotFoundError("palpate bench runs from a source checkout: no bench/ directory with "
                            "bench_runtime_error.py found next to the planner package or in the current directory; "
                            "give --bench-dir or set PALPATE_BENCH_DIR")


def load_script(path: Path):
    root = str(path.parent.parent)
    if root not in sys.path:            # the scripts import fem and planner from their checkout
        sys.path.insert(0, root)
    spec = importlib.util.spec_from_file_location(f"palpate_bench_{path.stem}", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _call(name: str, mod, out: Path, quick: bool):
    if hasattr(mod, "run") and name != "convergence":
        return mod.run(out, quick)
    if name == "planner":
        return mod.main(["--out", str(out / "planner.json")] + (["--repeats", "2"] if quick else []))
    if name == "convergence":
        sizes = ["0.004", "0.002", "0.001"] if quick else ["0.004", "0.002", "0.001", "0.0005"]
        return mod.main(["--out", str(out), "--sizes", *sizes])
    return mod.main(["--out", str(out)] + (["--quick"] if quick else []))


def run(args) -> int:
    with json_alone(args.json):                 # --json -: standard output holds the JSON alone
        return _run(args)


def _run(args) -> int:
    try:
        bdir = bench_dir(args.bench_dir)
    except FileNotFoundError as e:
        print(f"palpate bench: {e}", file=sys.stderr)
        return 2
    check_output_dir(args.out, "--out")
    refuse_measured(args.out, "--out")
    check_output_file(args.json, "--json")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    summary, failed = {"bench_dir": str(bdir), "out_dir": str(out), "quick": args.quick, "parts": {}}, False
    for name in args.only or list(PARTS):
        script = bdir / PARTS[name][0]
        if not script.is_file():
            summary["parts"][name] = {"status": "absent", "script": str(script)}
            print(f"== {name}: {script.name} not present, skipped")
            continue
        print(f"== {name}: {PARTS[name][1]}", flush=True)
        before = {p for p in out.rglob("*") if p.is_file()}
        t0 = time.perf_counter()
        try:
            res = _call(name, load_script(script), out, args.quick)
            ok = not (isinstance(res, int) and res != 0) and not (isinstance(res, dict) and res.get("failures"))
            status = "ok" if ok else "failed"
        except Exception as e:  # noqa: BLE001 - one part failing must not hide the others
            traceback.print_exc()
            status = f"error: {type(e).__name__}: {e}"
        failed |= status != "ok"
        outputs = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file() and p not in before)
        summary["parts"][name] = {"status": status, "time_s": round(time.perf_counter() - t0, 2),
                                  "script": str(script), "new_outputs": outputs}
        print(f"== {name}: {status} in {summary['parts'][name]['time_s']} s", flush=True)
    write_json(args.json, summary)
    print(f"palpate bench: results in {out}/" + ("" if not failed else " (some parts failed, see above)"))
    return 1 if failed else 0
