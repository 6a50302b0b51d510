"""Lagrange tetrahedra (P1, P2) on the reference tetrahedron (0,0,0), (1,0,0), (0,1,0), (0,0,1), and quadrature.

Node order follows gmsh: vertices 0..3, then (P2) the mid-edge nodes of edges 0-1, 1-2, 2-0, 3-0, 3-2, 3-1
(gmsh's 10-node tetrahedron; tests check every mid-edge node of a gmsh mesh lies where this order says).
"""
from __future__ import annotations

import numpy as np

EDGES = ((0, 1), (1, 2), (2, 0), (3, 0), (3, 2), (3, 1))   # P2: node 4 + k sits on EDGES[k]


def _barycentric(pts: np.ndarray) -> np.ndarray:
    """(n, 4) barycentric coordinates L0..L3 of reference points (n, 3)."""
    r, s, t = pts[:, 0], pts[:, 1], pts[:, 2]
    return np.stack([1.0 - r - s - t, r, s, t], axis=1)


# dL_a / d(r, s, t)
_DL = np.array([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def shape(order: int, pts: np.ndarray) -> np.ndarray:
    """Shape function values at reference points pts (n, 3): array (n, nen)."""
    L = _barycentric(pts)
    if order == 1:
        return L
    vert = L * (2 * L - 1)
    mid = np.stack([4 * L[:, a] * L[:, b] for a, b in EDGES], axis=1)
    return np.hstack([vert, mid])


def shape_grad(order: int, pts: np.ndarray) -> np.ndarray:
    """Reference gradients at pts (n, 3): array (n, nen, 3)."""
    n = len(pts)
    if order == 1:
        return np.broadcast_to(_DL, (n, 4, 3)).copy()
    L = _barycentric(pts)
    vert = (4 * L - 1)[:, :, None] * _DL[None]                                     # (n, 4, 3)
    mid = np.stack([4 * (L[:, a, None] * _DL[b] + L[:, b, None] * _DL[a]) for a, b in EDGES], axis=1)
    return np.concatenate([vert, mid], axis=1)


def nodes_ref(order: int) -> np.ndarray:
    """Reference coordinates of the element's nodes (nen, 3)."""
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    if order == 1:
        return v
    return np.vstack([v, [0.5 * (v[a] + v[b]) for a, b in EDGES]])


def quadrature(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 3) and weights (n,) exact for polynomials of the given degree (weights sum to 1/6)."""
    if degree <= 1:
        return np.array([[0.25, 0.25, 0.25]]), np.array([1 / 6])
    if degree == 2:
        a, b = 0.5854101966249685, 0.1381966011250105
        p = np.array([[b, b, b], [a, b, b], [b, a, b], [b, b, a]])
        return p, np.full(4, 1 / 24)
    if degree >= 5:
        return _degree5()
    # Keast's 11-point rule, degree 4 (one negative weight)
    p = [[0.25, 0.25, 0.25]]
    w = [-0.01315555555555556]
    a, b = 0.7857142857142857, 0.0714285714285714
    p += [[b, b, b], [a, b, b], [b, a, b], [b, b, a]]
    w += [0.007622222222222222] * 4
    a, b = 0.3994035761667992, 0.1005964238332008
    p += [[a, a, b], [a, b, a], [a, b, b], [b, a, a], [b, a, b], [b, b, a]]
    w += [0.02488888888888889] * 6
    return np.array(p), np.array(w)


def _degree5() -> tuple[np.ndarray, np.ndarray]:
    """The 14-point rule of degree 5 with positive weights (Walkington; Keast's rule 6)."""
    pts, w = [], []
    for a, wa in ((0.0927352503108912, 0.01224884051939366), (0.3108859192633006, 0.01878132095300264)):
        for k in range(4):
            L = np.full(4, a)
            L[k] = 1 - 3 * a
            pts.append(L[1:])
            w.append(wa)
    b = 0.4544962958743504
    for i in range(4):
        for j in range(i + 1, 4):
            L = np.full(4, 0.5 - b)
            L[[i, j]] = b
            pts.append(L[1:])
            w.append(0.007091003462846911)
    return np.array(pts), np.array(w)
