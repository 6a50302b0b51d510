"""Vectorized assembly of linear-elastic P1/P2 triangles (no Python loop over elements).

DOFs are interleaved: node i has ux at 2i and uy at 2i+1. Strain in Voigt form [exx, eyy, gxy].
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .elements import quadrature, shape, shape_grad
from .mesh import Mesh

if TYPE_CHECKING:
    import scipy.sparse as sp


@dataclass(frozen=True)
class Material:
    youngs_pa: float
    poisson: float


def elasticity_matrix(youngs_pa: float, poisson: float, plane: str = "strain") -> np.ndarray:
    """D such that [sxx, syy, sxy] = D [exx, eyy, gxy]."""
    E, nu = youngs_pa, poisson
    if plane == "strain":
        c = E / ((1 + nu) * (1 - 2 * nu))
        return c * np.array([[1 - nu, nu, 0], [nu, 1 - nu, 0], [0, 0, (1 - 2 * nu) / 2]])
    if plane == "stress":
        c = E / (1 - nu ** 2)
        return c * np.array([[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]])
    raise ValueError(f"plane must be 'strain' or 'stress', got {plane!r}")


def element_D(mesh: Mesh, materials: list[Material], plane: str) -> np.ndarray:
    """(M, 3, 3) elasticity matrix of each element, from its region's material."""
    Ds = np.array([elasticity_matrix(m.youngs_pa, m.poisson, plane) for m in materials])
    return Ds[mesh.region]


def gradients(mesh: Mesh, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Physical shape gradients (M, n, nen, 2) and Jacobian determinants (M, n) at reference points pts (n, 2)."""
    dN = shape_grad(mesh.order, pts)                       # (n, nen, 2)
    X = mesh.nodes[mesh.tris]                              # (M, nen, 2)
    J = np.einsum("mai,qaj->mqij", X, dN)                  # J[i, j] = dx_i / dxi_j
    det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
    if np.any(det <= 0):
        raise ValueError(f"{int((det <= 0).sum())} quadrature points with non-positive Jacobian: inverted elements")
    inv = np.empty_like(J)
    inv[..., 0, 0] = J[..., 1, 1] / det
    inv[..., 1, 1] = J[..., 0, 0] / det
    inv[..., 0, 1] = -J[..., 0, 1] / det
    inv[..., 1, 0] = -J[..., 1, 0] / det
    G = np.einsum("qaj,mqji->mqai", dN, inv)               # dN/dx_i
    return G, det


def strain_matrices(G: np.ndarray) -> np.ndarray:
    """B (..., 3, 2*nen) from physical gradients G (..., nen, 2), interleaved DOFs."""
    shp = G.shape[:-2]
    nen = G.shape[-2]
    B = np.zeros(shp + (3, 2 * nen))
    B[..., 0, 0::2] = G[..., 0]
    B[..., 1, 1::2] = G[..., 1]
    B[..., 2, 0::2] = G[..., 1]
    B[..., 2, 1::2] = G[..., 0]
    return B


def element_dofs(mesh: Mesh) -> np.ndarray:
    """(M, 2*nen) global DOF numbers of each element."""
    t = mesh.tris
    d = np.empty((len(t), 2 * t.shape[1]), dtype=np.int64)
    d[:, 0::2] = 2 * t
    d[:, 1::2] = 2 * t + 1
    return d


def stiffness(mesh: Mesh, D: np.ndarray, elements: np.ndarray | None = None) -> sp.csr_matrix:
    """Global stiffness matrix (2N x 2N, CSR) from per-element D (M, 3, 3); ``elements`` restricts the sum."""
    import scipy.sparse as sp
    pts, w = quadrature(2 * (mesh.order - 1))
    G, det = gradients(mesh, pts)
    B = strain_matrices(G)                                 # (M, q, 3, ne)
    Ke = np.einsum("mq,mqki,mkl,mqlj->mij", det * w, B, D, B, optimize=True)
    dofs = element_dofs(mesh)
    if elements is not None:
        Ke, dofs = Ke[elements], dofs[elements]
    ne = dofs.shape[1]
    rows = np.repeat(dofs, ne, axis=1).ravel()
    cols = np.tile(dofs, (1, ne)).ravel()
    n = mesh.n_dofs
    return sp.csr_matrix((Ke.ravel(), (rows, cols)), shape=(n, n))


def body_force(mesh: Mesh, f, degree: int = 6) -> np.ndarray:
    """Consistent nodal load of a body force f(x, y) -> (fx, fy) per unit volume (for verification)."""
    pts, w = quadrature(4)
    N = shape(mesh.order, pts)                             # (q, nen)
    _, det = gradients(mesh, pts)
    X = np.einsum("qa,mai->mqi", N, mesh.nodes[mesh.tris])
    fx, fy = f(X[..., 0], X[..., 1])
    F = np.zeros(mesh.n_dofs)
    dofs = element_dofs(mesh)
    np.add.at(F, dofs[:, 0::2], np.einsum("mq,qa->ma", det * w * fx, N))
    np.add.at(F, dofs[:, 1::2], np.einsum("mq,qa->ma", det * w * fy, N))
    return F
