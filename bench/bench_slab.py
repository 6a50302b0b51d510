"""2D against 3D: a slab of the study's section with u_y = 0 on both y faces is in plane strain, so the 3D model must
reproduce the 2D plane-strain model (issue 15). The stone is a cylinder along y (elastic, 5 GPa, both models).

    python bench/bench_slab.py [--out bench-out] [--length-m 0.002] [--top-m 0.0005] [--size-m 0.002]

Load A: the top moved down 5 mm; the peak von Mises on the top surface (3D: the top-face map's maximum on the
slab's mid-line). Load B: a cylindrical tip R = 5 mm along y pressed 3 mm at x = 35 mm; the force per unit length
(3D: total force / slab length) against 2D force_n_per_m. Both directions of comparison use the scenes' default 2D
mesh options for the 2D side (P2, h = 2 mm, top 0.5 mm). Writes OUT/bench_slab.json.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fem.assembly import Material  # noqa: E402
from fem.condense import schur  # noqa: E402
from fem.contact import surface_model  # noqa: E402
from fem.lcp import solve_lcp  # noqa: E402
from fem.mesh3d import mesh_block  # noqa: E402
from fem.model3d import Model3D  # noqa: E402
from fem.scene import load  # noqa: E402
from fem.stress3d import components3d, recovery_operator3d  # noqa: E402
from fem.uniform import solve_uniform  # noqa: E402

X0, DEPTH, R = 0.035, 0.003, 0.005


def run(length_m: float, top_m: float, size_m: float) -> dict:
    sc2 = load("paper")
    t, s = sc2.tissue, sc2.stones[0]
    t0 = time.perf_counter()
    a2 = solve_uniform(sc2, rigid_stones=False, full_field=False)
    _, peak2 = a2.surface.peak()
    m2 = surface_model(sc2, cache=False, rigid_stones=False)
    f2 = m2.force_n_per_m(X0, DEPTH)
    t1 = time.perf_counter()
    mesh = mesh_block(t.width_m, length_m, t.height_m, [], size_m, size_m / top_m, 2,
                      cylinders_y=[(s.x_m, t.height_m - s.depth_m, s.radius_m)])
    model = Model3D(mesh=mesh, materials=[Material(t.youngs_pa, t.poisson), Material(s.youngs_pa, s.poisson)],
                    centres=[(s.x_m, length_m / 2, t.height_m - s.depth_m)], rigid=[False])
    X = mesh.nodes
    tol = 1e-9 * t.width_m
    yfaces = np.flatnonzero((X[:, 1] < tol) | (X[:, 1] > length_m - tol))
    left_bottom = mesh.bottom[X[mesh.bottom, 0] < tol]
    base = np.unique(np.concatenate([3 * yfaces + 1, 3 * mesh.bottom + 2, 3 * left_bottom]))
    # load A
    top_z = 3 * mesh.top + 2
    fixed = np.concatenate([base, np.setdiff1d(top_z, base)])
    vals = np.concatenate([np.zeros(len(base)), np.full(len(fixed) - len(base), -sc2.analysis.top_displacement_m)])
    order = np.argsort(fixed)
    fac = model.partition(fixed[order])
    u = fac.full(fac.solve(vals[order]))
    vm = components3d((recovery_operator3d(model, mesh.top) @ u).reshape(-1, 6))["von_mises_pa"]
    mid = np.abs(X[mesh.top, 1] - length_m / 2) <= 0.5 * length_m
    peak3 = float(vm[mid].max())
    # load B: the whole top face's vertical DOFs condensed, a cylindrical tip along y
    free = np.setdiff1d(np.arange(model.n_dofs), base)
    f = schur(model.K, free, 3 * mesh.top + 2)
    x = X[mesh.top, 0]
    win = np.flatnonzero(np.abs(x - X0) <= R)
    q = -DEPTH + (R - np.sqrt(np.maximum(R * R - (x[win] - X0) ** 2, 0.0)))
    inner = win[q < 0]
    r = solve_lcp(f.compliance[np.ix_(inner, inner)], q[q < 0], start=q[q < 0] < 0.5 * q.min())
    w = q + f.compliance[np.ix_(win, inner)] @ r.z
    assert w.min() > -1e-12 * DEPTH, "a node outside the overlap penetrates"
    f3 = float(r.z.sum()) / length_m
    t2 = time.perf_counter()
    return {"length_m": length_m, "top_m": top_m, "size_m": size_m, "dofs_3d": int(model.n_dofs),
            "top_nodes_3d": int(len(mesh.top)), "load_a_peak_2d_pa": float(peak2), "load_a_peak_3d_pa": peak3,
            "load_a_rel_diff": peak3 / peak2 - 1, "force_per_m_2d": f2, "force_per_m_3d": f3,
            "load_b_rel_diff": f3 / f2 - 1, "time_2d_s": t1 - t0, "time_3d_s": t2 - t1, "load_avg": os.getloadavg()[0]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "bench-out"))
    ap.add_argument("--length-m", type=float, default=0.002)
    ap.add_argument("--top-m", type=float, default=0.0005)
    ap.add_argument("--size-m", type=float, default=0.002)
    a = ap.parse_args(argv)
    row = run(a.length_m, a.top_m, a.size_m)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "bench_slab.jsonl", "a") as fh:
        fh.write(json.dumps(row) + "\n")
    print(json.dumps(row, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
