"""3D stress and strain recovery, as sparse linear operators on the displacement vector: at nodes, and at the
elements' stress points.

At nodes (fields for export and figures), as fem.stress in 2D: each element evaluates its own strain at its nodes;
a node takes the mean over the elements of its primary region (tissue before stones), so a node on a stone's surface
reports the tissue-side stress. At stress points (``point_operator3d``; the maximum von Mises under a tip): each
element's own stress at the four points of the degree-2 rule, where a quadratic tetrahedron's stress is most
accurate. Under a Hertz sphere the maximum over nodes came out +7 to +28 % above Hertz's at 2-6 surface elements per
contact radius (a P2 stress evaluated at vertices and averaged), the maximum over these points +1 to +12 % at 3 or
more (more for nu near 0.5, and mesh noise of several percent from one tip position to the next; docs/fem.md "3D
stresses under a round tip"). Components in the Voigt order of fem.assembly3d: [sxx, syy, szz, syz, sxz, sxy].
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .assembly3d import element_dofs3d, gradients3d, strain_matrices3d
from .elements3d import nodes_ref, quadrature, shape

CHUNK = 4000          # elements per block of the recovery operator's assembly
NAMES = ("sxx_pa", "syy_pa", "szz_pa", "syz_pa", "sxz_pa", "sxy_pa")


def primary_region(mesh) -> np.ndarray:
    """(N,) the lowest region number among each node's elements (0 = tissue wins on a stone's surface)."""
    primary = np.full(mesh.n_nodes, np.iinfo(np.int64).max)
    np.minimum.at(primary, mesh.tets.ravel(), np.repeat(mesh.region, mesh.tets.shape[1]))
    return primary


def _averaging(mesh, nodes: np.ndarray | None):
    """What nodal recovery averages over: (the nodes, each node's row or -1, (elements, local nodes) that count
    (the node asked for and the element in its primary region), the elements with any, each node's count)."""
    nodes = np.arange(mesh.n_nodes) if nodes is None else np.asarray(nodes)
    primary = primary_region(mesh)
    want = np.full(mesh.n_nodes, -1)
    want[nodes] = np.arange(len(nodes))
    hit = (want[mesh.tets] >= 0) & (mesh.region[:, None] == primary[mesh.tets])
    els = np.flatnonzero(hit.any(axis=1))
    count = np.zeros(mesh.n_nodes)
    np.add.at(count, mesh.tets[els][hit[els]], 1.0)
    return nodes, want, hit, els, count


def recovery_operator3d(model, nodes: np.ndarray | None = None, strain: bool = False) -> sp.csr_matrix:
    """Sparse (6 n, 3N) operator: full displacement -> the six stress (or strain) components at ``nodes`` (all
    nodes when None), row 6 i + k for the i-th requested node."""
    mesh = model.mesh
    nodes, want, hit, els, count = _averaging(mesh, nodes)
    shape = (6 * len(nodes), mesh.n_dofs)
    out = sp.csr_matrix(shape)
    for a in range(0, len(els), CHUNK):          # in blocks of elements: the triplets of all at once would take
        out = out + _block(model, els[a:a + CHUNK], hit, want, count, strain, shape)   # several times the result
    return out


def recover3d(model, u: np.ndarray, nodes: np.ndarray | None = None, strain: bool = False) -> np.ndarray:
    """(n, 6): ``recovery_operator3d(model, nodes, strain) @ u`` reshaped, to round-off, without building the
    operator (for one displacement vector: the operator's assembly, 1.1 s on block3d's top face, would be used once).
    Each element's strain at its nodes from its own displacements, then its stress, averaged over the elements of
    each node's primary region as the operator does."""
    mesh = model.mesh
    u = np.asarray(u, dtype=float).ravel()
    if u.shape != (mesh.n_dofs,):
        raise ValueError(f"a displacement vector of {mesh.n_dofs} entries, got {u.shape}")
    nodes, want, hit, els, count = _averaging(mesh, nodes)
    dofs = element_dofs3d(mesh)
    out = np.zeros((len(nodes), 6))
    for a in range(0, len(els), CHUNK):
        e = els[a:a + CHUNK]
        G, _ = gradients3d(mesh, nodes_ref(mesh.order), e)                               # (m, nen, nen, 3)
        eps = np.einsum("makn,mn->mak", strain_matrices3d(G), u[dofs[e]])               # (m, nen, 6)
        val = eps if strain else np.einsum("mkl,mal->mak", model.D[e], eps)
        h = hit[e]
        w = np.where(h, 1.0 / np.maximum(count[mesh.tets[e]], 1), 0.0)
        np.add.at(out, want[mesh.tets[e]][h], (val * w[:, :, None])[h])
    return out


def _block(model, els: np.ndarray, hit: np.ndarray, want: np.ndarray, count: np.ndarray, strain: bool,
           shape: tuple[int, int]) -> sp.csr_matrix:
    """The recovery operator's rows contributed by elements ``els`` (see recovery_operator3d)."""
    mesh = model.mesh
    G, _ = gradients3d(mesh, nodes_ref(mesh.order), els)       # (m, nen, nen, 3): at each local node
    B = strain_matrices3d(G)                                   # (m, nen, 6, ne)
    if not strain:
        B = np.einsum("mkl,maln->makn", model.D[els], B)
    h = hit[els]
    row_node = want[mesh.tets[els]]
    scale = np.where(h, 1.0 / np.maximum(count[mesh.tets[els]], 1), 0.0)
    dofs = element_dofs3d(mesh)[els]
    m, nen, _, ne = B.shape
    rows = np.broadcast_to(6 * row_node[:, :, None, None] + np.arange(6)[None, None, :, None], (m, nen, 6, ne))
    cols = np.broadcast_to(dofs[:, None, None, :], (m, nen, 6, ne))
    keep = np.broadcast_to(h[:, :, None, None], (m, nen, 6, ne))
    vals = B * scale[:, :, None, None]
    return sp.csr_matrix((vals[keep], (rows[keep], cols[keep])), shape=shape)


def stress_points() -> np.ndarray:
    """Reference coordinates (4, 3) of an element's stress points: the degree-2 rule's."""
    return quadrature(2)[0]


def point_operator3d(model, elements: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """(R, X): R sparse (6 n, 3N), full displacement -> the six stresses at the stress points of ``elements`` (n =
    4 per element, in element order; row 6 i + k), and X (n, 3) those points' positions, m."""
    mesh = model.mesh
    els = np.asarray(elements, dtype=np.int64)
    pts = stress_points()
    q = len(pts)
    X = np.einsum("qa,mai->mqi", shape(mesh.order, pts), mesh.nodes[mesh.tets[els]]).reshape(-1, 3)
    dofs = element_dofs3d(mesh)
    ne = dofs.shape[1]
    data, cols = [], []          # each row holds its element's ne DOFs once: the CSR arrays directly, in row order
    for a in range(0, len(els), CHUNK):
        e = els[a:a + CHUNK]
        G, _ = gradients3d(mesh, pts, e)                               # (m, q, nen, 3)
        B = np.einsum("mkl,mqln->mqkn", model.D[e], strain_matrices3d(G))   # (m, q, 6, ne)
        data.append(B.ravel())
        cols.append(np.broadcast_to(dofs[e][:, None, None, :], B.shape).ravel())
    n_rows = 6 * q * len(els)
    R = sp.csr_matrix((np.concatenate(data) if data else np.zeros(0),
                       np.concatenate(cols) if cols else np.zeros(0, dtype=np.int64),
                       np.arange(0, ne * n_rows + 1, ne)), shape=(n_rows, mesh.n_dofs))
    return R, X


def components3d(s6: np.ndarray) -> dict[str, np.ndarray]:
    """From stacked Voigt stresses (..., 6) to named components and von Mises (Pa)."""
    sxx, syy, szz, syz, sxz, sxy = (s6[..., k] for k in range(6))
    vm = np.sqrt(0.5 * ((sxx - syy) ** 2 + (syy - szz) ** 2 + (szz - sxx) ** 2) + 3.0 * (syz ** 2 + sxz ** 2 + sxy ** 2))
    out = {name: s6[..., k] for k, name in enumerate(NAMES)}
    out["von_mises_pa"] = vm
    return out
