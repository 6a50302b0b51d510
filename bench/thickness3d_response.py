"""How exact the 3D localizer's thickness interpolation is (planner.tissue_response3d, docs/localize.md "The block's thickness
in 3D").

    python bench/thickness3d_response.py --out bench-out/thickness3d-s41

On block3d's prior, a 5 x 5 grid over the probed area anchored at 3 mm: the prior's response at a relative
thickness change eta (quadratic through the 0.9, 1 and 1.1 models) against direct fem on a block of height
(1 + eta) H, for eta on the nodes (exact at the anchor) and between them (0.93, 0.95, 1.05: fem models of their own),
at the anchor and 0.5 mm deeper. Appends one JSON line per block to OUT/thickness3d_response.jsonl.
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

from fem.contact3d import surface_model3d  # noqa: E402
from fem.scene import load  # noqa: E402
from planner.area import probe_bounds  # noqa: E402
from planner.tissue_response import scene_with_height  # noqa: E402
from planner.tissue_response3d import PriorResponse3D  # noqa: E402

DEPTH_M = 3e-3


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--factors", type=float, nargs="+", default=[0.9, 1.1, 0.93, 0.95, 1.05])
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    prior = load("block3d").prior()
    x0, x1, y0, y1 = probe_bounds(prior)
    xy = np.array([(x, y) for x in np.linspace(x0, x1, 5) for y in np.linspace(y0, y1, 5)])
    d0 = np.full(len(xy), DEPTH_M)
    t0 = time.perf_counter()
    resp = PriorResponse3D(prior, xy[:, 0], xy[:, 1], d0)
    print(f"the response at three thicknesses: {time.perf_counter() - t0:.1f} s", flush=True)
    for f in a.factors:
        t0 = time.perf_counter()
        m = surface_model3d(scene_with_height(prior, f))
        row = {"height_factor": f, "model_s": time.perf_counter() - t0, "grid": 5, "anchor_depth_m": DEPTH_M}
        for h in (0.0, 5e-4):
            direct = np.array([m.force_n(float(x), float(y), float(d + h)) for (x, y), d in zip(xy, d0)])
            err = resp.force_n(d0 + h, eta=f - 1.0) / direct - 1.0
            row[f"max_rel_err_at_{h * 1e3:g}mm_beyond"] = float(np.abs(err).max())
            row[f"rms_rel_err_at_{h * 1e3:g}mm_beyond"] = float(np.sqrt(np.mean(err ** 2)))
            row[f"mean_force_n_at_{h * 1e3:g}mm_beyond"] = float(direct.mean())
        print(json.dumps(row), flush=True)
        with (a.out / "thickness3d_response.jsonl").open("a") as fh:
            fh.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
