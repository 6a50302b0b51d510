"""The elastic spherical tip in 3D (fem.tip3d): numbers printed and written (bench-out/tip3d/), not timed tests.

    python bench/bench_tip3d.py [--out bench-out/tip3d]

1. The tip alone (R = 5 mm, E = 2500 Pa, nu = 0.4; its lower half gripped at its flat face) pressed d onto a rigid
   flat, on the default tip mesh and two finer ones: F / F_Hertz - 1 (Hertz: F = 4/3 E/(1-nu^2) R^1/2 d^3/2) and that
   excess over sqrt(d / R), which is constant for a finite body whose approach loses a term proportional to
   F / (E* R); the straight line through the excesses meets sqrt(d / R) = 0 near 0 (Hertz in the limit).
2. The tip on a tissue block 10 R wide and 5 R deep (E = 2500 Pa; the 3D Hertz test's mesh): the force at d = 0.05 R
   and 0.1 R for tip moduli 1, 5 and 1000 times the tissue's, against the rigid tip's and against Hertz's
   combination of the two bodies (their approaches add at the same pressure: one body of the combined modulus) plus
   each body's own extra approach per newton b_i, measured on it alone at the same depth:
   d = (3 F / (4 E*_c R^1/2))^(2/3) + (b_tissue + b_tip) F.
3. What the tip costs per waypoint (force only) on that block, against the rigid tip.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import numpy as np
from scipy.optimize import brentq

import fem.scene as S
from fem.contact3d import SurfaceModel3D
from fem.lcp import solve_lcp
from fem.mesh3d import mesh_block
from fem.tip3d import FINE_TIP_FRACTION, TipCompliance3D

ROOT = Path(__file__).resolve().parents[1]
R, E, NU, W, H = 0.005, 2500.0, 0.4, 0.05, 0.025


def _hertz(e_star: float, d: float) -> float:
    return 4 / 3 * e_star * math.sqrt(R) * d ** 1.5


def on_rigid_flat(tip: TipCompliance3D, d: float) -> float:
    z = R - np.sqrt(np.maximum(R * R - (tip.xy ** 2).sum(1), 0.0))
    sel = np.flatnonzero(z < 3 * d)
    q = z[sel] - d
    return float(solve_lcp(tip.C[np.ix_(sel, sel)], q, start=q < 0).z.sum())


def extra_per_newton(e_star: float, d: float, F: float) -> float:
    """A body's extra approach per unit force beyond Hertz, from its force F alone at approach d."""
    return (d - (3 * F / (4 * e_star * math.sqrt(R))) ** (2 / 3)) / F


