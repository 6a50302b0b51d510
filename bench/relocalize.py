"""The localizer again on a finished run's records, against the truth the run was simulated on (session 44).

    python bench/relocalize.py RUN_DIR TRUTH_SCENE

Reads RUN_DIR's measured probes (every round's), localizes them with today's code on the truth's prior (its stones
removed: what the localizer would be given) and prints the estimate's errors against TRUTH_SCENE's first stone, in
mm and in the reported sigmas, with the fitted surface offset and tilt. A before-and-after of a localizer change on
the same measurements: run it from each checkout (``PYTHONPATH=OLD python bench/relocalize.py ...``). 2D sections.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from core.contracts import MEASURED  # noqa: E402
from fem.scene import load as load_scene  # noqa: E402
from planner.localize import Measurements, localize  # noqa: E402
from planner.surrogate import load_surrogate  # noqa: E402
from robot.records import read_records  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dir")
    p.add_argument("truth_scene")
    a = p.parse_args()
    truth = load_scene(a.truth_scene)
    prior = truth.prior()
    meas = Measurements.from_records(read_records(a.run_dir), None, statuses=MEASURED)
    loc = localize(prior, meas, load_surrogate(prior, build=False)).to_dict()
    out = [f"LR {loc['evidence']['likelihood_ratio']:.0f}"]
    est = loc["estimate"]
    if truth.stones:
        s = truth.stones[0]
        for k, t in (("x_m", s.x_m), ("depth_m", s.depth_m), ("diameter_m", s.diameter_m)):
            v, sg = est[k]["value"], est[k]["sigma"]
            out.append(f"{k} {1e3 * (v - t):+.3f} mm ({(v - t) / sg:+.2f} sigma)")
    nu = loc["nuisance"]
    out.append(f"tilt {1e3 * nu['surface_tilt_rad']['value']:.2f} mrad, offset "
               f"{1e3 * nu['surface_offset_m']['value']:.3f} mm")
    print(" | ".join(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
