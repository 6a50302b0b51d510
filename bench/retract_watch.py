"""Forces met leaving the tissue, and what the driver's retract watch does with them (session 56).

    python bench/retract_watch.py --out bench-out/retract-watch

The in-memory simulated arm (robot.sim, the tests' stand-in tissue force, seed 3), a plan of three probes 3 mm deep
with the default 2 N force limit; a force injected as probe 0's tip, on its way out, is back at 1.5 mm
(``KIND-leaving-depth-m``, robot.simfaults): along the normal for 10 ms (``force-spike``: negative pulls towards the
tissue) or across it for 0.2 s (``side-push``). Per case: the run's status and fault, how long after the force began
the driver's stop came, and where the tip was held. Writes OUT/retract_watch.json and .md, and prints the table.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
from robot_fixtures import make_plan, make_sim  # noqa: E402

from robot.driver import run_plan  # noqa: E402
from robot.simfaults import inject_arm, parse  # noqa: E402

XS = (0.02, 0.035, 0.05)
LEAVING_M = 0.0015
CASES = (("10 N towards the tissue", "force-spike", -10.0), ("5 N towards the tissue", "force-spike", -5.0),
         ("2.5 N towards the tissue", "force-spike", -2.5), ("1 N towards the tissue", "force-spike", -1.0),
         ("20 N along the normal", "force-spike", 20.0), ("40 N across the normal", "side-push", 40.0),
         ("1 N across the normal", "side-push", 1.0))


def one(kind: str, x: float) -> dict:
    arm, c, r = make_sim(seed=3)
    inject_arm(arm, parse(f"{kind}-leaving-depth-m={LEAVING_M}:{x}"))
    with tempfile.TemporaryDirectory() as out:
        rep = run_plan(make_plan(XS, depth_m=0.003), c, r, out)
    fired = arm.faults[0]["fired_s"]
    stops = [t for t in arm.stops_s if fired is not None and t >= fired]
    f = rep.fault or {}
    return {"status": str(rep.status), "fault": str(f["kind"]) if f else None, "n_ok": rep.n_ok,
            "retracted": bool(f.get("retracted")) if f else None,
            "stop_after_s": round(stops[0] - fired, 6) if f and stops else None,
            "tip_depth_m": round(float(arm.tip_in_tissue()[1]), 6)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path, help="folder for retract_watch.json and .md")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for label, kind, x in CASES:
        rows.append({"case": label, "spec": f"{kind}-leaving-depth-m={LEAVING_M}:{x:g}", **one(kind, x)})
    lines = ["| force as the tip leaves | status | fault | stopped after | tip at (depth) |", "|---|---|---|---:|---:|"]
    for r in rows:
        stop = "" if r["stop_after_s"] is None else f"{r['stop_after_s'] * 1e3:.0f} ms"
        held = f"{r['tip_depth_m'] * 1e3:.2f} mm" + ("" if r["retracted"] is not False else " (held)")
        lines.append(f"| {r['case']} | {r['status']} | {r['fault'] or ''} | {stop} | {held} |")
    md = "\n".join(lines) + "\n"
    print(md)
    (a.out / "retract_watch.md").write_text(md)
    (a.out / "retract_watch.json").write_text(json.dumps({"leaving_depth_m": LEAVING_M, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
