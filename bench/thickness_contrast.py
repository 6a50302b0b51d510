"""How a 2D stone's contrast changes with the tissue's thickness, against the stone-free tissue's force (session 55).

    python bench/thickness_contrast.py --out bench-out/thickness-contrast [--scene paper] [--factor 1.1]

The 2D table (planner.surrogate) holds a stone's contrast in tissue of the prior's thickness; the localizer fits the
thickness (planner.localize, ``thickness_change``) but only the stone-free tissue's force follows it. This measures
with fem, on SCENE's section and on one ``factor`` times as tall (the stones as deep below the top), probes 3 mm
deep every 5 mm over the middle 40 mm: the ratio (tall / as is) of the stone-free force and of each stone's contrast
(a rigid stone's model less the stone-free one, as the table's entries are). Writes OUT/thickness_contrast.json and
.md, and prints the table.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from fem.contact import surface_model  # noqa: E402
from fem.scene import Stone, load  # noqa: E402
from planner.surrogate import stone_model  # noqa: E402

DEPTH_M = 0.003
STONES = ((0.025, 0.015), (0.012, 0.008), (0.040, 0.012))     # (depth, diameter) at the middle


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True)
    p.add_argument("--scene", default="paper")
    p.add_argument("--factor", type=float, default=1.1)
    a = p.parse_args()
    base = load(a.scene)
    prior = dataclasses.replace(base, stones=())
    W = prior.tissue.width_m
    xs = W / 2 + np.arange(-0.020, 0.0201, 0.005)
    tall = dataclasses.replace(prior, tissue=dataclasses.replace(prior.tissue,
                                                                 height_m=prior.tissue.height_m * a.factor))
    force = {}
    for name, sc in (("as_is", prior), ("tall", tall)):
        m = surface_model(sc)
        force[name] = np.array([m.force_n(float(x), DEPTH_M) for x in xs])
    rows = []
    for dep, diam in STONES:
        c = {}
        for name, sc in (("as_is", prior), ("tall", tall)):
            m = stone_model(sc.with_stones([Stone(x_m=W / 2, depth_m=dep, diameter_m=diam)]))
            c[name] = np.array([m.force_n(float(x), DEPTH_M) for x in xs]) - force[name]
        rows.append({"depth_m": dep, "diameter_m": diam, "contrast_as_is_n": c["as_is"].tolist(),
                     "contrast_ratio": (c["tall"] / c["as_is"]).tolist()})
    out = {"scene": a.scene, "height_m": prior.tissue.height_m, "factor": a.factor, "probe_depth_m": DEPTH_M,
           "x_m": xs.tolist(), "force_ratio": (force["tall"] / force["as_is"]).tolist(), "stones": rows}
    d = Path(a.out)
    d.mkdir(parents=True, exist_ok=True)
    (d / "thickness_contrast.json").write_text(json.dumps(out, indent=1))
    mid, side = len(xs) // 2, 0
    lines = [f"{a.scene}, {a.factor:g} times as tall, probes {DEPTH_M * 1e3:g} mm deep: ratio tall / as is",
             "", "| stone (depth, diameter) | the tissue's force | the contrast under the stone | 20 mm to a side |",
             "|---|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['depth_m'] * 1e3:g} mm, {r['diameter_m'] * 1e3:g} mm | x {out['force_ratio'][mid]:.3f} | "
                     f"x {r['contrast_ratio'][mid]:.3f} | x {r['contrast_ratio'][side]:.3f} |")
    (d / "thickness_contrast.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
