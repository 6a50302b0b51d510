"""How far apart may a 2D table's stone positions be? The table's blend in xs (planner.surrogate: the two
neighbouring positions' contrasts shifted to the query and blended linearly) against direct fem midway between them
(session 52: the positions of a section wider than 70 mm, ``planner.surrogate._grid_xs``).

    python bench/table_spacing.py SCENE --out DIR [--clearance-m 0.011] [--diameter-m 0.008] [--depth-m 0.004]
                                  [--pairs 15:35,25:35,35:55,...]

SCENE's prior is the section. For every pair A:B (mm from the left side) fem computes the contrast of a rigid stone
(top ``--clearance-m`` deep, ``--diameter-m`` across) at A, at B and midway, probes ``--depth-m`` deep on a 0.5 mm
grid over the whole surface; the blend of A's and B's shifted contrasts is compared with the midway one: RMS and
largest error relative to its peak (the RMS over the probes where the contrast is above 2 % of its peak), and the
contrast centroid's shift. No table is built (one fem model per position: seconds). Prints one line per pair;
writes DIR/table_spacing.json (nothing there is overwritten: a run into a DIR that has it stops).
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

from fem.contact import surface_model  # noqa: E402
from fem.scene import Stone, load  # noqa: E402
from planner.surrogate import _forces, stone_model  # noqa: E402

PAIRS = "15:35,15:25,25:35,35:45,35:55,40:60,60:80,60:100"


def _pairs(text: str) -> list[tuple[float, float]]:
    out = []
    for p in text.split(","):
        a, b = (float(v) * 1e-3 for v in p.split(":"))
        if not 0 < a < b:
            raise argparse.ArgumentTypeError(f"--pairs {p}: want A:B with 0 < A < B (mm)")
        out.append((a, b))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene")
    p.add_argument("--out", required=True)
    p.add_argument("--clearance-m", type=float, default=0.011)
    p.add_argument("--diameter-m", type=float, default=0.008)
    p.add_argument("--depth-m", type=float, default=0.004)
    p.add_argument("--pairs", type=_pairs, default=_pairs(PAIRS), help=f"A:B in mm (default {PAIRS})")
    a = p.parse_args(argv)
    out = Path(a.out)
    if (out / "table_spacing.json").exists():
        p.error(f"--out {out}: holds a table_spacing.json already (nothing measured is overwritten)")
    prior = load(a.scene).prior()
    W = prior.tissue.width_m
    for lo, hi in a.pairs:
        if hi > W / 2 + 1e-9:
            p.error(f"--pairs {lo * 1e3:g}:{hi * 1e3:g}: beyond the middle of the {W * 1e3:g} mm section")
    x0 = np.arange(0.0, W + 1e-12, 0.5e-3)
    t0 = time.perf_counter()
    base = _forces(surface_model(prior), [a.depth_m], x0)[0]
    cache: dict[float, np.ndarray] = {}

    def contrast(xs: float) -> np.ndarray:
        k = round(xs, 7)
        if k not in cache:
            m = stone_model(prior.with_stones([Stone(x_m=xs, depth_m=a.clearance_m + a.diameter_m / 2,
                                                     diameter_m=a.diameter_m)]))
            cache[k] = _forces(m, [a.depth_m], x0)[0] - base
        return cache[k]

    def shifted(xs: float, to: float) -> np.ndarray:
        return np.interp(x0 - to + xs, x0, contrast(xs))

    rows = []
    print(f"{prior.name}: {W * 1e3:g} x {prior.tissue.height_m * 1e3:g} mm, stone top {a.clearance_m * 1e3:g} mm "
          f"deep, {a.diameter_m * 1e3:g} mm across, probes {a.depth_m * 1e3:g} mm deep")
    for lo, hi in a.pairs:
        mid = 0.5 * (lo + hi)
        true = contrast(mid)
        est = 0.5 * shifted(lo, mid) + 0.5 * shifted(hi, mid)
        pk = float(np.abs(true).max())
        sel = true > 0.02 * pk
        err = est - true
        cen = float((est * x0).sum() / est.sum() - (true * x0).sum() / true.sum())
        row = {"a_m": lo, "b_m": hi, "spacing_m": hi - lo, "rms_rel": float(np.sqrt(np.mean(err[sel] ** 2)) / pk),
               "max_rel": float(np.abs(err).max() / pk), "centroid_shift_m": cen, "peak_contrast_n": pk}
        rows.append(row)
        print(f"  {lo * 1e3:5.1f}-{hi * 1e3:5.1f} mm (midway {mid * 1e3:5.1f}): RMS {row['rms_rel']:.2%}, largest "
              f"{row['max_rel']:.2%}, centroid {cen * 1e3:+.3f} mm", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "table_spacing.json").write_text(json.dumps(
        {"scene": a.scene, "width_m": W, "height_m": prior.tissue.height_m, "clearance_m": a.clearance_m,
         "diameter_m": a.diameter_m, "depth_m": a.depth_m, "rows": rows,
         "wall_s": time.perf_counter() - t0}, indent=1))
    print(f"wrote {out / 'table_spacing.json'} ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
