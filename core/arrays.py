"""Small array helpers on the localizer's hot paths."""
from __future__ import annotations

import numpy as np


def clip(a, lo, hi):
    """``np.clip(a, lo, hi)``'s values as ``np.minimum(np.maximum(a, lo), hi)``: np.clip costs about 5 us on a small
    array, this one about 1.5 us (the localizer calls it some 40,000 times per fit). NaN stays NaN; a -0.0 at a
    bound of 0.0 stays -0.0 (np.clip gives 0.0): equal values."""
    return np.minimum(np.maximum(a, lo), hi)
