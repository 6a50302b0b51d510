"""Shared by the subcommands: ``--json PATH`` (``-`` for standard output) writing."""
from __future__ import annotations

import contextlib
import json
import sys
from pathlib import Path

from app.errors import UsageError
from fem.scene import STRAIN_MAX, STRAIN_WARN

_JSON_OUT = []       # the standard output ``json_alone`` kept for the JSON while the rest went to stderr


@contextlib.contextmanager
def json_alone(dest: str | None):
    """With ``--json -``: while the block runs, whatever it prints to standard output goes to stderr, and only
    ``write_json("-", ...)`` writes to standard output (which then holds the JSON alone); otherwise nothing changes."""
    if dest != "-":
        yield
        return
    _JSON_OUT.append(sys.stdout)
    try:
        with contextlib.redirect_stdout(sys.stderr):
            yield
    finally:
        _JSON_OUT.pop()


def write_json(dest: str | None, data: dict) -> None:
    """Write ``data`` as JSON to ``dest``; ``-`` prints it (to the standard output ``json_alone`` kept); None or ""
    writes nothing."""
    if not dest:
        return
    text = json.dumps(data, indent=1)
    if dest == "-":
        print(text, file=_JSON_OUT[-1] if _JSON_OUT else sys.stdout)
    else:
        try:
            Path(dest).parent.mkdir(parents=True, exist_ok=True)
            Path(dest).write_text(text + "\n")
        except OSError as e:         # a full disk, a vanished directory: the one line names the file
            raise UsageError(f"--json {dest}: {e.strerror or e}") from None


def warn_strain(command: str, sc, depth_m: float) -> None:
    """One line on stderr when an indentation exceeds the STRAIN_WARN of the tissue height the linear small-strain
    model is stated for (fem refuses above STRAIN_MAX): the force and stresses are then a linear extrapolation."""
    h = sc.tissue.height_m
    if depth_m > STRAIN_WARN * h * (1 + 1e-9):
        print(f"palpate {command}: {sc.name}: warning: --depth-m {depth_m:g} is {depth_m / h:.0%} of the tissue height "
              f"({h:g} m): the linear small-strain model is stated for up to {STRAIN_WARN:.0%} (refused above "
              f"{STRAIN_MAX:.0%}); the force and stresses are a linear extrapolation", file=sys.stderr)
