"""Two 2D tables of one section against direct fem at the same random stones (session 50: the stone positions of a
section wider than 70 mm).

    python bench/table_compare.py SCENE A.npz B.npz --out DIR [--stones 24] [--seed 0] [--depth-m 0.004]

SCENE's prior is the section; A and B are tables built for it (``surrogate-*.npz`` from two cache directories, e.g.
one built by an older checkout). The stones are drawn over B's range (``planner.surrogate.random_stones``); a stone
outside A's range is asked of A at A's nearest position (what a fit at A's bound sees) and counted apart. For each
stone and table: the RMS and the largest error of the contrast over the surface (111 probes, 5 mm from the sides),
relative to the stone's peak contrast. Prints one line per stone and a summary; writes DIR/table_compare.json.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fem.contact import surface_model  # noqa: E402
from fem.scene import Stone, load  # noqa: E402
from planner.surrogate import Surrogate, random_stones, stone_model  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene")
    p.add_argument("a", metavar="A.npz")
    p.add_argument("b", metavar="B.npz")
    p.add_argument("--out", required=True)
    p.add_argument("--stones", type=int, default=24)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--depth-m", type=float, default=0.004)
    a = p.parse_args(argv)
    prior = load(a.scene).prior()
    tabs = {}
    for name, path in (("A", a.a), ("B", a.b)):
        with np.load(path) as z:
            tabs[name] = Surrogate({k: z[k] for k in z.files}, prior)
        print(f"{name}: {path}: positions (mm) {np.round(tabs[name].xs * 1e3, 2).tolist()}")
    W = prior.tissue.width_m
    for name, t in tabs.items():
        if abs(t.W - W) > 1e-9:
            p.error(f"{name}: a table for a section {t.W} m wide, not SCENE's {W} m")
    m0 = surface_model(prior)
    x0 = np.linspace(0.005, W - 0.005, 111)
    rows = []
    for xs, s, D in random_stones(tabs["B"].bounds, W, prior.tissue.height_m, a.stones, np.random.default_rng(a.seed)):
        m1 = stone_model(prior.with_stones([Stone(x_m=xs, depth_m=s + D / 2, diameter_m=D)]))
        true = np.full(len(x0), np.nan)
        for i, x in enumerate(x0):
            try:
                true[i] = m1.force_n(float(x), a.depth_m) - m0.force_n(float(x), a.depth_m)
            except ValueError:          # fem refuses a probe too close over a shallow stone
                pass
        ok = np.isfinite(true)
        peak = float(np.max(np.abs(true[ok])))
        row = {"xs_m": xs, "s_m": s, "diam_m": D, "peak_contrast_n": peak}
        for name, t in tabs.items():
            lo, hi = t.bounds["xs_m"]
            err = t.contrast(x0[ok], a.depth_m, min(max(xs, lo), hi), s + D / 2, D) - true[ok]
            row[name] = {"rel_rms": float(np.sqrt(np.mean(err ** 2)) / peak), "rel_max": float(np.max(np.abs(err)) / peak),
                         "inside": bool(lo <= xs <= hi)}
        rows.append(row)
        print(f"stone x {xs * 1e3:6.2f} mm, s {s * 1e3:5.2f}, D {D * 1e3:5.2f}: " + "; ".join(
            f"{n} RMS {row[n]['rel_rms']:.3%} max {row[n]['rel_max']:.3%}{'' if row[n]['inside'] else ' (outside)'}"
            for n in tabs), flush=True)
    summary = {}
    inside = np.array([r["A"]["inside"] for r in rows])
    for n in tabs:
        rms = np.array([r[n]["rel_rms"] for r in rows])
        mx = np.array([r[n]["rel_max"] for r in rows])
        summary[n] = {f"{part}_{k}": float(f(v[sel])) if sel.any() else None
                      for part, sel in (("inside_A", inside), ("outside_A", ~inside))
                      for k, f, v in (("rms_median", np.median, rms), ("rms_max", np.max, rms), ("max_max", np.max, mx))}
        parts = [f"{int(sel.sum())} stones {part.replace('_', ' ')}'s range: RMS median "
                 f"{summary[n][part + '_rms_median']:.3%}, worst {summary[n][part + '_rms_max']:.3%}, pointwise worst "
                 f"{summary[n][part + '_max_max']:.3%}" for part, sel in (("inside_A", inside), ("outside_A", ~inside))
                 if sel.any()]
        print(f"{n}: " + "; ".join(parts))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "table_compare.json").write_text(json.dumps({"scene": a.scene, "a": a.a, "b": a.b, "seed": a.seed,
                                                         "depth_m": a.depth_m, "summary": summary, "stones": rows},
                                                        indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
