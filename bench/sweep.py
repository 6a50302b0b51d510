"""Stress sweep: several hundred random valid scenes, each solved under load A and load B on a coarse mesh.

    python bench/sweep.py --out bench-out [--n 300] [--seed 1] [--quick] [--workers N | --scheduler ADDRESS]

The scenes and checks are fem.sweep's (``palpate study sweep`` is the same sweep). Writes OUT/sweep.csv (one row per
scene), OUT/sweep.md (summary) and exits 1 on any failure. Finished scenes are kept in OUT/pieces/ (a re-run
resumes).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fem.sweep import check_scene, random_scene, summarize, sweep_piece, write_results  # noqa: E402, F401
from planner.tasks import Runner, run_pieces  # noqa: E402


def run(out_dir, quick: bool = False, n: int | None = None, seed: int = 1, runner: Runner = Runner()) -> dict:
    out = Path(out_dir)
    n = n or (40 if quick else 300)
    rows = run_pieces(sweep_piece, seed, list(range(n)), [f"scene-{i:04d}" for i in range(n)], runner=runner,
                      store=out / "pieces" / f"sweep-seed{seed}", desc="sweep scenes")
    print(write_results(rows, out))
    return {"rows": rows, "failures": sum(r["status"] == "FAIL" for r in rows)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="bench-out")
    p.add_argument("--n", type=int, help="number of scenes (default 300, --quick 40)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--workers", type=int, default=1, help="dask LocalCluster workers (1: serial)")
    p.add_argument("--scheduler", help="an existing dask scheduler (tcp://HOST:PORT)")
    a = p.parse_args(argv)
    runner = Runner(workers=a.workers, scheduler=a.scheduler)
    return 1 if run(a.out, a.quick, a.n, a.seed, runner)["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
