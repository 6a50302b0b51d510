"""The force-limited indentation depth on a 3D block, exactly and fast: a parametric solve of fem's contact LCP.

fem's 3D contact model (fem.contact3d.SurfaceModel3D) answers a waypoint (x, y, depth) with the linear
complementarity problem  gap = q + C_ww f >= 0,  f >= 0,  gap . f = 0  over the probed-patch nodes under the tip's
footprint (the window w), where C is the condensed patch compliance and q = h - depth, h the tip profile's height above
each node (fem.contact3d.tip_profile3d at depth 0). C_ww is symmetric positive definite, so the LCP has one solution,
and on a fixed contact set A the force is affine in the depth:

    F(depth) = 1' C_AA^-1 (depth 1 - h_A),     dF/ddepth = 1' C_AA^-1 1 > 0.

F is therefore continuous and piecewise linear in depth. The depth where F reaches a target is found by Newton steps
on it (each an exact LCP solve at the new depth, fem.lcp.solve_lcp, warm-started from the last contact set, plus
one solve for the slope): once the step's contact set is the answer's, the step lands on the target to round-off, so
two or three LCPs per waypoint do what a bisection needs ~15 for. Every returned force is the LCP's certified
solution at the returned depth (not an extrapolation): it is fem's ``force_n`` there to round-off (the solution is
unique; tests/test_planner3d.py and bench/bench_planner3d.py compare them) and never above the target.

Why not fem's ``force_n`` in ``raster.depth_for_force``: each call re-derives the window and solves from a generic
start (~1 ms), and the secant search needs 3-8 of them; for 400 waypoints that alone is 2-4 s (bench_planner3d.py).
"""
from __future__ import annotations

import math

import numpy as np

from fem.contact3d import check_waypoint3d, tip_profile3d
from fem.lcp import solve_lcp


