"""How far a neo-Hookean tissue's stone contrast lies from the localizer's model of it (session 51).

    python bench/contrast_finite_strain.py --out DIR [--stone X,DEPTH,DIAMETER ...] [--depths-m 0.001,0.002,...]
                                           [--offsets-m -0.01,0,0.01]

The 2D localizer models a finite-strain tissue's force as (F_lin prior + C_lin) (1 + a g), g = the PRIOR's
finite-strain correction (planner.finite_strain_response) with a fitted amplitude a (about 1 for a neo-Hookean
tissue), C_lin the linear model's stone contrast (the table). The truth (fem.hypertruth: the stone scene's own
neo-Hookean sweep) is F_lin stone x r_stone. With a = 1 the model's error is F_lin stone (r_stone - r_prior), printed
here relative to the linear contrast C_lin = F_lin stone - F_lin prior at each probe position (the stone's x + 0, 3,
6, 10 mm; or --offsets-m, negative towards the section's left side) and depth, with eps = depth / (the tissue over the stone's top) and beta = that error / g: the factor by
which the contrast stiffens faster than the tissue. Paper prior; the probe depths fem's linear model refuses (a
layer crushed past fem.contact.STONE_LAYER_MAX) are left out. Writes DIR/contrast_finite_strain.txt and prints it.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.options import float_list  # noqa: E402
from fem.contact import surface_model  # noqa: E402
from fem.hypertruth import HyperelasticForce  # noqa: E402
from fem.scene import Stone, load  # noqa: E402

STONES = ("0.035,0.007,0.008", "0.035,0.013,0.010", "0.035,0.020,0.012", "0.015,0.010,0.008", "0.050,0.016,0.014")


def triple(text: str) -> tuple[float, float, float]:
    try:
        x, d, D = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--stone {text!r}: give X,DEPTH,DIAMETER in m, e.g. 0.035,0.007,0.008")
    return x, d, D


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True)
    p.add_argument("--stone", type=triple, action="append", help="x, centre depth, diameter in m (repeatable)")
    p.add_argument("--depths-m", default="0.001,0.002,0.003,0.004")
    p.add_argument("--offsets-m", type=float_list(what="probe offsets in m"), default="0,0.003,0.006,0.010",
                   help="probe positions from the stone's x, in m")
    a = p.parse_args()
    depths = [float(v) for v in a.depths_m.split(",")]
    offsets = a.offsets_m
    prior = load("paper").prior()
    hp, lp = HyperelasticForce(prior), surface_model(prior)
    lines = []

    def say(s: str) -> None:
        print(s, flush=True)
        lines.append(s)
    for xs, dep, D in a.stone or [triple(s) for s in STONES]:
        t0 = time.perf_counter()
        scene = prior.with_stones([Stone(x_m=xs, depth_m=dep, diameter_m=D)])
        hs, ls = HyperelasticForce(scene), surface_model(scene)
        top = dep - D / 2
        say(f"stone at x {xs * 1e3:.1f} mm, {dep * 1e3:.1f} mm deep, {D * 1e3:.1f} mm across (its top {top * 1e3:.1f} "
            f"mm deep): model error / C_lin (beta)")
        for dx in offsets:
            row = []
            for d in depths:
                try:
                    Fs, Fp, Ls, Lp = hs.force_n(xs + dx, d), hp.force_n(xs + dx, d), ls.force_n(xs + dx, d), \
                        lp.force_n(xs + dx, d)
                except ValueError:
                    row.append(f"{d * 1e3:.1f} mm: refused")
                    continue
                rs, rp = Fs / Ls, Fp / Lp
                e = Ls * (rs - rp) / (Ls - Lp)
                row.append(f"{d * 1e3:.1f} mm (eps {d / top:.2f}): {e:+.3f} ({e / (rp - 1):.1f})")
            say(f"  x {dx * 1e3:+5.1f} mm: " + "; ".join(row))
        say(f"  ({time.perf_counter() - t0:.0f} s)")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "contrast_finite_strain.txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
