"""How deep the tip is in the tissue during a descent, from the force felt: what the depth limit measures.

The driver feels contact where the filtered force first passes the contact threshold, some way into the tissue
already: the lag, the indentation at which the tissue pushes back that force (about 1 mm in the paper's tissue with a
Nano17's 20 mN, 1.5 mm in 1500 Pa tissue). Counted from the contact felt, the depth limit let the tip go that much
past it wherever the surface stood higher than registered (before session 43: 4.9-5.5 mm into the tissue against
a 4 mm limit, bench/depth_limit.py).

The tissue's force rises as F = c d^p (d the indentation below the undeformed surface; ``p`` the plan's
``force_exponent``: the prior's own curve between the contact threshold and the probe's planned depth; c unknown, so
any stiffness). So F^(1/p) is a straight line in the tip's travel, zero at the surface: a least-squares line through
every filtered reading since contact was felt gives the surface as its zero, and the lag as the distance from there
to the contact (``SurfaceFit``; running sums, so each period costs the same). Every reading counts: the single reading
at the contact is as noisy as any (a Nano17's filtered sigma is 1.3 mN against a 20 mN threshold, and the first
reading past a threshold is the one noise lifted: counted from it alone, probes stopped up to 0.16 mm short).

Guards: the lag used is the fit's less LAG_SIGMAS standard errors (from the line's residuals, times the square root of
the filter's window: its readings are not independent), so a fit with few or noisy readings gives a shorter lag --
never a negative one: the depth is at least the travel since contact, the old measure -- and at most ``max_lag_m``
(the contact's depth below the descent's start: the tip started in free air, the surface is no higher). A force
curve steeper than the prior's (a stone, thinner tissue) bends the line and shortens the lag too; a flatter one
(relaxing tissue) lengthens it. Measured against fem's forces (bench/depth_limit.py, docs/driver.md).

The fast-forward's blocks and the period-by-period loop compute the same floating-point operations in the same
order (sums folded left from the committed ones), so both stop at the same period.
"""
from __future__ import annotations

import numpy as np

LAG_SIGMAS = 3.0           # the lag used: the fit's less this many standard errors
_N_MIN = 3                 # readings before a line is fitted (its residuals need n > 2)
MIN_RISE = 0.01            # the line must rise this fraction of its mean value over the travel


class SurfaceFit:
    """The least-squares line of F^(1/p) against the travel since contact, from running sums of the readings
    committed so far (``commit``); ``depth_m`` the depth below the fitted surface of candidate readings that follow
    them (each with all before it, not yet committed)."""

    def __init__(self, exponent: float | None, max_lag_m: float, window: int):
        self.inv_p = None if exponent is None else 1.0 / exponent
        self.max_lag = max(float(max_lag_m), 0.0)
        self.k = LAG_SIGMAS * float(np.sqrt(max(window, 1)))
        self.sums = np.zeros(6)         # n, sum x, sum y, sum x^2, sum x y, sum y^2 (x the travel, y F^(1/p))
        self.last_past = 0.0            # the travel of the last reading committed

    def _terms(self, past, f) -> np.ndarray:
        y = np.power(np.maximum(f, 0.0), self.inv_p)
        return np.stack([np.ones_like(past), past, y, past * past, past * y, y * y])

    def _running(self, past, f) -> np.ndarray:
        """The sums after each candidate reading: folded left from the committed sums, one reading at a time."""
        t = self._terms(past, f)
        return np.add.accumulate(np.concatenate([self.sums[:, None], t], axis=1), axis=1)[:, 1:]

    def _lag(self, sums: np.ndarray, past: np.ndarray) -> np.ndarray:
        """The lag (m) of the line through ``sums`` (columns: after each reading; ``past`` its travel)."""
        n, sx, sy, sxx, sxy, syy = sums
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            mx, my = sx / n, sy / n
            vxx, vxy, vyy = sxx - sx * mx, sxy - sx * my, syy - sy * my
            a = vxy / vxx                                   # the line's slope
            lag = my / a - mx                               # its zero's distance above the contact
            rss = np.maximum(vyy - a * vxy, 0.0)
            se = np.sqrt(rss / (n - 2) * (1.0 / n + (lag + mx) ** 2 / vxx)) / a
            lag = lag - self.k * se
            # a line that rises: by MIN_RISE of its mean over the travel (rounding in a flat force's sums gives a
            # slope of 1e-20, whose zero lies anywhere), and by more than LAG_SIGMAS of its own standard error
            se_a = self.k * np.sqrt(rss / (n - 2) / vxx)
            ok = (n >= _N_MIN) & (vxx > 0) & (a > se_a) & (a * past >= MIN_RISE * my) & np.isfinite(lag)
        return np.clip(np.where(ok, lag, 0.0), 0.0, self.max_lag)

    def depth_m(self, past_m, f_n) -> np.ndarray:
        """The depth below the fitted surface after each reading of ``past_m`` (travel since contact, m) and ``f_n``
        (the filtered force, N): the travel plus the lag (0 without an exponent or a line to fit)."""
        past = np.atleast_1d(np.asarray(past_m, dtype=float))
        if self.inv_p is None:
            return past
        return past + self._lag(self._running(past, np.atleast_1d(np.asarray(f_n, dtype=float))), past)

    def lag_m(self) -> float:
        """The lag of the readings committed so far (0 without an exponent or a line to fit)."""
        if self.inv_p is None:
            return 0.0
        return float(self._lag(self.sums[:, None], np.array([self.last_past]))[0])

    def commit(self, past_m, f_n) -> None:
        """The readings consumed (in order): into the sums."""
        if self.inv_p is None:
            return
        past = np.atleast_1d(np.asarray(past_m, dtype=float))
        if past.size:
            self.sums = self._running(past, np.atleast_1d(np.asarray(f_n, dtype=float)))[:, -1].copy()
            self.last_past = float(past[-1])
