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


def ratio_of(a, b) -> np.ndarray:
    """a / b element by element, NaN where it is undefined (b not positive, either not finite): a reference that
    feels no force at a waypoint (the tip touches no surface node at a very shallow depth) has no ratio there."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = (b > 0) & np.isfinite(a) & np.isfinite(b)
    return np.divide(a, b, out=np.full(np.broadcast(a, b).shape, np.nan), where=ok)


def or_null(v) -> list:
    """A list for JSON: NaN (undefined) as None (null)."""
    return [float(x) if np.isfinite(x) else None for x in np.asarray(v, float).ravel()]


def upper_window(y, i: int, fraction: float = 0.25, dip: float = 0.02) -> tuple[int, int]:
    """The contiguous samples around the largest, ``y[i]``, in the profile's upper ``fraction`` (of its finite
    range), for ``parabola_peak``. Where a side passes a valley (the profile rises again by more than ``dip`` of
    that range, and by more than twice the median |second difference| of the samples (a noisy profile, such as a
    stress ratio on two meshes, zig-zags by that much), above the lowest sample passed: another hump, as between
    two stones) that side keeps only the upper
    half of its drop to the valley, and the window is made symmetric about ``i`` (a parabola through one hump's top,
    not through the valley's flat floor). NaN samples end a side."""
    y = np.asarray(y, float)
    span = y[i] - np.nanmin(y)
    d2 = np.abs(np.diff(y, 2))
    rough = float(np.median(d2[np.isfinite(d2)])) if np.isfinite(d2).any() else 0.0
    cut, tol = y[i] - fraction * span, max(dip * span, 2.0 * rough)    # a rise beyond the samples' own roughness

    def edge(step, floor):
        j, low, valley = i, y[i], False
        while 0 <= j + step < len(y) and y[j + step] >= floor:
            if y[j + step] > low + tol:
                valley = True
                break
            j += step
            low = min(low, y[j])
        return j, low, valley
    (lo, low_l, v_l), (hi, low_r, v_r) = edge(-1, cut), edge(1, cut)
    if not (v_l or v_r):
        return lo, hi
    if v_l:
        lo = edge(-1, y[i] - 0.5 * (y[i] - low_l))[0]
    if v_r:
        hi = edge(1, y[i] - 0.5 * (y[i] - low_r))[0]
    k = min(i - lo, hi - i)
    return i - k, i + k
