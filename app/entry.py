"""The console scripts' entry points (pyproject.toml): a Ctrl-C while the command's modules load (up to half a second:
numpy, scipy, casadi) ends as it does once the command runs, ``prog: interrupted`` and exit 130, not a traceback; so
does a supervisor's SIGTERM, from here on (app.cli.main says why)."""
from __future__ import annotations

import importlib
import signal
import sys


def _start(module: str, prog: str) -> int:
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        return importlib.import_module(module).main()
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130


def palpate() -> int:
    return _start("app.cli", "palpate")


def palpate_cell() -> int:
    return _start("app.cell", "palpate-cell")
