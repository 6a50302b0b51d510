"""core.peak: the one sub-sample peak fit (fem's surface stress, the localizer's contrast, predict's ratio)."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from core.peak import parabola_peak


@settings(max_examples=60, deadline=None)
@given(xp=st.floats(0.1, 0.9), curv=st.floats(0.1, 10.0), n=st.integers(5, 40))
def test_a_sampled_parabola_peak_is_recovered_exactly(xp, curv, n):
    x = np.linspace(0.0, 1.0, n)
    y = 3.0 - curv * (x - xp) ** 2
    i = int(np.argmax(y))
    lo, hi = max(i - 1, 0), min(i + 1, n - 1)
    if hi - lo < 2:
        return
    px, py = parabola_peak(x, y, lo, hi)
    assert abs(px - xp) < 1e-9 and abs(py - 3.0) < 1e-9


def test_no_vertex_outside_the_window_or_for_an_upward_parabola():
    x = np.array([0.0, 1.0, 2.0, 3.0])
    assert parabola_peak(x, np.array([0.0, 1.0, 2.0, 3.0]), 1, 3) == (3.0, 3.0)      # monotone: the largest sample
    assert parabola_peak(x, np.array([1.0, 0.0, 1.0, 5.0]), 0, 2) in ((0.0, 1.0), (2.0, 1.0))  # opens upwards
    assert parabola_peak(x, np.array([1.0, 2.0, 1.5, 0.0]), 1, 1) == (1.0, 2.0)      # fewer than 3 samples
