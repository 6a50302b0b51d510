"""The console scripts' entry points (pyproject.toml): a Ctrl-C while the command's modules load (up to half a second:
numpy, scipy, casadi) ends as it does once the command runs, ``prog: interrupted`` and exit 130, not a traceback."""
from __future__ import annotations

import importlib
import sys


def _start(module: str, prog: str) -> int:
    try:
        return importlib.import_module(module).main()
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130


def palpate() -> int:
    return _start("app.cli", "palpate")


def palpate_cell() -> int:
    return _start("app.cell", "palpate-cell")
