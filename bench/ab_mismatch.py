"""Two mismatch studies of the same truths, run by two versions of palpate, compared trial by trial.

    python bench/ab_mismatch.py OLD_DIR NEW_DIR

OLD_DIR and NEW_DIR are ``palpate study mismatch --out DIR`` outputs with the same options and seed (run each from its
own checkout). Prints: detections that differ, probe counts that differ, how far each detected stone's estimate moved
in units of the old run's sigma, the median and 90th percentile errors of both, and the two runs' final chi2 under
both hypotheses (``result.json`` of every trial's run: lower, higher, largest change).
"""
from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import numpy as np


def rows(d: Path) -> dict[str, dict]:
    with open(d / "mismatch.csv") as f:
        return {r["trial"]: r for r in csv.DictReader(f)}


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    old_dir, new_dir = map(Path, argv)
    a, b = rows(old_dir), rows(new_dir)
    common = sorted(set(a) & set(b), key=int)
    print(f"trials: {len(a)} old, {len(b)} new, {len(common)} in both")
    moved = []
    for t in common:
        ra, rb = a[t], b[t]
        for k in ("detected", "detected_no_finite_strain", "detected_known_tissue", "probes"):
            if ra.get(k) != rb.get(k):
                print(f"trial {t}: {k} {ra.get(k)} -> {rb.get(k)}")
        if ra["stone"] == rb["stone"] == "True" and ra["detected"] == rb["detected"] == "True":
            moved.append((abs(float(ra["err_x_m"]) - float(rb["err_x_m"])) / float(ra["sigma_x_m"]),
                          abs(float(ra["err_depth_m"]) - float(rb["err_depth_m"])) / float(ra["sigma_depth_m"])))
    m = np.array(moved).reshape(-1, 2)
    if len(m):
        print(f"estimates moved (detected stones, {len(m)}): x median {np.median(m[:, 0]):.2g} sigma, max "
              f"{m[:, 0].max():.2g}; depth median {np.median(m[:, 1]):.2g}, max {m[:, 1].max():.2g}")
    for col in ("err_x_m", "err_depth_m"):
        for name, d in (("old", a), ("new", b)):
            v = [abs(float(r[col])) for r in d.values() if r["stone"] == "True" and r["detected"] == "True"]
            if v:
                print(f"|{col}| {name}: median {np.median(v) * 1e3:.3f} mm, p90 {np.percentile(v, 90) * 1e3:.3f} mm")
    chi = []
    for f in sorted(old_dir.glob("pieces/*/runs/*/run/result.json")):
        g = new_dir / f.relative_to(old_dir)
        if g.exists():
            ea, eb = json.loads(f.read_text())["evidence"], json.loads(g.read_text())["evidence"]
            chi.append((ea["chi2_no_stone"], eb["chi2_no_stone"], ea["chi2_stone"], eb["chi2_stone"]))
    c = np.array(chi, dtype=float).reshape(-1, 4)
    for name, i in (("chi2 no stone", 0), ("chi2 stone", 2)):
        if len(c):
            d = c[:, i + 1] - c[:, i]
            tol = 1e-6 * np.abs(c[:, i])
            print(f"{name} (new - old, {len(d)} runs): lower in {int(np.sum(d < -tol))}, higher in "
                  f"{int(np.sum(d > tol))}; largest rise {d.max():.4g}, largest drop {d.min():.4g}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
