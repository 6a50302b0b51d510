"""Vectorized assembly of linear-elastic P1/P2 tetrahedra (no Python loop over elements).

DOFs are interleaved: node i has ux at 3i, uy at 3i+1, uz at 3i+2. Strain in Voigt form
[exx, eyy, ezz, gyz, gxz, gxy] (engineering shears).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .assembly import Material
from .elements3d import EDGES, quadrature, shape, shape_grad
from .mesh3d import Mesh3D


def elasticity_matrix3d(youngs_pa: float, poisson: float) -> np.ndarray:
    """D (6, 6) such that sigma = D eps in the Voigt order above (isotropic)."""
    E, nu = youngs_pa, poisson
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    mu = E / (2 * (1 + nu))
    D = np.zeros((6, 6))
    D[:3, :3] = lam
    D[[0, 1, 2], [0, 1, 2]] += 2 * mu
    D[[3, 4, 5], [3, 4, 5]] = mu
    return D


def element_D3d(mesh: Mesh3D, materials: list[Material]) -> np.ndarray:
    """(M, 6, 6) elasticity matrix of each element, from its region's material."""
    Ds = np.array([elasticity_matrix3d(m.youngs_pa, m.poisson) for m in materials])
    return Ds[mesh.region]


def gradients3d(mesh: Mesh3D, pts: np.ndarray, elements: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Physical shape gradients (M, n, nen, 3) and Jacobian determinants (M, n) at reference points pts (n, 3)."""
    dN = shape_grad(mesh.order, pts)                           # (n, nen, 3)
    tets = mesh.tets if elements is None else mesh.tets[elements]
    J = np.einsum("mai,qaj->mqij", mesh.nodes[tets], dN)       # J[i, j] = dx_i / dxi_j
    det = np.linalg.det(J)
    if np.any(det <= 0):
        raise ValueError(f"{int((det <= 0).sum())} quadrature points with non-positive Jacobian: inverted elements")
    inv = np.linalg.inv(J)
    G = np.einsum("qaj,mqji->mqai", dN, inv)                   # dN/dx_i
    return G, det


def strain_matrices3d(G: np.ndarray) -> np.ndarray:
    """B (..., 6, 3*nen) from physical gradients G (..., nen, 3), interleaved DOFs."""
    shp, nen = G.shape[:-2], G.shape[-2]
    B = np.zeros(shp + (6, 3 * nen))
    gx, gy, gz = G[..., 0], G[..., 1], G[..., 2]
    B[..., 0, 0::3] = gx
    B[..., 1, 1::3] = gy
    B[..., 2, 2::3] = gz
    B[..., 3, 1::3] = gz
    B[..., 3, 2::3] = gy
    B[..., 4, 0::3] = gz
    B[..., 4, 2::3] = gx
    B[..., 5, 0::3] = gy
    B[..., 5, 1::3] = gx
    return B


def element_dofs3d(mesh: Mesh3D) -> np.ndarray:
    """(M, 3*nen) global DOF numbers of each element."""
    t = mesh.tets
    d = np.empty((len(t), 3 * t.shape[1]), dtype=np.int64)
    for k in range(3):
        d[:, k::3] = 3 * t + k
    return d


CHUNK = 20_000   # elements per vectorized block (bounds the temporary arrays to a few hundred MB for P2)


def curved(mesh: Mesh3D) -> np.ndarray:
    """(M,) bool: P2 elements whose mid-edge nodes are off their edges' midpoints (on a stone's sphere)."""
    if mesh.order == 1:
        return np.zeros(len(mesh.tets), bool)
    X = mesh.nodes
    off = np.zeros(len(mesh.tets))
    for k, (a, b) in enumerate(EDGES):
        dev = X[mesh.tets[:, 4 + k]] - 0.5 * (X[mesh.tets[:, a]] + X[mesh.tets[:, b]])
        off = np.maximum(off, np.abs(dev).max(axis=1))
    return off > 1e-9 * max(mesh.width_m, mesh.length_m, mesh.height_m)


def stiffness3d(mesh: Mesh3D, D: np.ndarray, elements: np.ndarray | None = None) -> sp.csr_matrix:
    """Global stiffness matrix (3N x 3N, CSR) from per-element D (M, 6, 6); ``elements`` restricts the sum.
    Straight elements: the rule exact for their integrand (degree 2 (p - 1)); curved P2 elements (on a sphere) a
    degree-5 rule: their Jacobian's cofactors are quadratic, so the constant-strain (patch) test needs degree 3."""
    els = np.arange(len(mesh.tets)) if elements is None else np.asarray(elements)
    bent = curved(mesh)[els]
    K = _stiffness(mesh, D, els[~bent], quadrature(2 * (mesh.order - 1)))
    if bent.any():
        K = K + _stiffness(mesh, D, els[bent], quadrature(5))
    return K


def _stiffness(mesh: Mesh3D, D: np.ndarray, els: np.ndarray, rule) -> sp.csr_matrix:
    pts, w = rule
    dofs_all = element_dofs3d(mesh)
    n = mesh.n_dofs
    K = sp.csr_matrix((n, n))
    for start in range(0, len(els), CHUNK):
        e = els[start:start + CHUNK]
        G, det = gradients3d(mesh, pts, e)
        B = strain_matrices3d(G)                               # (m, q, 6, ne)
        DB = np.einsum("mkl,mqlj->mqkj", D[e], B)
        Ke = np.einsum("mq,mqki,mqkj->mij", det * w, B, DB, optimize=True)
        dofs = dofs_all[e]
        ne = dofs.shape[1]
        rows = np.repeat(dofs, ne, axis=1).ravel()
        cols = np.tile(dofs, (1, ne)).ravel()
        K = K + sp.csr_matrix((Ke.ravel(), (rows, cols)), shape=(n, n))
    return K


def body_force3d(mesh: Mesh3D, f) -> np.ndarray:
    """Consistent nodal load of a body force f(x, y, z) -> (fx, fy, fz) per unit volume (for verification)."""
    pts, w = quadrature(4)
    N = shape(mesh.order, pts)                                 # (q, nen)
    _, det = gradients3d(mesh, pts)
    X = np.einsum("qa,mai->mqi", N, mesh.nodes[mesh.tets])
    fs = f(X[..., 0], X[..., 1], X[..., 2])
    F = np.zeros(mesh.n_dofs)
    dofs = element_dofs3d(mesh)
    for k in range(3):
        np.add.at(F, dofs[:, k::3], np.einsum("mq,qa->ma", det * w * fs[k], N))
    return F
