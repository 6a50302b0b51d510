"""Lagrange triangles (P1, P2) on the reference triangle (0,0), (1,0), (0,1), and quadrature rules.

Node order follows gmsh: vertices 0, 1, 2, then (P2) the mid-edge nodes of edges 0-1, 1-2, 2-0.
"""
from __future__ import annotations

import numpy as np


def shape(order: int, pts: np.ndarray) -> np.ndarray:
    """Shape function values at reference points pts (n, 2): array (n, nen)."""
    r, s = pts[:, 0], pts[:, 1]
    t = 1.0 - r - s
    if order == 1:
        return np.stack([t, r, s], axis=1)
    return np.stack([t * (2 * t - 1), r * (2 * r - 1), s * (2 * s - 1), 4 * t * r, 4 * r * s, 4 * s * t], axis=1)


def shape_grad(order: int, pts: np.ndarray) -> np.ndarray:
    """Reference gradients at pts (n, 2): array (n, nen, 2) of dN/dr, dN/ds."""
    n = len(pts)
    r, s = pts[:, 0], pts[:, 1]
    t = 1.0 - r - s
    if order == 1:
        g = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])
        return np.broadcast_to(g, (n, 3, 2)).copy()
    dr = np.stack([1 - 4 * t, 4 * r - 1, 0 * r, 4 * (t - r), 4 * s, -4 * s], axis=1)
    ds = np.stack([1 - 4 * t, 0 * r, 4 * s - 1, -4 * r, 4 * r, 4 * (t - s)], axis=1)
    return np.stack([dr, ds], axis=2)


def nodes_ref(order: int) -> np.ndarray:
    """Reference coordinates of the element's nodes (nen, 2)."""
    v = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    if order == 1:
        return v
    return np.vstack([v, 0.5 * (v + v[[1, 2, 0]])])


def quadrature(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 2) and weights (n,) exact for polynomials of the given degree (weights sum to 1/2)."""
    if degree <= 1:
        return np.array([[1 / 3, 1 / 3]]), np.array([0.5])
    if degree == 2:
        p = np.array([[1 / 6, 1 / 6], [2 / 3, 1 / 6], [1 / 6, 2 / 3]])
        return p, np.full(3, 1 / 6)
    # Strang-Fix / Dunavant 6-point rule, degree 4
    a, b = 0.445948490915965, 0.091576213509771
    wa, wb = 0.223381589678011, 0.109951743655322
    p = np.array([[a, a], [1 - 2 * a, a], [a, 1 - 2 * a], [b, b], [1 - 2 * b, b], [b, 1 - 2 * b]])
    return p, 0.5 * np.array([wa, wa, wa, wb, wb, wb])
