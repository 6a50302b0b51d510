"""A finished mismatch study's stone runs localized again with today's code, and the intervals' coverage (session 45).

    python bench/relocalize_study.py STUDY_DIR [--out FILE.jsonl]

Reads every stone trial's records under STUDY_DIR/pieces/*/runs/trial-*/ (the measured probes of all its rounds:
what the run's final localization saw), localizes them on the paper prior as the study does (the truth's tissue and
stones never reach the localizer; the truth scene is read only to score the answer), with the depth's profile, and
prints the coverage of the depth's 68 % / 95 % profile intervals and of x's 1 / 2 sigma, and the median errors: over
all detected stones, those whose top lies within the probes' reach (above 4 mm / STONE_LAYER_MAX: the linear model
does not cover the tissue over them at the plan's depths) and the others, and by the truth's material (linear or
neo-Hookean, from STUDY_DIR/mismatch.csv). The same probes for a before-and-after of
a localizer change (``PYTHONPATH=OLD python bench/relocalize_study.py ...``); a study run with the
new code also re-plans its refinement rounds (run it again for that).
"""
from __future__ import annotations

import argparse
import csv
import glob
import json
import os
import sys
from pathlib import Path

import numpy as np

# the code under test: PYTHONPATH's first entry when given (an older checkout), else this one
sys.path.insert(0, os.environ.get("PYTHONPATH", "").split(os.pathsep)[0] or str(Path(__file__).resolve().parents[1]))

from core.contracts import MEASURED  # noqa: E402
from fem.contact import STONE_LAYER_MAX  # noqa: E402
from fem.scene import load as load_scene  # noqa: E402
from planner.localize import Measurements, localize  # noqa: E402
from planner.surrogate import load_surrogate  # noqa: E402
from robot.records import read_records  # noqa: E402

REACH_M = 0.004 / STONE_LAYER_MAX        # a stone's top shallower than this: within a 4 mm probe's reach


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("study_dir")
    p.add_argument("--out", help="one JSON line per stone trial")
    a = p.parse_args()
    prior = load_scene("paper").prior()
    sur = load_surrogate(prior, build=False)
    rows = []
    for d in sorted(glob.glob(f"{a.study_dir}/pieces/*/runs/trial-*")):
        truth = load_scene(f"{d}/truth.toml")
        if not truth.stones:
            continue
        meas = Measurements.from_records(read_records(f"{d}/run"), None, statuses=MEASURED)
        loc = localize(prior, meas, sur, profile=True)
        s, iv = truth.stones[0], loc.depth_interval_m
        rows.append({"trial": Path(d).name, "detected": loc.detected, "top_m": s.depth_m - s.radius_m,
                     "err_depth_m": loc.depth_m - s.depth_m, "sigma_depth_m": loc.sigma_depth_m,
                     "err_x_m": loc.x_m - s.x_m, "sigma_x_m": loc.sigma_x_m,
                     "in68": bool(iv and iv["68"][0] <= s.depth_m <= iv["68"][1]),
                     "in95": bool(iv and iv["95"][0] <= s.depth_m <= iv["95"][1]),
                     "readings_beyond_linear_range": getattr(loc, "n_beyond_linear_range", 0)})
    if a.out:
        Path(a.out).write_text("".join(json.dumps(r) + "\n" for r in rows))
    det = [r for r in rows if r["detected"]]
    top = np.array([r["top_m"] for r in det])
    # the truth's material, from the study's table (studies since v7 have the column)
    table = Path(a.study_dir) / "mismatch.csv"
    hyper = {int(r["trial"]): r.get("hyperelastic") for r in csv.DictReader(table.open())} if table.exists() else {}
    material = np.array([hyper.get(int(r["trial"].split("-")[1])) for r in det])
    print(f"{len(det)} of {len(rows)} stones detected; coverage and median errors (mm):")
    for name, m in (("all", top > -1.0), (f"top < {REACH_M * 1e3:.2f} mm", top < REACH_M),
                    (f"top >= {REACH_M * 1e3:.2f} mm", top >= REACH_M), ("linear truths", material == "False"),
                    ("neo-Hookean truths", material == "True")):
        sel = [r for r, k in zip(det, m) if k]
        if not sel:
            continue

        def col(k):
            return np.array([r[k] for r in sel])
        zx = np.abs(col("err_x_m") / col("sigma_x_m"))
        print(f"  {name:18s} n={len(sel):3d}  depth in 68 / 95 %: {col('in68').mean():.0%} / {col('in95').mean():.0%}"
              f"  x within 1 / 2 sigma: {np.mean(zx < 1):.0%} / {np.mean(zx < 2):.0%}  |depth err| "
              f"{np.median(np.abs(col('err_depth_m'))) * 1e3:.2f}  |x err| {np.median(np.abs(col('err_x_m'))) * 1e3:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
