"""Stress and strain recovery at nodes, as sparse linear operators on the displacement vector.

Each element evaluates its own strain at its nodes; a node takes the mean over the elements of its *primary*
region (tissue before stones), so a node on a stone's boundary reports the tissue-side stress, as the study plots
it. Building the operator only for the nodes asked for ("surface only") skips full-field recovery.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .assembly import element_dofs, gradients, strain_matrices
from .elements import nodes_ref
from .model import Model

if TYPE_CHECKING:
    import scipy.sparse as sp


def recovery_operator(model: Model, nodes: np.ndarray | None = None, strain: bool = False) -> sp.csr_matrix:
    """Sparse (3 n, 2N) operator: full displacement -> [sxx, syy, sxy] (or [exx, eyy, gxy]) at ``nodes``
    (all nodes when None), row 3 i + k for the i-th requested node."""
    import scipy.sparse as sp
    mesh = model.mesh
    nodes = np.arange(mesh.n_nodes) if nodes is None else np.asarray(nodes)
    primary = np.full(mesh.n_nodes, np.iinfo(np.int64).max)
    np.minimum.at(primary, mesh.tris.ravel(), np.repeat(mesh.region, mesh.tris.shape[1]))
    want = np.full(mesh.n_nodes, -1)
    want[nodes] = np.arange(len(nodes))
    # element-local node slots that are requested and belong to the node's primary region
    hit = (want[mesh.tris] >= 0) & (mesh.region[:, None] == primary[mesh.tris])
    els = np.flatnonzero(hit.any(axis=1))
    sub = type(mesh)(nodes=mesh.nodes, tris=mesh.tris[els], region=mesh.region[els], order=mesh.order,
                     width_m=mesh.width_m, height_m=mesh.height_m, top=mesh.top, bottom=mesh.bottom)
    G, _ = gradients(sub, nodes_ref(mesh.order))            # (m, nen, nen, 2): at each local node
    B = strain_matrices(G)                                  # (m, nen, 3, ne)
    if not strain:
        B = np.einsum("mkl,maln->makn", model.D[els], B)
    h = hit[els]                                            # (m, nen)
    count = np.zeros(mesh.n_nodes)
    np.add.at(count, mesh.tris[els][h], 1.0)
    row_node = want[mesh.tris[els]]                         # (m, nen)
    scale = np.where(h, 1.0 / np.maximum(count[mesh.tris[els]], 1), 0.0)
    dofs = element_dofs(mesh)[els]                          # (m, ne)
    m, nen, _, ne = B.shape
    rows = (3 * row_node[:, :, None, None] + np.arange(3)[None, None, :, None])
    rows = np.broadcast_to(rows, (m, nen, 3, ne))
    cols = np.broadcast_to(dofs[:, None, None, :], (m, nen, 3, ne))
    vals = B * scale[:, :, None, None]
    keep = np.broadcast_to(h[:, :, None, None], (m, nen, 3, ne))
    return sp.csr_matrix((vals[keep], (rows[keep], cols[keep])), shape=(3 * len(nodes), mesh.n_dofs))


def nodal_poisson(model: Model, nodes: np.ndarray) -> np.ndarray:
    """Poisson ratio of each node's primary region (for sigma_zz in plane strain)."""
    mesh = model.mesh
    primary = np.full(mesh.n_nodes, np.iinfo(np.int64).max)
    np.minimum.at(primary, mesh.tris.ravel(), np.repeat(mesh.region, mesh.tris.shape[1]))
    nu = np.array([m.poisson for m in model.materials])
    return nu[primary[nodes]]


def components(s3: np.ndarray, nu: np.ndarray, plane: str) -> dict[str, np.ndarray]:
    """From stacked [sxx, syy, sxy] (..., 3) to named components with szz and von Mises (Pa)."""
    sxx, syy, sxy = s3[..., 0], s3[..., 1], s3[..., 2]
    szz = nu * (sxx + syy) if plane == "strain" else np.zeros_like(sxx)
    vm = np.sqrt(0.5 * ((sxx - syy) ** 2 + (syy - szz) ** 2 + (szz - sxx) ** 2) + 3.0 * sxy ** 2)
    return {"sxx_pa": sxx, "syy_pa": syy, "sxy_pa": sxy, "szz_pa": szz, "von_mises_pa": vm}
