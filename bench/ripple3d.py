"""The simulated truth's mesh ripple in 3D (docs/loop3d.md, "The truth's mesh").

    python bench/ripple3d.py --out bench-out/ripple3d [--mesh-size-m 0.012 --grade 0.25] [--grid 9]

A simulated truth is fem on its own mesh, and its stone changes that mesh: the force the arm feels carries a
discretization ripple that the prior (fem on the stone-free mesh) does not share. For the paper's stone in block3d
(15 mm, 25 mm deep, under (35, 35) mm) on an n x n grid over the probed area at 3 mm, this measures

- ``direct``: truth - prior, each on its own mesh (what a simulated run's contrast is);
- ``same``: truth - the prior on the truth's own mesh (the stone's contrast without the ripple: the table's
  definition);
- ripple = direct - same (the two stone-free meshes' difference), and direct - table (the surrogate table
  calibrated for this mesh, planner.surrogate3d: the model error the localizer meets);

as rms and max over the grid, next to the peak contrast. Default mesh: block3d's own; --mesh-size-m and --grade
take another (its surface_refine is kept). Appends one JSON line per run to OUT/ripple3d.jsonl.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fem import scene as S  # noqa: E402
from planner.surrogate3d import direct_contrasts, load_surrogate3d  # noqa: E402

STONE = (0.035, 0.035, 0.025, 0.015)       # xs, ys, centre depth, diameter (m): block3d's
DEPTH_M = 0.003


def measure(mesh_size_m: float | None, grade: float | None, n_grid: int) -> dict:
    prior = S.load("block3d-healthy")
    changes = {k: v for k, v in (("mesh_size_m", mesh_size_m), ("grade", grade)) if v is not None}
    if changes:
        prior = prior.with_analysis(**changes)
    t0 = time.perf_counter()
    d = direct_contrasts(prior, [STONE], levels=(DEPTH_M,), n_grid=n_grid, same_mesh=True)
    row = d["stones"][0]
    direct, same = np.array(row["direct_n"][0]), np.array(row["same_n"][0])
    X, Y = np.array(d["x_m"]), np.array(d["y_m"])
    try:                                  # the table calibrated for this mesh (shipped for block3d's own)
        sur = load_surrogate3d(prior, build=False)
        table = sur.contrast(X, Y, np.full(len(X), DEPTH_M), *STONE)
    except FileNotFoundError:
        table = np.full(len(X), np.nan)

    def stats(v):
        v = v[np.isfinite(v)]
        if not len(v):
            return {"rms_n": None, "max_abs_n": None, "n": 0}
        return {"rms_n": float(np.sqrt(np.mean(v ** 2))), "max_abs_n": float(np.abs(v).max()), "n": int(len(v))}
    a = prior.analysis
    return {"mesh_size_m": a.mesh_size_m, "grade": a.grade, "surface_refine": a.surface_refine, "grid": n_grid,
            "depth_m": DEPTH_M, "stone": dict(zip(("xs_m", "ys_m", "depth_m", "diameter_m"), STONE)),
            "peak_contrast_n": float(np.nanmax(same)) if np.isfinite(same).any() else None,
            "ripple": stats(direct - same),
            "direct_minus_table": stats(direct - table), "same_minus_table": stats(same - table),
            "x_m": X.tolist(), "y_m": Y.tolist(), "direct_n": _json(direct), "same_n": _json(same),
            "table_n": _json(table), "wall_s": time.perf_counter() - t0}


def _json(v: np.ndarray) -> list:
    """Values for JSON: null where fem refused a probe or there is no table (JSON has no NaN)."""
    return [float(x) if np.isfinite(x) else None for x in v]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True)
    p.add_argument("--mesh-size-m", type=float)
    p.add_argument("--grade", type=float)
    p.add_argument("--grid", type=int, default=9)
    a = p.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    r = measure(a.mesh_size_m, a.grade, a.grid)
    with open(out / "ripple3d.jsonl", "a") as f:
        f.write(json.dumps(r) + "\n")
    def mn(s):
        return "n/a" if not s["n"] else f"rms {s['rms_n'] * 1e3:.3f} mN, max {s['max_abs_n'] * 1e3:.3f} mN"
    peak = "n/a" if r["peak_contrast_n"] is None else f"{r['peak_contrast_n'] * 1e3:.3f} mN"
    print(f"mesh {r['mesh_size_m']} m, grade {r['grade']}: peak contrast {peak}; "
          f"ripple (direct - same) {mn(r['ripple'])}; direct - table {mn(r['direct_minus_table'])}; "
          f"same - table {mn(r['same_minus_table'])}; {r['wall_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
