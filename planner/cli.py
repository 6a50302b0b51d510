"""`palpate`: the planning CLI. Each subcommand lives in planner/commands/<name>.py and provides
``add_parser(subparsers)`` (which sets ``func``); this module only composes them."""
from __future__ import annotations

import argparse
import importlib
import os
import sys

# Single-threaded BLAS unless the environment says otherwise (before any numpy import): on 2 shared cores
# OpenBLAS's threads spin against other processes; 100 predictions with stresses measured 3-4x more CPU time.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

# name -> module in planner.commands; a module is imported only when its subcommand runs or --help lists it.
COMMANDS = ["simulate", "predict", "plan", "run", "bench"]

EPILOG = """examples:
  palpate simulate paper --load uniform --plots out/      stress under a 5 mm top displacement (load A)
  palpate simulate paper --load indent --x0-m 0.035 --depth-m 0.004
  palpate predict paper --waypoints 50 --depth-m 0.004    force and stress across the surface (load B)
  palpate plan paper --out plan.json --plots out/          CasADi raster plan for a UR5e
  palpate run paper --sim --out run/                       plan, probe with the simulated arm, locate the stone
scenes: a built-in name (paper, paper-left, paper-right, paper-deep, healthy) or a TOML file (see README)."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="palpate", description="Robotic palpation: predict, plan, probe, locate.",
                                epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"planner.commands.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"planner.commands.{name}":
                continue  # not built yet
            raise
        mod.add_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from fem.scene import SceneError
    try:
        return int(args.func(args) or 0)
    except SceneError as e:
        print(f"palpate: scene error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("palpate: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
