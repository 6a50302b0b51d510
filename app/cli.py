"""`palpate`: the planning CLI, the composition root of the product. Each subcommand lives in app/commands/<name>.py
and provides ``add_parser(subparsers)`` (which sets ``func``). Only the chosen subcommand's module is imported, so a
command pays only for the libraries it uses (``palpate --help`` lists them all from the table below)."""
from __future__ import annotations

import argparse
import gc
import importlib
import math
import os
import re
import signal
import sys

# Single-threaded BLAS unless the environment says otherwise (before any numpy import, so before app.errors, which
# imports numpy through core): on 2 shared cores OpenBLAS's threads spin against other processes; 100 predictions
# with stresses measured 3-4x more CPU time. It also makes a study's serial run and its dask workers (which dask
# starts single-threaded) compute bit for bit the same.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from app.errors import EXIT_USAGE, UsageError, guarded  # noqa: E402
from app.parser import Parser  # noqa: E402
from fem import cachesize  # noqa: E402

# name -> one-line help (the module app.commands.<name> is imported only when its subcommand runs)
COMMANDS = {
    "simulate": "load A (top moved down) or load B (the tip pressed in at one waypoint) on a scene",
    "predict": "force and max stress at every waypoint: stone scene against its healthy prior",
    "plan": "a CasADi raster plan for a UR5e: poses, joints, depths, timing (plan.json)",
    "run": "plan, probe (simulated arm by default), locate the stone, refine",
    "bench": "run time against error, skips, scaling, stress tests",
    "study": "accuracy and detectability studies on dask.distributed (serial, LocalCluster or a cluster)",
    "ft": "read an ATI Net F/T box for a while: rate, lost records, mean and noise per axis",
    "cache": "what the disk cache holds (by kind, size, last use); prune or clear it",
}

EPILOG = """examples:
  palpate simulate paper --load uniform --plots out/      stress under a 5 mm top displacement (load A)
  palpate simulate paper --load indent --x-m 0.035 --depth-m 0.004
  palpate predict paper --waypoints 50 --depth-m 0.004    force and stress across the surface (load B)
  palpate plan paper --out plan.json --plots out/          CasADi raster plan for a UR5e
  palpate run paper --sim --out run/                       plan, probe with the simulated arm, locate the stone
  palpate study accuracy --out study/ --quick              the accuracy study on a dask LocalCluster
  palpate ft --ft netft:192.168.1.1 --ft-range-n 25 --ft-range-nm 0.25   check an ATI Net F/T box
  palpate cache                                            the disk cache: where, how big, what; prune, clear
scenes: a built-in name (2D: paper, paper-left, paper-right, paper-deep, healthy; 3D blocks: block3d,
  block3d-healthy, block3d-left, block3d-front, block3d-deep) or a TOML file (README; a block: docs/fem.md).
environment: PALPATE_CACHE_DIR (the disk cache; default ~/.cache/palpate), PALPATE_CACHE=0 (no disk cache),
  PALPATE_CACHE_MAX_BYTES (its size bound in bytes; default 20e9: the entries used least recently go first),
  PALPATE_MAX_DOFS (the largest finite-element model a command builds; default 2e6 degrees of freedom).
Add --debug to any command to see a traceback instead of a one-line error."""