class ContactDepths3D:
    """Exact forces and force-limited depths on a fem.contact3d.SurfaceModel3D (its window compliance, patch node
    positions ``xy`` and scene). ``force_n(x, y, depth)`` is fem's force; ``depth_for(position, target, depth_max,
    guess)`` the deepest depth in [0, depth_max] whose force is at most ``target`` (and within ``rtol_force`` of it,
    unless depth_max is reached first). Counts LCP solves in ``n_lcp``."""

    def __init__(self, model, rtol_force: float = 5e-4):
        self.model = model
        self.scene = model.scene
        self.xy = model.xy
        self.rtol_force = rtol_force
        self.n_lcp = 0
        self.n_fallback = 0         # LCPs the block pivoting left to fem.lcp.solve_lcp
        self._last = None           # (contact radius, depth) of the last waypoint's answer: the next one's start

    def _window(self, x_m: float, y_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(window node indices, tip height h at depth 0 there, squared distance from the tip's axis); the window is
        fem's (SurfaceModel3D._window: patch nodes within the tip radius)."""
        R = self.scene.indenter.radius_m
        r2 = (self.xy[:, 0] - x_m) ** 2 + (self.xy[:, 1] - y_m) ** 2
        idx = np.flatnonzero(r2 <= R * R)
        h = tip_profile3d(self.scene.indenter, x_m, y_m, 0.0, self.xy[idx, 0], self.xy[idx, 1])
        return idx, h, r2[idx]

    def _solve(self, Cw: np.ndarray, h: np.ndarray, depth_m: float, start: np.ndarray):
        """(force, contact set, slope dF/ddepth on that set) of the exact LCP at ``depth_m``."""
        q = h - depth_m
        if depth_m <= 0.0 or not np.any(q < 0):
            return 0.0, np.zeros(len(h), bool), 0.0
        self.n_lcp += 1
        A = start & (q < 0) if start.any() else q < 0.5 * q.min()
        out = _lcp_block_pivoting(Cw, q, A)
        if out is None:                       # no certified answer in a few block pivots: fem's own solver
            self.n_fallback += 1
            r = solve_lcp(Cw, q, start=A)
            A = r.z > 0
            z = r.z
            slope = float(np.linalg.solve(Cw[np.ix_(A, A)], np.ones(int(A.sum()))).sum()) if A.any() else 0.0
        else:
            z, A, slope = out
        return float(z.sum()), A, slope

    def force_n(self, x_m: float, y_m: float, depth_m: float) -> float:
        """fem's contact force at (x, y, depth), N (the same LCP, solved on the whole window)."""
        check_waypoint3d(self.scene, x_m, y_m, depth_m)
        idx, h, _ = self._window(x_m, y_m)
        return self._solve(self._compliance(idx, x_m, y_m), h, depth_m, np.zeros(len(idx), bool))[0]

    def _compliance(self, idx: np.ndarray, x_m: float, y_m: float) -> np.ndarray:
        """The window's gap compliance as fem's LCP has it (the tissue's, plus an elastic tip's)."""
        return self.model.window_compliance(idx, x_m, y_m)(None, None)

    def depth_for(self, position, target_n: float, depth_max_m: float,
                  guess_m: float | None = None) -> tuple[float, float]:
        """(depth_m, force_n): the largest depth in [0, depth_max] with force <= target, to ``rtol_force`` in force
        (the force is exact at the returned depth and never above the target). Newton steps on the piecewise linear
        F(depth), safeguarded by the bracket; ``guess_m`` (the neighbour's depth) is the first depth tried when
        below depth_max."""
        x_m, y_m = (float(v) for v in position)
        check_waypoint3d(self.scene, x_m, y_m, depth_max_m)
        idx, h, r2 = self._window(x_m, y_m)
        Cw = self._compliance(idx, x_m, y_m)
        aim = target_n * (1.0 - 0.5 * self.rtol_force)
        lo, f_lo, A_lo, hi = 0.0, 0.0, None, None
        d = depth_max_m if guess_m is None else min(max(guess_m, 1e-6 * depth_max_m), depth_max_m)
        start = np.zeros(len(idx), bool)
        if self._last is not None:       # the neighbour's contact disk, scaled as sqrt(depth) (Hertz)
            a, d0 = self._last
            start = r2 < a * a * d / d0
        for _ in range(60):
            f, A, slope = self._solve(Cw, h, d, start)
            if A.any():
                start = A
            if f <= target_n:
                lo, f_lo, A_lo = d, f, A
                if d >= depth_max_m or f >= target_n * (1.0 - self.rtol_force):
                    break
            else:
                hi = d
            if hi is not None and hi - lo <= 1e-12 * depth_max_m:
                break
            top = depth_max_m if hi is None else hi
            nxt = d + (aim - f) / slope if slope > 0 else (float(h.min()) if f == 0 else math.nan)
            if not (lo < nxt < top):          # outside the bracket (or no slope): bisect it
                nxt = 0.5 * (lo + top) if hi is not None else min(2.0 * max(d, 1e-6 * depth_max_m), depth_max_m)
            d = min(nxt, depth_max_m)
        if A_lo is not None and A_lo.any():
            self._last = (float(np.sqrt(r2[A_lo].max())) + 1e-12, lo)
        return lo, f_lo


def _lcp_block_pivoting(M: np.ndarray, q: np.ndarray, A: np.ndarray, max_pivots: int = 12):
    """The LCP  w = q + M z >= 0, z >= 0, z.w = 0  (M symmetric positive definite) by block principal pivoting from
    the contact set ``A``: solve M_AA z_A = -q_A, then drop every node of A with z <= 0 and add every node outside
    with w < 0, until neither is left. Returns (z, A, 1' M_AA^-1 1) once certified (z_A > 0, w >= -tol elsewhere,
    w_A = 0 by construction: the LCP's unique solution, to fem.lcp's tolerance), or None after ``max_pivots`` (block
    pivoting may cycle; the caller then uses fem.lcp's finite active-set method)."""
    tol = 1e-12 * max(float(np.abs(q).max(initial=0.0)), 1e-300)
    n = len(q)
    A = A.copy()
    for _ in range(max_pivots):
        ia = np.flatnonzero(A)
        z = np.zeros(n)
        s = 0.0
        if len(ia):
            sol = np.linalg.solve(M[np.ix_(ia, ia)], np.column_stack([-q[ia], np.ones(len(ia))]))
            z[ia] = sol[:, 0]
            s = float(sol[:, 1].sum())
        w = q + M[:, ia] @ z[ia]
        drop = A & (z <= 0)
        add = ~A & (w < -tol)
        if not drop.any() and not add.any():
            return z, A, s
        A = (A & ~drop) | add
    return None
