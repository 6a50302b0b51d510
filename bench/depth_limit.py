"""How deep the tip goes below the TRUE surface, against the depth limit, when the surface is higher than registered
(session 43: the depth limit counted from the surface fitted to the force curve, robot.tissue_depth; before, from
the contact felt).

    python bench/depth_limit.py --out bench-out/depth-limit [--quick]

One plan on the paper section's prior (15 probes, 4 mm deep: the depth limit; the Nano17's 20 mN contact threshold)
is driven on the in-memory arm over fem truths the planner did not see: the paper scene, its tissue at 1000, 1500
and 4000 Pa, 40 and 60 mm high, a shallow stone, a relaxing tissue (25 % over 2 s) and a neo-Hookean one; and a 3x3
plan on block3d's prior over the block3d truth (a 3D sphere tip and stone). Each with its
surface registered right, 2 mm too low (the tissue higher than registered: the limit stops the probes) and 1.5 mm too
high (shallower: the plan's depth is reached first). The same plan with its force exponents removed (an older plan)
gives the old rule. Per case: the probes' statuses and the deepest any tip went below the true surface. Writes
OUT/depth_limit.json and OUT/depth_limit.md.

The fit's cost in the loop that runs one 2 ms period at a time (a real arm's, and the loopback controller's; the
in-memory arm fast-forwards): the paper plan on the paper truth, surface 2 mm high, driven period by period with the
fit and without it (the old rule, no fit), medians of REPEATS alternated runs; and the fit's own cost per reading,
its path of floats (the loop's, since session 44) against its arrays' path (the fast-forward's; the loop's before).
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from core.contracts import PERIOD_S  # noqa: E402
from fem import scene as S  # noqa: E402
from planner.plan import plan_raster  # noqa: E402
from robot.driver import DriverConfig, run_plan  # noqa: E402
from robot.records import load_raw, read_records  # noqa: E402
from robot.sim import SimRTDEControl, SimRTDEReceive  # noqa: E402
from robot.simarm import build_truth_arm  # noqa: E402
from robot.tissue_depth import SurfaceFit  # noqa: E402
from robot.truth import TruthConditions  # noqa: E402

OFFSETS_M = (0.0, 0.002, -0.0015)        # the true surface above the registered one


def truths() -> dict:
    paper = S.load("paper")
    t = paper.tissue
    shallow = dataclasses.replace(paper.stones[0], depth_m=0.012, diameter_m=0.012)
    return {"paper": (paper, {}),
            "E 1000 Pa": (dataclasses.replace(paper, tissue=dataclasses.replace(t, youngs_pa=1000.0)), {}),
            "E 1500 Pa": (dataclasses.replace(paper, tissue=dataclasses.replace(t, youngs_pa=1500.0)), {}),
            "E 4000 Pa": (dataclasses.replace(paper, tissue=dataclasses.replace(t, youngs_pa=4000.0)), {}),
            "height 40 mm": (dataclasses.replace(paper, tissue=dataclasses.replace(t, height_m=0.04)), {}),
            "height 60 mm": (dataclasses.replace(paper, tissue=dataclasses.replace(t, height_m=0.06)), {}),
            "stone 12 mm deep": (paper.with_stones([shallow]), {}),
            "relaxing 25 %": (paper, {"relaxation_fraction": 0.25}),
            "neo-Hookean": (paper, {"hyperelastic": True}),
            "block3d (3D)": (S.load("block3d"), {})}


REPEATS = 5


def drive(plan, truth, cond: TruthConditions, out: Path, seed: int, config: DriverConfig | None = None) -> dict:
    arm = build_truth_arm(truth, sensor="nano17", seed=seed, tissue_pose=plan.frames.tissue_pose_base,
                          tcp_offset=plan.frames.tcp_offset, start_above_pose=plan.probes[0].approach_pose,
                          conditions=cond)
    t = time.perf_counter()
    rep = run_plan(plan, SimRTDEControl(arm), SimRTDEReceive(arm), out, config=config)
    wall = time.perf_counter() - t
    recs = read_records(out)
    deepest = [float(load_raw(out, r)["depth_m"].max()) + cond.surface_offset_m for r in recs]
    return {"run": str(rep.status), "statuses": dict(Counter(str(r.status) for r in recs)),
            "deepest_below_true_surface_m": max(deepest), "shallowest_deepest_m": min(deepest),
            "wall_s": wall, "periods": round(arm.t_s / PERIOD_S)}


def period_cost(plan, plan_old, tmp: Path, seed: int) -> dict:
    """The fit's cost in the period-by-period loop, and per reading (floats against arrays)."""
    truth, cond = S.load("paper"), TruthConditions(surface_offset_m=0.002)
    cfg = DriverConfig(fast_forward=False)
    walls = {"fit": [], "contact": []}
    for i in range(REPEATS):
        for rule, pl in (("fit", plan), ("contact", plan_old)):
            r = drive(pl, truth, cond, tmp / f"period-{rule}-{i}", seed, cfg)
            walls[rule].append(r["wall_s"] / r["periods"])
    med = {k: float(np.median(v)) for k, v in walls.items()}
    p = plan.probes[0].force_exponent
    past = np.linspace(0.0, 3e-3, 1500)
    f = 0.02 * ((1e-3 + past) / 1e-3) ** p
    per = {}
    for path in ("floats", "arrays"):
        ts = []
        for _ in range(REPEATS):
            fit = SurfaceFit(p, 0.01, 5)
            t = time.perf_counter()
            if path == "floats":
                for a, b in zip(past.tolist(), f.tolist()):
                    fit.depth_one(a, b)
                    fit.commit_one(a, b)
            else:
                for a, b in zip(past.tolist(), f.tolist()):
                    fit.depth_m(a, b)
                    fit.commit(a, b)
            ts.append((time.perf_counter() - t) / past.size)
        per[path] = float(np.median(ts))
    return {"loop_s_per_period": med, "loop_fit_over_contact": med["fit"] / med["contact"],
            "fit_s_per_reading": per, "arrays_over_floats": per["arrays"] / per["floats"]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True)
    p.add_argument("--quick", action="store_true", help="three truths, five probes")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    plans = {"2d": plan_raster(S.load("paper").prior(), n_waypoints=5 if a.quick else 15),
             "3d": plan_raster(S.load("block3d").prior(), grid=(3, 3))}

    def without_exponents(plan):
        d = plan.to_dict()
        return plan.__class__.from_dict({**d, "probes": [{**q, "force_exponent": None} for q in d["probes"]]})
    plan = plans["2d"]
    limit = plan.limits.depth_limit_m
    cases = truths()
    if a.quick:
        cases = {k: cases[k] for k in ("paper", "E 1500 Pa", "relaxing 25 %")}
    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for name, (truth, extra) in cases.items():
            for off in OFFSETS_M:
                cond = TruthConditions(surface_offset_m=off, **extra)
                row = {"truth": name, "surface_offset_m": off}
                pl = plans["3d" if truth.is_3d else "2d"]
                row["n_probes"] = len(pl.probes)
                for rule, pl in (("fit", pl), ("contact", without_exponents(pl))):
                    row[rule] = drive(pl, truth, cond, Path(tmp) / f"{len(rows)}-{rule}", a.seed)
                rows.append(row)
                f, c = row["fit"], row["contact"]
                print(f"{name:17s} surface {off * 1e3:+.1f} mm: deepest below the true surface "
                      f"{f['deepest_below_true_surface_m'] * 1e3:.3f} mm (from the contact felt: "
                      f"{c['deepest_below_true_surface_m'] * 1e3:.3f}); {f['statuses']} ({c['statuses']})",
                      flush=True)
        cost = period_cost(plan, without_exponents(plan), Path(tmp), a.seed)
    lp, fr = cost["loop_s_per_period"], cost["fit_s_per_reading"]
    print(f"period by period: {lp['fit'] * 1e6:.1f} us a period with the fit, {lp['contact'] * 1e6:.1f} without "
          f"(x{cost['loop_fit_over_contact']:.2f}); the fit per reading {fr['floats'] * 1e6:.1f} us (floats), "
          f"{fr['arrays'] * 1e6:.1f} us (arrays, x{cost['arrays_over_floats']:.1f})", flush=True)
    res = {"depth_limit_m": limit, "period_cost": cost, "exponents": {k: [q.force_exponent for q in v.probes] for k, v in plans.items()},
           "seed": a.seed,
           "wall_s": time.perf_counter() - t0, "rows": rows}
    (out / "depth_limit.json").write_text(json.dumps(res, indent=1))
    md = [f"Deepest tip below the true surface, depth limit {limit * 1e3:g} mm: {len(plan.probes)} probes at "
          f"{plan.probes[0].depth_m * 1e3:g} mm on the paper prior's plan (force exponents "
          f"{min(res['exponents']['2d']):.3f}-{max(res['exponents']['2d']):.3f}), 9 on block3d's (3x3, exponents "
          f"{min(res['exponents']['3d']):.3f}-{max(res['exponents']['3d']):.3f}); nano17, seed {a.seed} "
          f"(`python bench/depth_limit.py`):", "",
          "| truth | surface above registered | deepest (fit) | deepest (from contact felt) | statuses (fit) | "
          "statuses (from contact) |", "|---|---:|---:|---:|---|---|"]
    for r in rows:
        f, c = r["fit"], r["contact"]
        md.append(f"| {r['truth']} | {r['surface_offset_m'] * 1e3:+.1f} mm | "
                  f"{f['deepest_below_true_surface_m'] * 1e3:.3f} mm | {c['deepest_below_true_surface_m'] * 1e3:.3f} mm"
                  f" | {f['statuses']} | {c['statuses']} |")
    md += ["", f"Period by period (the loop of a real arm and of the loopback controller; medians of {REPEATS}, the "
           f"paper truth, surface 2 mm high): {lp['fit'] * 1e6:.1f} us a period with the fit, {lp['contact'] * 1e6:.1f}"
           f" us without it (x{cost['loop_fit_over_contact']:.2f}). The fit per reading: {fr['floats'] * 1e6:.1f} us "
           f"on its path of floats (the loop's), {fr['arrays'] * 1e6:.1f} us on its arrays' path (the fast-forward's; "
           f"x{cost['arrays_over_floats']:.1f})."]
    (out / "depth_limit.md").write_text("\n".join(md) + "\n")
    print(f"wrote {out / 'depth_limit.md'} ({res['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
