"""The stress inside a stone treated as a rigid body (fem.model's RIGID_RATIO), in 2D and 3D.

A rigid body has no strain, so recovering its stress from the displacement (E_s eps) gives 0: the rigid model says
nothing about the stone's inside. The stiff stone's real stress is the rigid limit of its elastic one, and that limit
is well defined: the stone is in equilibrium under the forces the tissue puts on its boundary nodes, f = -(K_t u) on
the stone's nodes (K_t: the deformable elements' stiffness; no other load acts there), and for given boundary
forces the stress of a homogeneous elastic body does not depend on its modulus. So one pure-traction solve of the
stone's own elements, K_s v = f (its rigid motions pinned: f is self-equilibrated, because the rigid body's reduced
equations are P^T K u = 0), gives v, whose stress is the stone's (its strain is the stiff stone's, E_s / E_t times
smaller than the tissue's). Checked against the same stone solved elastic (tests/test_rigid_stress.py).

Before session 38 a rigid stone's nodes reported zero stress in load A's and load B's full fields (the VTU and the
figures), and the mixed formulation NaN, which refused its full field.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from .assembly import stiffness
from .stress import recovery_operator


def _primary(mesh) -> np.ndarray:
    """Per node: the lowest region of its elements (tissue before stones): the region whose stress it reports."""
    cells = mesh.tris if hasattr(mesh, "tris") else mesh.tets
    primary = np.full(mesh.n_nodes, np.iinfo(np.int64).max)
    np.minimum.at(primary, cells.ravel(), np.repeat(mesh.region, cells.shape[1]))
    return primary


def stone_fields(model, u: np.ndarray, stiffness: Callable, recovery: Callable, dim: int,
                 tissue_force: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """For the nodes whose primary region is a rigid stone: (nodes, stress rows, strain rows) as ``recovery(model,
    nodes, strain)`` returns them for a deformable stone ((n, 3) in 2D, (n, 6) in 3D), from the full displacement
    ``u``; None when the model has no rigid stone. ``stiffness(mesh, D, elements)``: the global stiffness of those
    elements (fem.assembly.stiffness, fem.assembly3d.stiffness3d). ``tissue_force``: the deformable elements'
    internal force at every full DOF when it is not K_t u (the mixed formulation's A u + B^T p)."""
    if not any(model.rigid):
        return None
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla
    mesh = model.mesh
    cells = mesh.tris if hasattr(mesh, "tris") else mesh.tets
    primary = _primary(mesh)
    rigid_regions = [k + 1 for k, r in enumerate(model.rigid) if r]
    deformable = np.flatnonzero(~np.isin(mesh.region, rigid_regions))
    out_nodes, out_s, out_e = [], [], []
    for reg in rigid_regions:
        els = np.flatnonzero(mesh.region == reg)
        nodes = np.unique(cells[els])
        dofs = (dim * nodes[:, None] + np.arange(dim)).ravel()
        # the tissue's force on the stone's nodes: only the deformable elements touching them contribute
        if tissue_force is None:
            touching = deformable[np.isin(cells[deformable], nodes).any(axis=1)]
            f = -(stiffness(mesh, model.D, touching) @ u)[dofs]
        else:
            f = -tissue_force[dofs]
        Ks = stiffness(mesh, model.D, els)[dofs][:, dofs]
        # pin the rigid motions: node a entirely (the translations); b, the farthest along x, in y (and z: the
        # rotations about z and y); in 3D c, the farthest from a along y, in z (the rotation about x)
        x = mesh.nodes[nodes]
        a = int(np.argmin(x[:, 0]))
        b = int(np.argmax(x[:, 0]))
        pins = [dim * a + i for i in range(dim)] + [dim * b + 1]
        if dim == 3:
            c = int(np.argmax(np.abs(x[:, 1] - x[a, 1])))
            pins += [dim * b + 2, dim * c + 2]
        free = np.setdiff1d(np.arange(len(dofs)), pins)
        v = np.zeros(len(dofs))
        v[free] = sla.spsolve(sp.csc_matrix(Ks[free][:, free]), f[free])
        vf = np.zeros(mesh.n_dofs)
        vf[dofs] = v
        own = nodes[primary[nodes] == reg]
        out_nodes.append(own)
        out_s.append(np.asarray(recovery(model, own, False) @ vf).reshape(len(own), -1))
        out_e.append(np.asarray(recovery(model, own, True) @ vf).reshape(len(own), -1))
    return np.concatenate(out_nodes), np.concatenate(out_s), np.concatenate(out_e)


def with_stone_fields(model, u: np.ndarray, stress: np.ndarray, strain: np.ndarray, stiffness: Callable,
                      recovery: Callable, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """All nodes' (stress, strain) rows with a rigid stone's own nodes taken from ``stone_fields`` (copies)."""
    got = stone_fields(model, u, stiffness, recovery, dim)
    if got is None:
        return stress, strain
    nodes, s, e = got
    stress, strain = stress.copy(), strain.copy()
    stress[nodes], strain[nodes] = s, e
    return stress, strain


def nodal_fields(model, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A 2D model's (n_nodes, 3) stress [sxx, syy, sxy] and strain [exx, eyy, gxy] at every node, a rigid stone's
    nodes included (fem.stress's recovery elsewhere)."""
    return with_stone_fields(model, u, (recovery_operator(model) @ u).reshape(-1, 3),
                             (recovery_operator(model, strain=True) @ u).reshape(-1, 3), stiffness,
                             recovery_operator, 2)
