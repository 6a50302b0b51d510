"""Exact solver for the linear complementarity problem of frictionless contact.

    w = q + M z,   z >= 0,   w >= 0,   z . w = 0,        M symmetric positive definite

equivalently min 1/2 z'Mz + q'z subject to z >= 0. A primal active-set method (Lawson-Hanson's for NNLS, written
for the QP): each step solves the equality system on the current active set, so on return the active entries solve
M_AA z_A = -q_A to round-off, inactive entries are exactly zero, and every step strictly lowers the objective, so it
terminates in finitely many steps. Warm start: the geometric overlap (q < 0) is usually the answer already.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class LCPResult:
    z: np.ndarray           # contact forces (>= 0)
    w: np.ndarray           # gaps (>= 0 up to round-off)
    active: np.ndarray      # bool
    iterations: int


def _solve_active(M: np.ndarray, q: np.ndarray, P: np.ndarray) -> np.ndarray:
    s = np.zeros(len(q))
    idx = np.flatnonzero(P)
    if len(idx):
        if idx[-1] - idx[0] == len(idx) - 1:        # a contiguous set (a contact interval, as a rule): views
            idx = slice(int(idx[0]), int(idx[-1]) + 1)
            s[idx] = np.linalg.solve(M[idx, idx], -q[idx])
        else:
            s[idx] = np.linalg.solve(M[idx][:, idx], -q[idx])
    return s


def solve_lcp(M: np.ndarray, q: np.ndarray, start: np.ndarray | None = None, max_iter: int | None = None) -> LCPResult:
    n = len(q)
    tol = 1e-12 * max(float(np.abs(q).max(initial=0.0)), 1e-300)
    max_iter = max_iter or 10 * n + 10
    P = np.zeros(n, bool) if start is None else start.copy()
    z = np.zeros(n)
    it = 0
    # Warm start: shrink the guessed active set until its equality solution is positive (a feasible point).
    while P.any():
        it += 1
        s = _solve_active(M, q, P)
        if (s[P] > 0).all():
            z = s
            break
        P &= s > 0
    while True:
        w = q + M @ z
        cand = ~P & (w < -tol)
        if not cand.any():
            return LCPResult(z=z, w=w, active=P, iterations=it)
        P[np.argmin(np.where(cand, w, np.inf))] = True
        while True:  # Lawson-Hanson inner loop: move towards the active-set solution, staying feasible
            it += 1
            if it > max_iter:
                raise RuntimeError(f"LCP active-set iteration did not terminate in {max_iter} steps")
            s = _solve_active(M, q, P)
            if (s[P] > 0).all():
                z = s
                break
            bad = P & (s <= 0)
            alpha = np.min(z[bad] / (z[bad] - s[bad]))
            z = z + alpha * (s - z)
            P &= z > 0
            z[~P] = 0.0
