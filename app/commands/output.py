"""Shared by the subcommands: ``--json PATH`` (``-`` for standard output) writing."""
from __future__ import annotations

import json
from pathlib import Path


def write_json(dest: str | None, data: dict) -> None:
    """Write ``data`` as JSON to ``dest``; ``-`` prints it; None or "" writes nothing."""
    if not dest:
        return
    text = json.dumps(data, indent=1)
    if dest == "-":
        print(text)
    else:
        Path(dest).parent.mkdir(parents=True, exist_ok=True)
        Path(dest).write_text(text + "\n")
