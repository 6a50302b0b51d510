"""The fault table of docs/robot.md: every fault drill (app/faultdrill.py) through the real ur_rtde client
against the simulated controller, repeated, with its measured bounds.

    python bench/fault_table.py --out runs/fault_table [--repeats 3] [--only partition-descent,...]

Writes ``fault_table.json`` (every run) and ``fault_table.md`` (one row per drill: outcome, worst whole-process
time, detection in controller time, how the motion ended) into --out; prints the markdown. Each drill's runs go to
--out/<drill>/<k>/ and are never overwritten (an existing run directory is skipped and its result read back).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from app.faultdrill import DRILL_BOUND_S, DRILLS, coarse_paper_scene, run_drill  # noqa: E402


def _row(name, results) -> str:
    d = DRILLS[name]
    kinds = sorted({r["fault"].get("kind", "none") for r in results})
    walls = [r["wall_s"] for r in results]
    det = [r["reaction_s"] for r in results if r.get("reaction_s") is not None]
    ok = all(r["returncode"] == 1 and r["fault"].get("kind") in d.kinds and r["wall_s"] <= DRILL_BOUND_S
             and all(len(v) == 1 for v in r["statuses"].values()) and r["raw_samples"] > 0 for r in results)
    stopped = sorted({"controller (protective stop)" if r["fault"].get("kind") == "protective_stop" else
                      "host stopL" if r["fault"].get("stopped_by") == "stopL" else
                      "controller (program ended)" if r["fault"].get("stopped") else "controller watchdog"
                      for r in results})
    retracted = sum(bool(r["fault"].get("retracted")) for r in results)
    det_txt = f"{1e3 * statistics.median(det):.0f} ms (max {1e3 * max(det):.0f})" if det else "-"
    return (f"| {d.what} | {', '.join(kinds)} | {max(walls):.1f} s (median {statistics.median(walls):.1f}) | "
            f"{det_txt} | {', '.join(stopped)} | {retracted}/{len(results)} | {'yes' if ok else 'NO'} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--only", default="", help="comma-separated drill names (default: all)")
    a = ap.parse_args(argv)
    names = [n for n in a.only.split(",") if n] or list(DRILLS)
    bad = [n for n in names if n not in DRILLS]
    if bad or a.repeats < 1:
        ap.error(f"--only {bad[0]!r}: one of {', '.join(DRILLS)}" if bad else f"--repeats {a.repeats}: >= 1")
    a.out.mkdir(parents=True, exist_ok=True)
    scene = coarse_paper_scene(a.out / "paper_coarse.toml")
    rows, everything = [], {}
    for name in names:
        results = []
        for k in range(a.repeats):
            wd = a.out / name / str(k)
            saved = wd / "drill.json"
            if saved.exists():
                res = json.loads(saved.read_text())
            else:
                r = run_drill(name, wd, scene)
                res = {**dataclasses.asdict(r), "detection_s": r.detection_s}
                res.pop("stdout"), res.pop("stderr")
                res["statuses"] = {str(i): v for i, v in r.statuses.items()}
                saved.write_text(json.dumps(res, indent=1))
            results.append(res)
            print(f"{name} #{k}: exit {res['returncode']}, {res['fault'].get('kind')}, wall {res['wall_s']:.1f} s",
                  flush=True)
        everything[name] = results
        rows.append(_row(name, results))
    md = ("| fault | reported as | cell process ends within | driver's fault after injection | motion stopped by | "
          "retracted | records kept, each index once, within 30 s |\n|---|---|---|---|---|---|---|\n"
          + "\n".join(rows) + "\n")
    (a.out / "fault_table.md").write_text(md)
    (a.out / "fault_table.json").write_text(json.dumps(everything, indent=1))
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
