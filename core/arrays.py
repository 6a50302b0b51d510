"""Small array helpers on the localizer's hot paths."""
from __future__ import annotations

import numpy as np


def clip(a, lo, hi):
    """``np.clip(a, lo, hi)``'s values as ``np.minimum(np.maximum(a, lo), hi)``: np.clip costs about 5 us on a small
    array, this one about 1.5 us (the localizer calls it some 40,000 times per fit). The same values and dtypes (NaN
    stays NaN); only the sign of a zero at a bound of zero may differ, and the two zeros compare equal."""
    return np.minimum(np.maximum(a, lo), hi)
