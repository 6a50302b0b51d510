"""Benchmark of the raster planner: build time (once) and solve time for rasters of 10, 50 and 100 waypoints.

    python bench/bench_planner.py [--sizes 10 50 100] [--repeats 7] [--fem] [--out bench-out/planner.json]

Per size: ``build_s`` (CasADi: the IPOPT nlpsol for that raster size as ``plan_raster`` builds it, mapped per
waypoint, once per process; ``build_sx_s``: the one-graph SX build, the reference it replaced in 2D),
then over ``--repeats`` runs the median of ``seed_s`` (closed-form IK for all 2N poses), ``solve_s`` (IPOPT) and
``plan_s`` (wall clock; ``plan_cpu_s``: its process CPU time, steadier on a shared machine) of the whole
``plan_raster`` call with a cheap stand-in force model (depths, seed, NLP, checks, timing, poses). With ``--fem`` the depth choice is also timed on fem's real surface model of the paper scene's prior
(``fem_build_s`` once, ``depth_choice_s`` per raster)."""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fem.scene import load  # noqa: E402
from planner import kinematics as kin  # noqa: E402
from planner.plan import nlp_for, plan_raster  # noqa: E402
from planner.raster import choose_depths, raster_positions  # noqa: E402


def stand_in_force(x_m, depth_m):
    return 0.1 * (depth_m / 0.004) ** 1.1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 50, 100])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--fem", action="store_true", help="also time the depth choice on fem's model")
    ap.add_argument("--out", default="bench-out/planner.json")
    a = ap.parse_args(argv)

    prior = load("paper").prior()
    t0 = time.perf_counter()
    kin.fk_function()
    fk_build = time.perf_counter() - t0
    print(f"FK Function build: {fk_build * 1e3:.1f} ms (once per process)")
    rows = []
    for n in a.sizes:
        t0 = time.perf_counter()
        nlp_for(n, mapped=True)
        build = time.perf_counter() - t0
        t0 = time.perf_counter()
        nlp_for(n)
        build_sx = time.perf_counter() - t0
        seed, solve, total, cpu, iters = [], [], [], [], []
        for _ in range(a.repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            p = plan_raster(prior, n_waypoints=n, force_n=stand_in_force)
            total.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            s = p.notes["solver"]
            assert s["success"] and s["used"] == "nlp", s
            seed.append(s["seed_s"])
            solve.append(s["solve_s"])
            iters.append(s["iterations"])
        row = {"waypoints": n, "build_s": build, "build_sx_s": build_sx, "seed_s": statistics.median(seed),
               "solve_s": statistics.median(solve), "plan_s": statistics.median(total),
               "plan_cpu_s": statistics.median(cpu),
               "solve_s_min": min(solve), "solve_s_max": max(solve), "iterations": statistics.median(iters),
               "repeats": a.repeats, "execution_time_s": p.total_time_s}
        rows.append(row)
        print(f"{n:4d} waypoints: build {build:6.3f} s (once; one SX graph {build_sx:.3f} s) | median seed {row['seed_s'] * 1e3:6.1f} ms, "
              f"IPOPT solve {row['solve_s'] * 1e3:6.1f} ms ({row['iterations']:.0f} it), whole plan "
              f"{row['plan_s'] * 1e3:6.1f} ms (cpu {row['plan_cpu_s'] * 1e3:.0f} ms) | planned execution "
              f"{p.total_time_s:.0f} s")
    fem = None
    if a.fem:
        from fem.contact import surface_model
        t0 = time.perf_counter()
        m = surface_model(prior)
        fem = {"fem_build_s": time.perf_counter() - t0, "depth_choice_s": {}}
        for n in a.sizes:
            x = raster_positions(prior.tissue.width_m, n=n)
            t0 = time.perf_counter()
            choose_depths(m.force_n, x, force_limit_n=0.15, depth_limit_m=0.0045)
            fem["depth_choice_s"][str(n)] = time.perf_counter() - t0
        print(f"fem surface model build {fem['fem_build_s']:.2f} s; depth choice (force-limited, 0.075 N): "
              + ", ".join(f"{k} wp {v * 1e3:.0f} ms" for k, v in fem["depth_choice_s"].items()))
    res = {"benchmark": "planner", "fk_build_s": fk_build, "load_average": os.getloadavg(), "rows": rows, "fem": fem,
           "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
           "target": "100 waypoints planned in under 0.5 s once built",
           "target_met": next((r["plan_s"] < 0.5 for r in rows if r["waypoints"] == 100), None)}
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(f"-> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
