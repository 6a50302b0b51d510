"""Numbers that are not finite in outputs: null in JSON, an empty cell in CSV (a rate of no trials, a median of
none). The project writes no NaN or inf to a file a user reads (docs/architecture.md, core)."""
from __future__ import annotations

import math

import numpy as np


def nulled(obj):
    """``obj`` for ``json.dumps(..., allow_nan=False)``: every float that is not finite, at any depth, as None."""
    if isinstance(obj, dict):
        return {k: nulled(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [nulled(v) for v in obj]
    if isinstance(obj, (float, np.floating)) and not math.isfinite(obj):
        return None
    return obj


def csv_cell(v):
    """A CSV cell: empty for a float that is not finite, else the value."""
    return "" if isinstance(v, (float, np.floating)) and not math.isfinite(v) else v


def csv_row(row: dict) -> dict:
    return {k: csv_cell(v) for k, v in row.items()}
