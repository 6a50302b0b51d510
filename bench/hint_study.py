"""Does the shallow-stone warning's depth limit help? A finished mismatch study's stones run again at it (session 51).

    python bench/hint_study.py STUDY_DIR --out DIR [--trials 0000 0002 ...]

For every stone trial of STUDY_DIR (``palpate study mismatch --out STUDY_DIR``) whose run detected a stone with
readings past the linear model's range, the depth limit the warning suggests today (``planner.refine.depth_hint``
from the run's result.json: the estimate, the fitted surface's rise over it, the study plan's contact floor) is
computed; when it is shallower than the study plan's depths, the study plan is re-planned with that limit
(``planner.plan.replan``) and the trial's truth is run again with it (same seed and budget, one fit worker). Writes
DIR/hint.jsonl (one line per trial: both estimates' errors against the truth) and prints, for linear and neo-Hookean truths apart, the
lateral, depth and diameter errors and how often the truth lies within the reported sigmas, as run and at the
suggestion. Resumable: a trial whose DIR/trial-*/result.json exists is not run again. The truth is read only to
score the answers.
"""
from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import math
import os
import subprocess
import sys
import tomllib
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.contracts import Plan  # noqa: E402
from planner.plan import replan  # noqa: E402
from planner.refine import probe_reach, suggested_limit_m  # noqa: E402


def suggested_m(result: dict, plan: Plan, width_m: float) -> float:
    """The depth limit the warning suggests for this result today (NaN: none), from its estimate and nuisance."""
    e, nu = result["estimate"], result["nuisance"]
    rise = nu["surface_offset_m"]["value"] + nu["surface_tilt_rad"]["value"] * (e["x_m"]["value"] - 0.5 * width_m)
    loc = SimpleNamespace(depth_m=e["depth_m"]["value"], diameter_m=e["diameter_m"]["value"],
                          surface_rise_at_stone_m=rise)
    return suggested_limit_m(loc, probe_reach(plan))[0]


def score(result: dict, stone: dict) -> dict | None:
    if not result["detected"]:
        return None
    e = result["estimate"]
    iv = e.get("depth_interval_m") or {}
    out = {}
    for k in ("x_m", "depth_m", "diameter_m"):
        err = e[k]["value"] - stone[k]
        out[k] = {"err_m": err, "err_sigma": err / e[k]["sigma"]}
    for q in ("68", "95"):
        a = iv.get(q)
        out[f"depth_in{q}"] = bool(a and a[0] is not None and a[0] <= stone["depth_m"] <= a[1])
    out["probes"] = result["probes_used"]
    return out


def summary(rows: list, which: str) -> str:
    ok = [r[which] for r in rows if r[which] is not None]
    if not ok:
        return "none detected"

    def a(f):
        return np.array([f(o) for o in ok])
    x, xs = a(lambda o: abs(o["x_m"]["err_m"])), a(lambda o: abs(o["x_m"]["err_sigma"]))
    d = a(lambda o: abs(o["depth_m"]["err_m"]))
    D, Ds = a(lambda o: abs(o["diameter_m"]["err_m"])), a(lambda o: abs(o["diameter_m"]["err_sigma"]))
    return (f"{len(ok)} detected: lateral median {np.median(x) * 1e3:.2f} mm, x within 1 / 2 sigma "
            f"{np.mean(xs < 1):.0%} / {np.mean(xs < 2):.0%} (worst {xs.max():.1f} sigma); depth median / p90 "
            f"{np.median(d) * 1e3:.2f} / {np.percentile(d, 90) * 1e3:.2f} mm, 68 / 95 % intervals hold it "
            f"{np.mean(a(lambda o: o['depth_in68'])):.0%} / {np.mean(a(lambda o: o['depth_in95'])):.0%}; "
            f"diameter median {np.median(D) * 1e3:.2f} mm, within 2 sigma {np.mean(Ds < 2):.0%}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("study")
    p.add_argument("--out", required=True)
    p.add_argument("--trials", nargs="*", help="trial numbers (default: every stone trial)")
    a = p.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    pieces = sorted(glob.glob(os.path.join(a.study, "pieces", "mismatch-*")))
    if not pieces:
        raise SystemExit(f"hint_study: STUDY_DIR {a.study}: no pieces/mismatch-* in it (a `palpate study mismatch` "
                         f"output directory?)")
    piece = Path(pieces[-1])
    plan0 = Plan.load(piece / "plan.json")
    rows = []
    for tj in sorted(piece.glob("trial-*.json")):
        t = tj.stem.split("-")[1]
        if a.trials and t not in a.trials:
            continue
        trial = json.loads(tj.read_text())
        run = piece / "runs" / tj.stem / "run"
        if not trial.get("stone") or not (run / "result.json").exists():
            continue
        before = json.loads((run / "result.json").read_text())
        if not before["detected"] or not before["evidence"].get("readings_beyond_linear_range"):
            continue
        truth = tomllib.loads((piece / "runs" / tj.stem / "truth.toml").read_text())
        d = suggested_m(before, plan0, truth["tissue"]["width_m"])
        if not math.isfinite(d):
            continue
        dst = out / tj.stem
        if not (dst / "result.json").exists():
            plan = replan(plan0, [q.x_m for q in plan0.probes],
                          limits=dataclasses.replace(plan0.limits, depth_limit_m=d))
            plan.save(out / f"plan-{t}.json")
            cmd = [sys.executable, "-m", "app.cli", "run", str(piece / "runs" / tj.stem / "truth.toml"), "--plan",
                   str(out / f"plan-{t}.json"), "--sim", "--seed", str(trial["seed"]), "--budget-probes",
                   str(json.loads((run / "run_options.json").read_text())["budget_probes"]),
                   "--no-figure", "--fit-workers", "1", "--out", str(dst)]
            rc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True,
                                env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
            (out / f"{tj.stem}.err").write_text(rc.stderr)
            if rc.returncode != 0:
                print(f"trial {t}: rc {rc.returncode}: {rc.stderr.strip().splitlines()[-1:]}", flush=True)
                continue
        after = json.loads((dst / "result.json").read_text())
        stone = truth["stone"][0]
        row = {"trial": t, "hyperelastic": bool(trial.get("hyperelastic")), "depth_limit_m": d,
               "as_run": score(before, stone), "at_suggestion": score(after, stone)}
        rows.append(row)
        print(f"trial {t} ({'neo-Hookean' if row['hyperelastic'] else 'linear'}): limit {d * 1e3:.1f} mm", flush=True)
    with open(out / "hint.jsonl", "w") as f:         # (derived from the runs kept in OUT: written afresh)
        for r in rows:
            f.write(json.dumps(r) + "\n")
    for hyper, name in ((False, "linear truths"), (True, "neo-Hookean truths")):
        sel = [r for r in rows if r["hyperelastic"] == hyper]
        print(f"{name} ({len(sel)}):\n  as run:        {summary(sel, 'as_run')}\n"
              f"  at the limit:  {summary(sel, 'at_suggestion')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
