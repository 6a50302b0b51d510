"""The sub-sample peak of a sampled profile: the vertex of a least-squares parabola through the samples around the
largest one. One implementation for fem's surface-stress peak, the localizer's contrast peak and predict's ratio
peak."""
from __future__ import annotations

import numpy as np


def parabola_peak(x, y, lo: int, hi: int) -> tuple[float, float]:
    """(x, y) of the peak of samples ``lo..hi`` (inclusive, at least 3; the largest of them is the sample peak): the
    vertex of the least-squares parabola through them when it opens downwards and lies within [x[lo], x[hi]], else
    the largest sample itself."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    i = lo + int(np.argmax(y[lo:hi + 1]))
    if hi - lo < 2:
        return float(x[i]), float(y[i])
    a, b, c = np.polyfit(x[lo:hi + 1] - x[i], y[lo:hi + 1], 2)
    if a < 0 and x[lo] <= x[i] - b / (2 * a) <= x[hi]:
        return float(x[i] - b / (2 * a)), float(c - b * b / (4 * a))
    return float(x[i]), float(y[i])
