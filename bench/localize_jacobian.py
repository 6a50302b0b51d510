"""The localizer's closed-form Jacobian against scipy's finite differences (issue 19): time and result, same data.

    python bench/localize_jacobian.py --out bench-out/jacobian [RUN_DIR ...] [--repeats 3]

Each RUN_DIR is a 2D run's output (probes.jsonl; default: the test data's mismatch trial and a fresh
``palpate run paper --sim`` written under OUT). Its records are localized the way the run's final report does it
(``localize(prior, meas, profile=True)``, the prior from the run's result.json scene name) with
``planner.localize.JACOBIAN`` = "2-point" and "analytic" in turn, ``--repeats`` times each, alternating, in this
process. Prints and writes OUT/jacobian.json and OUT/jacobian.md: median seconds of each and their ratio, and the
differences of the estimates (in units of their sigma), of chi2 under both hypotheses, and of the depth intervals.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import planner.localize as L  # noqa: E402
from app.cli import main as palpate  # noqa: E402
from core.contracts import MEASURED  # noqa: E402
from fem.scene import load  # noqa: E402
from planner.surrogate import load_surrogate  # noqa: E402
from robot.records import read_records  # noqa: E402

MODES = ("2-point", "analytic")


def compare(run_dir: Path, repeats: int) -> dict:
    res = run_dir / "result.json"
    scene = json.loads(res.read_text())["scene"] if res.exists() else "paper"
    prior = load(scene).prior()
    sur = load_surrogate(prior)
    meas = L.Measurements.from_records(read_records(run_dir), statuses=MEASURED)
    times, locs, before = {m: [] for m in MODES}, {}, L.JACOBIAN
    try:
        for _ in range(repeats):
            for m in MODES:
                L.JACOBIAN = m
                L._LAST_FIT.clear()
                t = time.perf_counter()
                locs[m] = L.localize(prior, meas, sur, profile=True)
                times[m].append(time.perf_counter() - t)
    finally:
        L.JACOBIAN = before
        L._LAST_FIT.clear()
    fd, an = locs["2-point"], locs["analytic"]
    med = {m: statistics.median(v) for m, v in times.items()}
    return {"run": str(run_dir), "probes": len(meas), "median_s": med, "speedup": med["2-point"] / med["analytic"],
            "detected": [fd.detected, an.detected], "lr": [fd.lr, an.lr],
            "chi2_no_stone": [fd.chi2_0, an.chi2_0], "chi2_stone": [fd.chi2_1, an.chi2_1],
            "moved_in_sigma": {k: abs(getattr(an, f"{k}_m") - getattr(fd, f"{k}_m")) / getattr(fd, f"sigma_{k}_m")
                               for k in ("x", "depth", "diameter")},
            "sigma_ratio": {k: getattr(an, f"sigma_{k}_m") / getattr(fd, f"sigma_{k}_m")
                            for k in ("x", "depth", "diameter")},
            "depth_interval_95_m": [list(fd.depth_interval_m.get("95", [])), list(an.depth_interval_m.get("95", []))]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="*", type=Path)
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--repeats", type=int, default=3)
    a = p.parse_args()
    if a.repeats < 1:
        p.error(f"--repeats {a.repeats}: must be at least 1")
    a.out.mkdir(parents=True, exist_ok=True)
    runs = a.runs
    if not runs:
        paper = a.out / f"paper-run-{time.strftime('%Y%m%dT%H%M%S')}-{os.getpid()}"
        if palpate(["run", "paper", "--sim", "--out", str(paper)]) != 0:
            return 1
        runs = [ROOT / "tests" / "data" / "mismatch-trial-0048", paper]
    rows = [compare(r, a.repeats) for r in runs]
    (a.out / "jacobian.json").write_text(json.dumps(rows, indent=1))
    lines = [f"`python bench/localize_jacobian.py --out {a.out}`, {a.repeats} alternated repeats, "
             f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load {os.getloadavg()[0]:.1f}", "",
             "| run | probes | finite differences | closed form | speed-up | LR (fd / cf) | chi2 stone (fd / cf) | "
             "moved (x, depth, diameter; sigma) |", "|---|---:|---:|---:|---:|---|---|---|"]
    for r in rows:
        mv = ", ".join(f"{v:.3f}" for v in r["moved_in_sigma"].values())
        lines.append(f"| {Path(r['run']).name} | {r['probes']} | {r['median_s']['2-point']:.3f} s | "
                     f"{r['median_s']['analytic']:.3f} s | {r['speedup']:.2f}x | {r['lr'][0]:.1f} / {r['lr'][1]:.1f} | "
                     f"{r['chi2_stone'][0]:.3f} / {r['chi2_stone'][1]:.3f} | {mv} |")
    (a.out / "jacobian.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
