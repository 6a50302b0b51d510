"""One 3D scene's discretization: tetrahedral mesh, materials, stiffness and stones reduced to rigid bodies.

As in 2D (fem.model): a stone E_s >= RIGID_RATIO E_t is replaced by a rigid body tied to the tissue, here with 6
DOFs (a translation t and a small rotation w about its centre c: u(x) = t + w x (x - c)). Its elements leave the
stiffness and its nodes' DOFs are expressed by P. The model has the 2D Model's interface (K, P, n_dofs,
reduced_index, partition), so fem.model.Factored factorizes both (CHOLMOD here).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from .assembly import Material
from .assembly3d import element_D3d, stiffness3d
from .condense import factorize_spd
from .mesh3d import Mesh3D
from .model import (
    RIGID_RATIO,
    Factored,
    deformable_elements,
    materials_of,
    warn_if_ill_conditioned,
    warn_if_locking,
)
from .scene_mesh3d import mesh_for3d


@dataclass
class Model3D:
    mesh: Mesh3D
    materials: list[Material]                   # region 0 tissue, region k stone k-1
    centres: list[tuple[float, float, float]]   # stone centres (x, y, z)
    rigid: list[bool]                           # per stone
    D: np.ndarray = field(init=False)           # (M, 6, 6)
    P: sp.csr_matrix = field(init=False)        # full DOFs = P @ reduced DOFs

    dim = 3

    def __post_init__(self):
        self.D = element_D3d(self.mesh, self.materials)
        self.P = self._prolongation()

    @functools.cached_property
    def K(self) -> sp.csc_matrix:
        """The reduced stiffness (n_red x n_red), assembled on first use: stresses from a stored factor and
        compliance need D and P only."""
        el = deformable_elements(self.mesh.region, self.rigid)
        Kfull = stiffness3d(self.mesh, self.D, elements=None if len(el) == len(self.mesh.region) else el)
        return (self.P.T @ Kfull @ self.P).tocsc() if any(self.rigid) else Kfull.tocsc()

    def _owner(self) -> np.ndarray:
        """(N,) the rigid stone each node moves with (its elements' nodes, boundary included), -1 for the rest."""
        owner = np.full(self.mesh.n_nodes, -1)
        for k, r in enumerate(self.rigid):
            if r:
                owner[np.unique(self.mesh.tets[self.mesh.region == k + 1])] = k
        return owner

    @property
    def n_dofs(self) -> int:
        return self.P.shape[1]

    def reduced_index(self, full_dofs: np.ndarray) -> np.ndarray:
        """Reduced DOF numbers of full DOFs that belong to deformable nodes (identity rows of P)."""
        if not any(self.rigid):
            return np.asarray(full_dofs)
        P = self.P[np.asarray(full_dofs)]
        if np.any(np.diff(P.indptr) != 1) or np.any(P.data != 1.0):
            raise ValueError("a requested DOF belongs to a rigid stone")
        return P.indices.copy()

    def _prolongation(self) -> sp.csr_matrix:
        n = self.mesh.n_dofs
        if not any(self.rigid):
            return sp.identity(n, format="csr")
        owner = self._owner()
        free_nodes = np.flatnonzero(owner < 0)
        n_free = 3 * len(free_nodes)
        rows, cols, vals = [], [], []
        for c in range(3):
            rows.append(3 * free_nodes + c)
            cols.append(np.arange(c, n_free, 3))
            vals.append(np.ones(len(free_nodes)))
        for i, k in enumerate(k for k, r in enumerate(self.rigid) if r):
            nodes = np.flatnonzero(owner == k)
            r = self.mesh.nodes[nodes] - np.asarray(self.centres[k])
            col = n_free + 6 * i
            one = np.ones(len(nodes))
            # u = t + w x r:  ux = tx + wy rz - wz ry,  uy = ty + wz rx - wx rz,  uz = tz + wx ry - wy rx
            terms = ((0, 0, one), (0, 4, r[:, 2]), (0, 5, -r[:, 1]),
                     (1, 1, one), (1, 5, r[:, 0]), (1, 3, -r[:, 2]),
                     (2, 2, one), (2, 3, r[:, 1]), (2, 4, -r[:, 0]))
            for comp, j, v in terms:
                rows.append(3 * nodes + comp)
                cols.append(np.full(len(nodes), col + j))
                vals.append(v)
        rows, cols, vals = (np.concatenate(a) for a in (rows, cols, vals))
        return sp.csr_matrix((vals, (rows, cols.astype(np.int64))), shape=(n, n_free + 6 * sum(self.rigid)))

    def partition(self, fixed: np.ndarray) -> Factored:
        """Factor the stiffness with the given reduced DOFs fixed: CHOLMOD (fem.condense.factorize_spd); SuperLU
        fills 3D P2 models in several times more and takes minutes on block3d."""
        return Factored(self, np.asarray(fixed, dtype=np.int64), factorize=factorize_spd)


def build_model3d(scene, mesh: Mesh3D | None = None, rigid_stones: str | bool = "auto",
                  use_cache: bool | None = None) -> Model3D:
    """Discretize a 3D scene. rigid_stones: "auto" (rigid when E_stone >= RIGID_RATIO * E_tissue), True, False."""
    if mesh is None:
        mesh = mesh_for3d(scene, use=use_cache)
    t = scene.tissue
    warn_if_locking(scene)
    if rigid_stones == "auto":
        rigid = [s.youngs_pa >= RIGID_RATIO * t.youngs_pa for s in scene.stones]
    else:
        rigid = [bool(rigid_stones)] * len(scene.stones)
    warn_if_ill_conditioned(scene, rigid)
    centres = [(s.x_m, s.y_m, t.height_m - s.depth_m) for s in scene.stones]
    return Model3D(mesh=mesh, materials=materials_of(scene), centres=centres, rigid=rigid)


def fixed_bottom(model: Model3D) -> np.ndarray:
    """Reduced DOFs held on the bottom face: u_z = 0 everywhere, and the rigid-body modes left (x, y translation,
    rotation about z) removed minimally: u_x = u_y = 0 at the bottom node nearest the origin, u_y = 0 at the bottom
    node nearest (width, 0). A uniform lateral expansion u = (a x, a y, .) satisfies both."""
    mesh = model.mesh
    b = mesh.bottom
    xy = mesh.nodes[b, :2]
    n0 = b[np.argmin(np.hypot(xy[:, 0], xy[:, 1]))]
    n1 = b[np.argmin(np.hypot(xy[:, 0] - mesh.width_m, xy[:, 1]))]
    return model.reduced_index(np.concatenate([3 * b + 2, [3 * n0, 3 * n0 + 1, 3 * n1 + 1]]))
