"""Mismatch study (issue 14): ``palpate study mismatch`` (app.mismatch, on planner.tasks), kept runnable by its old
name. A script, not a test.

    python bench/mismatch_study.py [--quick] [--stones N] [--healthy N] [--budget 25] [--seed 1] [--out bench-out]
        [--workers N]

is ``palpate study mismatch --out OUT --trials N --healthy N --budget-probes B --seed S --workers N`` (the study's
ranges and method: app/mismatch.py; outputs: mismatch.csv, mismatch.json, mismatch.md, mismatch.png in OUT, every
run's files under OUT/pieces/mismatch-*/runs/; a re-run resumes).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from app.cli import main as palpate  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="20 stones and 10 healthy scenes")
    p.add_argument("--stones", type=int)
    p.add_argument("--healthy", type=int)
    p.add_argument("--budget", type=int, default=25, help="probe budget per run (default 25)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", default="bench-out")
    p.add_argument("--workers", type=int, default=1, help="1: serial (default); N: a dask LocalCluster")
    a = p.parse_args(argv)
    cmd = ["study", "mismatch", "--out", a.out, "--budget-probes", str(a.budget), "--seed", str(a.seed),
           "--workers", str(a.workers)]
    cmd += ["--quick"] if a.quick else []
    cmd += ["--trials", str(a.stones)] if a.stones is not None else []
    cmd += ["--healthy", str(a.healthy)] if a.healthy is not None else []
    return palpate(cmd)


if __name__ == "__main__":
    sys.exit(main())
