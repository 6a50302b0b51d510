"""How deep the tip is in the tissue during a descent, from the force felt: what the depth limit measures.

The driver feels contact where the filtered force first passes the contact threshold, some way into the tissue
already: the lag, the indentation at which the tissue pushes back that force (about 1 mm in the paper's tissue with a
Nano17's 20 mN, 1.5 mm in 1500 Pa tissue). Counted from the contact felt, the depth limit let the tip go that much
past it wherever the surface stood higher than registered (before session 43: 4.9-6.0 mm into fem truths against
a 4 mm limit with the surface 2 mm high, bench/depth_limit.py).

The tissue's force rises as F = c d^p (d the indentation below the undeformed surface; ``p`` the plan's
``force_exponent``: the prior's own curve between the contact threshold and the probe's planned depth; c unknown, so
any stiffness). So F^(1/p) is a straight line in the tip's travel, zero at the surface: a least-squares line through
the filtered readings gives the surface as its zero, and the lag as the distance from there to the contact
(``SurfaceFit``; running sums, so each period costs the same). The readings are every one since contact was felt
and, since session 44, those before it from where the force last rose past 30 % of the threshold
(robot.driver._ForceWatch: in soft tissue the contact is felt 2-3 mm in and the limit leaves 1-1.5 mm after it, a
short line to extrapolate that far; the plan's p is the prior's over that same chord). A truth flatter than the prior (q < p)
bends that line down and would put the surface too high, so lines for a few exponents below p are fitted too and
the one nearest p that fits as well as the best within noise is used (EXPONENT_FRACTIONS). Every reading counts:
the single reading at the contact is as noisy as any (a Nano17's filtered sigma is 1.3 mN against a 20 mN threshold,
and the first reading past a threshold is the one noise lifted: counted from it alone, probes stopped 0.16 mm short).

Guards: the lag used is the fit's less LAG_SIGMAS standard errors (from the line's residuals, times the square root of
the filter's window: its readings are not independent), so a fit with few or noisy readings gives a shorter lag --
never a negative one: the depth is at least the travel since contact, the old measure -- and at most ``max_lag_m``
(the contact's depth below the descent's start: the tip started in free air, the surface is no higher). A force
curve steeper than the prior's (a stone, thinner tissue) bends the line and shortens the lag too (the tip goes a
little past the limit: 0.07-0.35 mm on bench/depth_limit.py's fem truths). Not covered: a curve flatter than 0.6 p,
or not a power law at all (a tissue relaxing by half within 0.5 s stopped one probe of three 0.21 mm short), and a
force offset since the zeroing (5 mN makes a 1.5 mm lag read 0.3 mm long); each errs towards stopping early.

The fast-forward's blocks and the period-by-period loop compute the same floating-point operations in the same
order (sums folded left from the committed ones), so both stop at the same period. The period-by-period loop (a real
arm's: 2 ms a period) takes one reading at a time through a path of Python floats (``depth_one``, ``commit_one``),
about 20 us where the arrays' path took about 115 us (some 40 small numpy calls); only the powers F^(1/q) are
numpy's there too (its pow and Python's differ in the last bit for about 5 % of arguments here), so the two paths
agree bit for bit (tested).
"""
from __future__ import annotations

import math

import numpy as np

LAG_SIGMAS = 3.0           # the lag used: the fit's less this many standard errors
_N_MIN = 3                 # readings before a line is fitted (its residuals need n > 2)
MIN_RISE = 0.01            # the line must rise this fraction of its mean value over the travel
# the exponents tried, as fractions of the plan's: a truth whose force curve is flatter than the prior's (q < p: a
# thicker or more compliant tissue, fast relaxation) bends F^(1/p) down, and a line through it puts the surface too
# high (+0.2 mm of a 1 mm lag for q = 1.0 against p = 1.1, +1.1 mm for 1.0 against 1.5: probes stopped early on a
# correctly registered surface); the exponent nearest the plan's whose line fits as well as the best one within
# noise (squared residuals along the travel) is used. Only fractions <= 1: a steeper truth (a stone, thinner
# tissue) gives a shorter lag with p, the safe side
EXPONENT_FRACTIONS = (0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95, 1.0)