def scene(tip_e=None) -> S.Scene:
    return S.Scene(name="hertz", tissue=S.Tissue(width_m=W, length_m=W, height_m=H, youngs_pa=E, poisson=NU),
                   indenter=S.Indenter(shape="sphere", radius_m=R, youngs_pa=tip_e, poisson=NU),
                   analysis=S.Analysis(order=2, mesh_size_m=0.01, surface_refine=20.0, patch_m=2.2 * R))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(ROOT / "bench-out" / "tip3d"))
    out = Path(ap.parse_args(argv).out)
    out.mkdir(parents=True, exist_ok=True)
    res: dict = {"load_avg_start": os.getloadavg()[0], "alone": [], "block": []}
    lines = ["# The elastic spherical tip in 3D (`python bench/bench_tip3d.py`)", "",
             "Tip alone on a rigid flat (R = 5 mm): F / F_Hertz - 1, and that over sqrt(d/R):", "",
             "| tip mesh (fine size / R) | surface nodes | build (s) | d/R = 0.005 | 0.01 | 0.02 | 0.05 | 0.1 | 0.2 "
             "| line through 0.02-0.1 at d = 0 |", "|---|---:|---:|---|---|---|---|---|---|---:|"]
    e_star = E / (1 - NU ** 2)
    dr = np.array([0.005, 0.01, 0.02, 0.05, 0.1, 0.2])
    tips = {}
    for fine in (FINE_TIP_FRACTION, FINE_TIP_FRACTION / 2, FINE_TIP_FRACTION / 4):
        t0 = time.perf_counter()
        tip = TipCompliance3D.build(scene(E).indenter, order=2, fine_m=fine * R)
        build_s = time.perf_counter() - t0
        tips[fine] = tip
        ex = np.array([on_rigid_flat(tip, v * R) / _hertz(e_star, v * R) - 1 for v in dr])
        s = np.sqrt(dr)
        fit = np.polyfit(s[2:5], ex[2:5], 1)
        res["alone"].append({"fine_over_R": fine, "surface_nodes": len(tip.xy), "build_s": build_s,
                             "d_over_R": dr.tolist(), "excess": ex.tolist(), "intercept": float(fit[1])})
        cells = " | ".join(f"{100 * e:+.1f} % ({e / v:.2f})" for e, v in zip(ex, s))
        lines.append(f"| {fine:g}{' (default)' if fine == FINE_TIP_FRACTION else ''} | {len(tip.xy)} | "
                     f"{build_s:.1f} | {cells} | {100 * fit[1]:+.1f} % |")
        print(lines[-1], flush=True)
    t0 = time.perf_counter()
    mesh = mesh_block(W, W, H, [], 0.01, 20.0, 2, patch_m=2.2 * R, focus=(W / 2, W / 2, R / 8, 0.5 * R))
    rigid = SurfaceModel3D(scene(), mesh=mesh)
    res["block_setup_s"] = time.perf_counter() - t0
    lines += ["", f"On a block 10 R wide, 5 R deep ({3 * mesh.n_nodes} DOFs): the force against the rigid tip's and "
                  "against Hertz's combination with each body's extra approach (measured alone):", "",
              "| E_tip / E | d/R | F / F_rigid | Hertz 1/(1+rho) | F / predicted - 1 | ms per waypoint (rigid: ms) |",
              "|---:|---:|---:|---:|---:|---:|"]
    e_s = e_star
    for ratio in (1.0, 5.0, 1000.0):
        sc = scene(ratio * E)
        tip = tips[FINE_TIP_FRACTION] if ratio == 1.0 else TipCompliance3D.build(sc.indenter, order=2)
        el = SurfaceModel3D(sc, mesh=mesh, compliance=rigid.C, tip=tip, rigid_tip=False)
        e_t = ratio * E / (1 - NU ** 2)
        e_c = 1 / (1 / e_s + 1 / e_t)
        for d in (0.05 * R, 0.1 * R):
            fr = rigid.force_n(W / 2, W / 2, d)
            t0 = time.perf_counter()
            for _ in range(20):
                f = el.force_n(W / 2, W / 2, d)
            t_el = (time.perf_counter() - t0) / 20
            t0 = time.perf_counter()
            for _ in range(20):
                rigid.force_n(W / 2, W / 2, d)
            t_r = (time.perf_counter() - t0) / 20
            b = extra_per_newton(e_s, d, fr) + extra_per_newton(e_t, d, on_rigid_flat(tip, d))
            pred = brentq(lambda F: (3 * F / (4 * e_c * math.sqrt(R))) ** (2 / 3) + b * F - d, 0.0,
                          3 * _hertz(e_c, d))
            res["block"].append({"tip_over_tissue": ratio, "d_over_R": d / R, "force_n": f, "rigid_n": fr,
                                 "predicted_n": pred, "ms_per_waypoint": 1e3 * t_el, "rigid_ms": 1e3 * t_r})
            lines.append(f"| {ratio:g} | {d / R:.2f} | {f / fr:.4f} | {e_c / e_s:.4f} | {100 * (f / pred - 1):+.2f} % "
                         f"| {1e3 * t_el:.1f} ({1e3 * t_r:.1f}) |")
            print(lines[-1], flush=True)
    res["load_avg_end"] = os.getloadavg()[0]
    lines += ["", f"Load average {res['load_avg_start']:.1f} at the start, {res['load_avg_end']:.1f} at the end."]
    (out / "tip3d.json").write_text(json.dumps(res, indent=1))
    (out / "tip3d.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
