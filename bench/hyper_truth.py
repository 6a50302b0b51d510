"""The finite-strain (neo-Hookean) truth against the linear model along a section, and what a sweep costs.

    OPENBLAS_NUM_THREADS=1 python bench/hyper_truth.py [--scene paper] [--x-mm 5,15,25,35,45,55,65] [--own-mesh]

For each tip position: the sweep's time and Newton iterations on the correction mesh (fem.hypertruth) and the
ratio F_neo-Hookean / F_linear at 1, 2, 3, 4 mm. ``--own-mesh``: the same sweep at the first x on the scene's own
mesh, for the correction mesh's error. No disk cache (every sweep is computed).
"""
from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")     # as the CLI: small dense products, no thread contention


from fem.contact import surface_model  # noqa: E402
from fem.hyperindent import HyperIndenter  # noqa: E402
from fem.hypertruth import correction_scene, sweep_depths  # noqa: E402
from fem.scene import load  # noqa: E402

DEPTHS_MM = (1, 2, 3, 4)


def row(hi: HyperIndenter, lin, x_m: float) -> str:
    sw = hi.sweep(x_m, sweep_depths(hi.scene))
    r = {round(d * 1e3, 3): f / lin.force_n(x_m, float(d)) for d, f in zip(sw.depth_m, sw.force_n) if d < 0.005}
    cells = " | ".join(f"{100 * (r[float(d)] - 1):+.2f} %" for d in DEPTHS_MM)
    return (f"| {x_m * 1e3:.1f} | {cells} | {sw.time_s:.2f} | {int(sw.newton_iterations.sum())} | "
            f"{hi.tangent_fallbacks} | {sw.stopped or '-'} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="paper")
    ap.add_argument("--x-mm", default="5,15,25,35,45,55,65")
    ap.add_argument("--own-mesh", action="store_true")
    args = ap.parse_args()
    scene = load(args.scene)
    xs = [float(v) * 1e-3 for v in args.x_mm.split(",")]
    meshes = [("correction", correction_scene(scene))] + ([("own", scene)] if args.own_mesh else [])
    for name, sc in meshes:
        t0 = time.perf_counter()
        hi, lin = HyperIndenter(sc), surface_model(sc, cache=False)
        print(f"\n{args.scene} on its {name} mesh ({hi.model.n_dofs} DOFs; set-up {time.perf_counter() - t0:.1f} s, "
              f"load average {os.getloadavg()[0]:.1f}):\n")
        print("| x (mm) | " + " | ".join(f"{d} mm" for d in DEPTHS_MM) + " | sweep (s) | Newton iterations | "
              "material-tangent steps (cumulative) | stopped |")
        print("|---" * (len(DEPTHS_MM) + 5) + "|")
        for x in (xs if name == "correction" else xs[:1]):
            print(row(hi, lin, x), flush=True)


if __name__ == "__main__":
    main()
