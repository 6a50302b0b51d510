"""Accuracy study of localization and adaptive refinement over random stones (a script, not a test).

    python bench/accuracy_study.py [--quick] [--trials N] [--healthy N] [--sensor nano17] [--out bench-out]
                                   [--workers N | --scheduler ADDRESS] [--replot]

The same study as ``palpate study accuracy`` (the trials are planner.accuracy's, the report planner.accuracy_report's,
the pieces run on planner.tasks: serial, a dask LocalCluster or a cluster). Outputs in OUT: accuracy.csv (one row
per trial and method), accuracy.json, accuracy_ratio.json, accuracy.md (tables), accuracy.png; finished trials in
OUT/pieces/ (a re-run resumes). ``--replot``: the tables and figure again from OUT/accuracy.csv.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from app.cli import main as palpate  # noqa: E402
from planner.accuracy_report import read_rows, write_report  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="bench-out")
    p.add_argument("--replot", action="store_true", help="tables and figure again from OUT/accuracy.csv")
    p.add_argument("--sensor", default="nano17")
    p.add_argument("--budget", type=int, default=45)
    p.add_argument("--target-m", type=float, default=5e-4)
    a, rest = p.parse_known_args(argv)
    if a.replot:
        rows = read_rows(Path(a.out) / "accuracy.csv")
        print("\n".join(write_report(Path(a.out), rows, a.sensor, a.budget, a.target_m, float("nan"),
                                     write_csv=False)))
        return 0
    return palpate(["study", "accuracy", "--out", a.out, "--sensor", a.sensor, "--budget-probes", str(a.budget),
                    "--target-uncertainty-m", str(a.target_m), *rest])


if __name__ == "__main__":
    sys.exit(main())