def build_parser(chosen: str | None = None) -> argparse.ArgumentParser:
    """The parser, with the full options of the ``chosen`` subcommand only."""
    p = Parser(prog="palpate", description="Robotic palpation: predict, plan, probe, locate.",
                                epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--debug", action="store_true", dest="debug_any", help="show a traceback on errors (also after "
                                                                           "the command)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, help_ in COMMANDS.items():
        if name == chosen:
            importlib.import_module(f"app.commands.{name}").add_parser(sub)
        else:
            sub.add_parser(name, help=help_)
    for action in sub.choices.values():
        if not any("--debug" in a.option_strings for a in action._actions):
            action.add_argument("--debug", action="store_true", help="show a traceback on errors")
    return p


# a list of numbers that starts with a minus (``--branch -1,1,1``): argparse takes it for an option and refuses the
# option before it ("expected one argument"); only a lone negative number passes as a value
_NEGATIVE_LIST = re.compile(r"-[0-9.][0-9.eE+-]*(,[0-9.eE+-]+)+")


def join_negative_lists(argv: list[str]) -> list[str]:
    """``--opt -1,1,1`` as ``--opt=-1,1,1``: a long option (no ``=`` of its own) followed by a list of numbers with a
    leading minus takes it as its value, as the user meant."""
    out: list[str] = []
    for a in argv:
        if (_NEGATIVE_LIST.fullmatch(a) and out and out[-1].startswith("--") and "=" not in out[-1]
                and "--" not in out):   # (after a bare --, every argument is a positional one)
            out[-1] = f"{out[-1]}={a}"
        else:
            out.append(a)
    return out


def main(argv: list[str] | None = None) -> int:
    own_process = argv is None          # the console script's (tests call main with their arguments)
    argv = join_negative_lists(sys.argv[1:] if argv is None else list(argv))
    chosen = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(chosen if chosen in COMMANDS else None)
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:           # argparse's usage errors (a bad option value): its message, exit 2
        return e.code if isinstance(e.code, int) else EXIT_USAGE
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    if own_process:
        # the modules loaded (some 100,000 objects): out of the collector's way (it walked them at every full
        # collection, 0.11-0.16 s of a cached `palpate run paper --sim`, 0.06-0.08 s after), and not copied by
        # the forked fits' children touching their counts
        gc.freeze()
        if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
            # a supervisor's SIGTERM (systemd's stop, `kill`) is a Ctrl-C wherever it lands: the command's own line
            # and exit 130 (between a run's rounds its NO RESULT line), not a silent death. Python's own Ctrl-C
            # handler, which robot.signals' gate takes over around the arm's motion as before
            signal.signal(signal.SIGTERM, signal.default_int_handler)
    return guarded("palpate", lambda: check_environment() or args.func(args),
                   debug=getattr(args, "debug", False) or args.debug_any)


CACHE_SWITCH = {"1": True, "true": True, "yes": True, "on": True, "0": False, "false": False, "no": False,
                "off": False}


def check_environment() -> None:
    """The environment variables palpate reads, checked before a command starts (a bad value would otherwise surface
    deep in a run, or be taken as a default)."""
    use = os.environ.get("PALPATE_CACHE")
    if use is not None and use.strip() and use.strip().lower() not in CACHE_SWITCH:
        raise UsageError(f"PALPATE_CACHE={use!r}: give 0 (no disk cache) or 1 (the default); also accepted: "
                         f"{', '.join(k for k in CACHE_SWITCH if k not in '01')}")
    try:
        cachesize.max_bytes()
    except ValueError as e:
        raise UsageError(str(e)) from None
    dofs = os.environ.get("PALPATE_MAX_DOFS", "").strip()
    if dofs:
        try:
            n = float(dofs)
        except ValueError:
            n = math.nan
        if not (math.isfinite(n) and n >= 1 and n == int(n)):
            raise UsageError(f"PALPATE_MAX_DOFS={dofs!r}: give a whole number of degrees of freedom, 1 or more (such "
                             f"as 500000 or 2e6; unset: 2e6), the largest model a command may build")
    where = os.environ.get("PALPATE_CACHE_DIR")
    if where and not where.strip():      # (empty is unset, as for any variable; blank made a directory named "  ")
        raise UsageError(f"PALPATE_CACHE_DIR={where!r}: a blank path; give the disk cache's directory (made if "
                         f"absent), or unset it for ~/.cache/palpate")
    if where and os.path.exists(where) and not os.path.isdir(where):
        raise UsageError(f"PALPATE_CACHE_DIR={where!r}: not a directory; give the disk cache's directory (made if "
                         f"absent; unset: ~/.cache/palpate)")


if __name__ == "__main__":
    sys.exit(main())
