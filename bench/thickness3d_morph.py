"""Can a 3D run's two thickness models (the prior block 10 % thinner and thicker, planner.tissue_response3d: about half
of a cold `palpate run block3d --sim`'s fem set-up) be made cheaper? Three ways to the thickness slope d ln F / d eta
at a 5 x 5 grid over block3d's probed area and depths of 1, 2 and 3 mm:

- ``fine-remesh``: what the run does (each thickness meshed by gmsh at block3d's settings);
- ``fine-morph``: the prior's own mesh stretched in z (the same nodes on the top, no remeshing: no mesh ripple
  between the nodes, and no meshing or ordering cost beyond the first);
- ``coarse-morph``: the same on a mesh with half the surface refinement (a quarter of the top nodes).

    PALPATE_CACHE_DIR=DIR python bench/thickness3d_morph.py --out OUT [--modes fine-remesh,fine-morph,coarse-morph]

Writes OUT/thickness3d_morph.json (each mode's build times and slopes; the slopes' differences from fine-morph).
Each fine model takes about 45 s and 2-3 GB here.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from fem.contact3d import SurfaceModel3D, surface_model3d
from fem.mesh3d import Mesh3D
from fem.model3d import build_model3d
from fem.scene import load
from fem.scene_mesh3d import mesh_for3d
from planner.tissue_response import THICKNESS_STEP, scene_with_height

DEPTHS_M = (0.001, 0.002, 0.003)
XS_M = np.linspace(0.015, 0.055, 5)


def _forces(model) -> np.ndarray:
    return np.array([[model.force_n(x, y, d) for d in DEPTHS_M] for x in XS_M for y in XS_M])


def stretched(mesh: Mesh3D, factor: float) -> Mesh3D:
    """``mesh`` stretched in z by ``factor`` (its bottom at z = 0 stays): the same elements, top and bottom nodes."""
    nodes = mesh.nodes.copy()
    nodes[:, 2] *= factor
    return Mesh3D(nodes=nodes, tets=mesh.tets, region=mesh.region, order=mesh.order, width_m=mesh.width_m,
                  length_m=mesh.length_m, height_m=mesh.height_m * factor, top=mesh.top, bottom=mesh.bottom)


def run_mode(mode: str) -> dict:
    prior = load("block3d").prior()
    if mode.startswith("coarse"):
        prior = prior.with_analysis(surface_refine=prior.analysis.surface_refine / 2)
    out: dict = {}
    if mode == "fine-remesh":
        for k in (0, -1, 1):
            sc = prior if k == 0 else scene_with_height(prior, 1 + k * THICKNESS_STEP)
            t = time.perf_counter()
            m = surface_model3d(sc)
            out[f"build_s[{k}]"] = time.perf_counter() - t     # (from the disk cache when it has them)
            out[f"F[{k}]"] = _forces(m)
        return out
    mesh = mesh_for3d(prior)
    for k in (0, -1, 1):
        f = 1 + k * THICKNESS_STEP
        sc = dataclasses.replace(prior, tissue=dataclasses.replace(prior.tissue, height_m=prior.tissue.height_m * f))
        t = time.perf_counter()
        m = SurfaceModel3D(sc, model=build_model3d(sc, mesh=stretched(mesh, f)))
        out[f"build_s[{k}]"] = time.perf_counter() - t
        out["top_nodes"] = int(len(m.patch))
        out[f"F[{k}]"] = _forces(m)
        del m
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--modes", default="fine-remesh,fine-morph,coarse-morph")
    a = ap.parse_args()
    res = {m: run_mode(m) for m in a.modes.split(",")}
    slope = {m: (r["F[1]"] - r["F[-1]"]) / (2 * THICKNESS_STEP * r["F[0]"]) for m, r in res.items()}
    report = {"depths_m": DEPTHS_M, "grid_xs_m": XS_M.tolist(), "modes": {}}
    for m, r in res.items():
        report["modes"][m] = {"build_s": {k: v for k, v in r.items() if k.startswith("build_s")},
                              "top_nodes": r.get("top_nodes"),
                              "slope_median": np.median(slope[m], axis=0).tolist()}
        if "fine-morph" in slope and m != "fine-morph":
            d = np.abs(slope[m] - slope["fine-morph"]).max(axis=0)
            report["modes"][m]["slope_max_abs_diff_vs_fine_morph"] = d.tolist()
            report["modes"][m]["force_error_at_1_sigma_pct"] = (d * 0.06 * 100).tolist()
    Path(a.out).mkdir(parents=True, exist_ok=True)
    (Path(a.out) / "thickness3d_morph.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
