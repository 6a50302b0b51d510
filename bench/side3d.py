"""The 3D table against direct fem for one stone at several distances from a block's side (session 53).

    python bench/side3d.py SCENE.toml --diameter-m D --depth-m DEPTH --xs-m X1,X2,... --out DIR

The table (planner.surrogate3d) takes every stone's contrast as a stone's away from the block's side faces. For a
stone of the given diameter and centre depth at each x (y at the block's middle) it solves the stone scene with 3D fem
on the prior's own analysis over a 9 x 9 probe grid at 2 and 4 mm, and prints the table's RMS and largest error
relative to the direct contrast's peak, and the ratio of the peaks. SCENE's prior must have its table built (run
`palpate run SCENE --sim` once). Writes DIR/side3d.txt (and the direct contrasts as DIR/direct.json).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.options import float_list  # noqa: E402
from fem.scene import load  # noqa: E402
from planner.surrogate3d import check_error, direct_contrasts, load_surrogate3d  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene")
    p.add_argument("--diameter-m", type=float, required=True)
    p.add_argument("--depth-m", type=float, required=True, help="the stone's centre depth")
    p.add_argument("--xs-m", type=float_list(what="x positions in m"), required=True, help="the stone's x positions, comma-separated (m)")
    p.add_argument("--out", required=True, help="a directory; an existing side3d.txt there is not overwritten")
    a = p.parse_args()
    if (Path(a.out) / "side3d.txt").exists():
        p.error(f"--out {a.out}: holds a side3d.txt already (measured: not overwritten); give another directory")
    prior = load(a.scene).prior()
    sur = load_surrogate3d(prior, build=False)
    W, L = prior.tissue.width_m, prior.tissue.length_m
    stones = [(x, L / 2, a.depth_m, a.diameter_m) for x in a.xs_m]
    t0 = time.perf_counter()
    direct = direct_contrasts(prior, stones, levels=(2e-3, 4e-3), n_grid=9, same_mesh=False,
                              progress=lambda k, n, r: print(f"  fem {k}/{n}: {r['solve_s']:.0f} s", flush=True))
    lines = [f"{a.scene}: stone {a.diameter_m * 1e3:g} mm across, centre {a.depth_m * 1e3:g} mm deep, y at the middle; "
             f"table against direct fem (9 x 9 probes)"]
    for r in check_error(sur, direct)["stones"]:
        lines.append(f"  x {r['xs_m'] * 1e3:5.1f} mm ({min(r['xs_m'], W - r['xs_m']) * 1e3:4.1f} mm from a side): " + "; ".join(
            f"{lv['depth_m'] * 1e3:.0f} mm: RMS {lv['rms_err_n'] / lv['peak_contrast_n']:.1%}, largest "
            f"{lv['max_err_n'] / lv['peak_contrast_n']:.1%} of the peak, peaks {lv['peak_est_n'] / lv['peak_contrast_n']:.3f}"
            for lv in r["levels"]))
    lines.append(f"  ({time.perf_counter() - t0:.0f} s)")
    print("\n".join(lines))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "side3d.txt").write_text("\n".join(lines) + "\n")
    (out / "direct.json").write_text(json.dumps(direct))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
