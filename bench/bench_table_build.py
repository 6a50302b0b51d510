"""A 2D surrogate table's cost per stone, the fast path against the plain one, in one run.

A tissue new to palpate (another size, Poisson ratio, tip or mesh) needs its own surrogate table before the first
fit: some 450 fem models of the section with one rigid stone each, and for each one the force at 7 depths x a
0.5 mm grid of probe positions (about a thousand contact solves). Per stone, both ways on the same mesh:

- ``plain``: the condensation by SuperLU (fem.schur_lu.SchurFactor: one factorization for its ordering, one with
  the top last) and one ``force_n`` per waypoint, each LCP from the geometric overlap (palpate until session 59);
- ``fast``: CHOLMOD's supernodal factorization in AMD's order (fem.contact.condensation) and the force grid
  (SurfaceModel.force_grid_n: each position's depths swept, each LCP warm-started from the depth before).

    python bench/bench_table_build.py --out DIR [--scene paper] [--stones 6]

Prints and writes DIR/table_build.json: per stone the times of meshing and assembly, the condensation and the force
grid both ways, and the largest difference between the two ways' forces (relative to the largest force).
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from fem.contact import SurfaceModel, condensation
from fem.model import build_model
from fem.scene import Stone, load
from fem.scene_mesh import mesh_for
from fem.schur_lu import SchurFactor
from planner.surrogate import Grid, _grid_xs, _past_the_crush_limit, random_stones, table_scene


def _plain_grid(m: SurfaceModel, x0, levels) -> np.ndarray:
    out = np.full((len(levels), len(x0)), np.nan)
    for a, d in enumerate(levels):
        for b, x in enumerate(x0):
            try:
                out[a, b] = m.force_n(float(x), float(d))
            except ValueError:
                pass
    return out


def one_stone(prior, stone, x0, levels) -> dict:
    t0 = time.perf_counter()
    scene = prior.with_stones([Stone(x_m=stone[0], depth_m=stone[1] + stone[2] / 2, diameter_m=stone[2])])
    model = build_model(scene, mesh=mesh_for(scene, use=False), rigid_stones=True)
    model.K                                                              # noqa: B018 - assembled here, timed
    t1 = time.perf_counter()
    sm = SurfaceModel(scene, model=model, compliance=np.zeros((len(model.mesh.top),) * 2))   # no factorization
    t2 = time.perf_counter()
    plain_fac = SchurFactor(model.K, sm._free, sm.top_red)
    t3 = time.perf_counter()
    fast_fac = condensation(model.K, sm._free, sm.top_red)
    t4 = time.perf_counter()
    plain = SurfaceModel(scene, model=model, compliance=plain_fac.compliance)
    fast = SurfaceModel(scene, model=model, compliance=fast_fac.compliance)
    with _past_the_crush_limit():
        t5 = time.perf_counter()
        fp = _plain_grid(plain, x0, levels)
        t6 = time.perf_counter()
        ff = fast.force_grid_n(x0, levels)
        t7 = time.perf_counter()
        ref = _plain_grid(fast, x0, levels)                             # the grid against force_n on the same C
    ok = ~np.isnan(fp)
    return {"stone_m": list(stone), "dofs": int(model.n_dofs), "mesh_assemble_s": t1 - t0,
            "plain_condense_s": t3 - t2, "fast_condense_s": t4 - t3, "plain_forces_s": t6 - t5,
            "fast_forces_s": t7 - t6, "waypoints": int(ok.sum()),
            "grid_equals_force_n_bitwise": bool(np.array_equal(ff, ref, equal_nan=True)),
            "fast_vs_plain_max_rel": float(np.abs(ff[ok] - fp[ok]).max() / np.abs(fp[ok]).max())}


def run(out_dir, scene: str = "paper", n_stones: int = 6, seed: int = 0) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    prior = table_scene(load(scene).prior(), load(scene).tissue.youngs_pa)
    grid = Grid()
    x0 = np.arange(0.0, prior.tissue.width_m + 1e-12, grid.dx0_m)
    xs = _grid_xs(prior, grid)
    bounds = {"xs_m": (xs[0], prior.tissue.width_m - xs[0]), "s_m": (grid.s_m[0], grid.s_m[-1]),
              "diam_m": (grid.diam_m[0], grid.diam_m[-1])}
    stones = random_stones(bounds, prior.tissue.width_m, prior.tissue.height_m, n_stones + 1,
                           np.random.default_rng(seed))
    one_stone(prior, stones[0], x0, grid.levels_m)                      # warm-up: imports, first-call costs
    rows = []
    for s in stones[1:]:
        r = one_stone(prior, s, x0, grid.levels_m)
        rows.append(r)
        print(f"stone x {s[0] * 1e3:.1f} mm, top {s[1] * 1e3:.1f} mm, D {s[2] * 1e3:.1f} mm ({r['dofs']} DOFs): "
              f"mesh+K {r['mesh_assemble_s']:.3f} s; condense plain {r['plain_condense_s']:.3f} s, fast "
              f"{r['fast_condense_s']:.3f} s; {r['waypoints']} forces plain {r['plain_forces_s']:.3f} s, fast "
              f"{r['fast_forces_s']:.3f} s; max rel diff {r['fast_vs_plain_max_rel']:.1e}", flush=True)
    med = {k: statistics.median(r[k] for r in rows) for k in ("mesh_assemble_s", "plain_condense_s",
                                                              "fast_condense_s", "plain_forces_s", "fast_forces_s")}
    plain = med["mesh_assemble_s"] + med["plain_condense_s"] + med["plain_forces_s"]
    fast = med["mesh_assemble_s"] + med["fast_condense_s"] + med["fast_forces_s"]
    summary = {"scene": scene, "stones": len(rows), "medians_s": med, "per_stone_plain_s": plain,
               "per_stone_fast_s": fast, "speedup": plain / fast,
               "condense_speedup": med["plain_condense_s"] / med["fast_condense_s"],
               "forces_speedup": med["plain_forces_s"] / med["fast_forces_s"],
               "all_grids_bitwise_force_n": all(r["grid_equals_force_n_bitwise"] for r in rows),
               "fast_vs_plain_max_rel": max(r["fast_vs_plain_max_rel"] for r in rows), "rows": rows}
    print(f"per stone (medians): plain {plain:.3f} s, fast {fast:.3f} s ({plain / fast:.2f}x; condensation "
          f"{summary['condense_speedup']:.2f}x, forces {summary['forces_speedup']:.2f}x); grids equal force_n bit "
          f"for bit: {summary['all_grids_bitwise_force_n']}; fast against plain at most "
          f"{summary['fast_vs_plain_max_rel']:.1e} of the largest force")
    (out_dir / "table_build.json").write_text(json.dumps(summary, indent=1))
    return summary


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="output directory (table_build.json)")
    ap.add_argument("--scene", default="paper", help="a built-in scene or a scene TOML file (its prior is used)")
    ap.add_argument("--stones", type=int, default=6, help="random table stones to time (after one warm-up)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    run(a.out, a.scene, a.stones, a.seed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