class SurfaceFit:
    """Least-squares lines of F^(1/q) against the travel since contact, for q a few fractions of the plan's exponent
    p (EXPONENT_FRACTIONS), from running sums of the readings committed so far (``commit``); ``depth_m`` the depth
    below the fitted surface (the line of the q nearest p that fits as well as the best within noise) after
    candidate readings that follow them (each with all before it, not yet committed)."""

    def __init__(self, exponent: float | None, max_lag_m: float, window: int):
        self.inv_q = None if exponent is None else 1.0 / (exponent * np.array(EXPONENT_FRACTIONS))[:, None]
        self._inv_q1 = None if exponent is None else np.ascontiguousarray(self.inv_q[:, 0])
        self.max_lag = max(float(max_lag_m), 0.0)
        self.k = LAG_SIGMAS * float(np.sqrt(max(window, 1)))
        n_q = len(EXPONENT_FRACTIONS)
        # per exponent: n, sum x, sum y, sum x^2, sum x y, sum y^2 (x the travel, y F^(1/q))
        self._sums = np.zeros((6, n_q, 1))
        self.last_past = 0.0            # the travel of the last reading committed
        self._seen = None               # (travel, force, running sums) of depth_m's last candidates
        self._rows: list | None = None  # the committed sums as Python floats, per exponent (depth_one's)
        self._seen1 = None              # (travel, force, sums per exponent) of depth_one's last reading

    @property
    def sums(self) -> np.ndarray:
        """The committed running sums: (6, exponents, 1)."""
        if self._sums is None:
            self._sums = np.array(self._rows).T[:, :, None]
        return self._sums

    @sums.setter
    def sums(self, value: np.ndarray) -> None:
        self._sums = value
        self._rows = self._seen = self._seen1 = None

    def _terms(self, past: np.ndarray, f: np.ndarray) -> np.ndarray:
        y = np.power(np.maximum(f, 0.0)[None, :], self.inv_q)               # (exponents, readings)
        x = np.broadcast_to(past[None, :], y.shape)
        return np.stack([np.ones_like(y), x, y, x * x, x * y, y * y])

    def _running(self, past: np.ndarray, f: np.ndarray) -> np.ndarray:
        """The sums after each candidate reading: folded left from the committed sums, one reading at a time."""
        t = self._terms(past, f)
        return np.add.accumulate(np.concatenate([self.sums, t], axis=2), axis=2)[:, :, 1:]

    def _lag(self, sums: np.ndarray, past: np.ndarray) -> np.ndarray:
        """The lag (m) after each reading (``sums``: (6, exponents, readings); ``past`` the readings' travel): the
        best-fitting exponent's line's, less its standard errors."""
        n, sx, sy, sxx, sxy, syy = sums
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            mx, my = sx / n, sy / n
            vxx, vxy, vyy = sxx - sx * mx, sxy - sx * my, syy - sy * my
            a = vxy / vxx                                   # the line's slope
            lag = my / a - mx                               # its zero's distance above the contact
            rss = np.maximum(vyy - a * vxy, 0.0)
            se = np.sqrt(rss / (n - 2) * (1.0 / n + (lag + mx) ** 2 / vxx)) / a
            # a line that rises: by MIN_RISE of its mean over the travel (rounding in a flat force's sums gives a
            # slope of 1e-20, whose zero lies anywhere), and by more than LAG_SIGMAS of its own standard error
            se_a = self.k * np.sqrt(rss / (n - 2) / vxx)
            ok = (n >= _N_MIN) & (vxx > 0) & (a > se_a) & (a * past >= MIN_RISE * my) & np.isfinite(lag + se) \
                & (a * a > 0)           # (a slope below 1e-162 squares to 0: no misfit to compare)
            misfit = np.where(ok, rss / (a * a), np.inf)    # squared residuals along the travel (m^2)
            # the exponent nearest the plan's whose line fits as well as the best within noise (an F-test's bound:
            # LAG_SIGMAS^2 more than the best's residual variance, times the window for correlated readings): where
            # noise alone makes the misfits differ, the plan's (a lower one shortens the lag: the tip goes deeper)
            near = misfit <= (1.0 + self.k * self.k / n[0]) * np.min(misfit, axis=0)
            best = misfit.shape[0] - 1 - np.argmax(near[::-1], axis=0)
            cols = np.arange(misfit.shape[1])
            used = np.where(ok[best, cols], lag[best, cols] - self.k * se[best, cols], 0.0)
        return np.clip(used, 0.0, self.max_lag)

    def depth_m(self, past_m, f_n) -> np.ndarray:
        """The depth below the fitted surface after each reading of ``past_m`` (travel since contact, m) and ``f_n``
        (the filtered force, N): the travel plus the lag (0 without an exponent or a line to fit)."""
        past = np.atleast_1d(np.asarray(past_m, dtype=float))
        if self.inv_q is None:
            return past
        f = np.atleast_1d(np.asarray(f_n, dtype=float))
        run = self._running(past, f)
        self._seen = (past, f, run)     # commit() of the same readings reuses the sums (the driver's period: 2 ms)
        return past + self._lag(run, past)

    def lag_m(self) -> float:
        """The lag of the readings committed so far (0 without an exponent or a line to fit)."""
        if self.inv_q is None:
            return 0.0
        return float(self._lag(self.sums, np.array([self.last_past]))[0])

    def commit(self, past_m, f_n) -> None:
        """The readings consumed (in order): into the sums."""
        if self.inv_q is None:
            return
        past = np.atleast_1d(np.asarray(past_m, dtype=float))
        if past.size:
            f = np.atleast_1d(np.asarray(f_n, dtype=float))
            seen = self._seen
            if seen is not None and len(seen[0]) >= len(past) and np.array_equal(seen[0][:len(past)], past) \
                    and np.array_equal(seen[1][:len(past)], f):
                run = seen[2][:, :, :len(past)]
            else:
                run = self._running(past, f)
            self.sums = run[:, :, -1:].copy()
            self.last_past = float(past[-1])
            self._seen = self._seen1 = self._rows = None

    # the period-by-period path: one reading, Python floats (the same operations in the same order as the arrays')

    def depth_one(self, past_m: float, f_n: float) -> float:
        """``depth_m`` of one reading after the committed ones, as a float, bit for bit."""
        if self.inv_q is None:
            return past_m
        x = past_m
        ys = np.power(np.maximum(f_n, 0.0), self._inv_q1).tolist()
        if self._rows is None:
            self._rows = self.sums[:, :, 0].T.tolist()              # per exponent: n, sx, sy, sxx, sxy, syy
        xx = x * x
        rows = [(n + 1.0, sx + x, sy + y, sxx + xx, sxy + x * y, syy + y * y)
                for (n, sx, sy, sxx, sxy, syy), y in zip(self._rows, ys)]
        self._seen1 = (past_m, f_n, rows)
        return past_m + self._lag_one(rows, x)

    def commit_one(self, past_m: float, f_n: float) -> None:
        """``commit`` of one reading."""
        if self.inv_q is None:
            return
        seen = self._seen1
        if seen is None or seen[0] != past_m or seen[1] != f_n:
            self.depth_one(past_m, f_n)
            seen = self._seen1
        self._rows = seen[2]
        self._sums = None               # (made from the rows when an array's path needs them)
        self.last_past = float(past_m)
        self._seen = self._seen1 = None

    def _lag_one(self, rows: list, past: float) -> float:
        """``_lag`` of one reading: ``rows`` the sums per exponent."""
        k = self.k
        misfit, fits = [], []
        for n, sx, sy, sxx, sxy, syy in rows:
            fit = None
            if n >= _N_MIN:
                mx, my = sx / n, sy / n
                vxx = sxx - sx * mx
                if vxx > 0:
                    vxy, vyy = sxy - sx * my, syy - sy * my
                    a = vxy / vxx
                    rss = max(vyy - a * vxy, 0.0)
                    se_a = k * math.sqrt(rss / (n - 2) / vxx)
                    if a > se_a and a * past >= MIN_RISE * my:
                        lag = my / a - mx
                        t = lag + mx
                        se = math.sqrt(rss / (n - 2) * (1.0 / n + t * t / vxx)) / a
                        if math.isfinite(lag + se) and a * a > 0:
                            fit = (lag, se, rss / (a * a))
            fits.append(fit)
            misfit.append(math.inf if fit is None else fit[2])
        n0 = rows[0][0]
        bound = (1.0 + k * k / n0) * min(misfit) if n0 > 0 else math.inf
        best = max(i for i, m in enumerate(misfit) if m <= bound) if any(m <= bound for m in misfit) \
            else len(misfit) - 1
        fit = fits[best]
        used = 0.0 if fit is None else fit[0] - k * fit[1]
        return min(max(used, 0.0), self.max_lag)
