"""One scene's discretization: mesh, materials, stiffness, and (optionally) stones reduced to rigid bodies.

Rigid stones ("skip what a scene doesn't need"): a stone E_s times stiffer than tissue deforms E_t/E_s as much as
the tissue around it (5e-7 for the study's kidney stone). Replacing it by a rigid body tied to the tissue (3 DOFs:
two translations and a rotation about its centre) removes its DOFs and the 2e6 stiffness contrast from the linear
system. The solution differs from the elastic stone's by O(E_t/E_s); tests and the bench measure it.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from .assembly import Material, element_D, stiffness
from .mesh import Mesh
from .scene_mesh import mesh_for

if TYPE_CHECKING:
    import scipy.sparse as sp

RIGID_RATIO = 1.0e4   # a stone at least this much stiffer than tissue is made rigid when rigid_stones="auto"


def deformable_elements(region: np.ndarray, rigid: list[bool]) -> np.ndarray:
    """The elements that deform (indices): all but a rigid stone's (stone k is region k + 1)."""
    keep = np.ones(len(region), bool)
    for k, r in enumerate(rigid):
        if r:
            keep &= region != k + 1
    return np.flatnonzero(keep)


@dataclass
class Model:
    mesh: Mesh
    materials: list[Material]            # region 0 tissue, region k stone k-1
    plane: str
    centres: list[tuple[float, float]]   # stone centres (x, y)
    rigid: list[bool]                    # per stone

    # D, K and P are made on first use (and scipy imported then): a model whose surface operators come from the
    # disk cache needs none of them to predict forces and stresses (issue 19: start-up).
    @cached_property
    def D(self) -> np.ndarray:
        """(M, 3, 3) elasticity matrices."""
        return element_D(self.mesh, self.materials, self.plane)

    @cached_property
    def K(self) -> sp.csc_matrix:
        """Reduced stiffness (n_red x n_red)."""
        el = deformable_elements(self.mesh.region, self.rigid)
        Kfull = stiffness(self.mesh, self.D, elements=None if len(el) == len(self.mesh.region) else el)
        return (self.P.T @ Kfull @ self.P).tocsc() if any(self.rigid) else Kfull.tocsc()

    @cached_property
    def P(self) -> sp.csr_matrix:
        """Full DOFs = P @ reduced DOFs."""
        return self._prolongation()

    @cached_property
    def _owner(self) -> np.ndarray:
        """Per node: the rigid stone it moves with, -1 for a deformable node."""
        owner = np.full(self.mesh.n_nodes, -1)
        for k, r in enumerate(self.rigid):
            if r:
                owner[self.mesh.tris[self.mesh.region == k + 1].ravel()] = k   # (np.unique would load numpy.ma)
        return owner

    def _prolongation(self) -> sp.csr_matrix:
        import scipy.sparse as sp
        n = self.mesh.n_dofs
        if not any(self.rigid):
            return sp.identity(n, format="csr")
        owner = self._owner
        free_nodes = np.flatnonzero(owner < 0)
        n_free = 2 * len(free_nodes)
        rigid_ids = [k for k, r in enumerate(self.rigid) if r]
        col_of = {k: n_free + 3 * i for i, k in enumerate(rigid_ids)}
        rows, cols, vals = [], [], []
        rows += [2 * free_nodes, 2 * free_nodes + 1]
        cols += [np.arange(0, n_free, 2), np.arange(1, n_free, 2)]
        vals += [np.ones(len(free_nodes))] * 2
        for k in rigid_ids:
            nodes = np.flatnonzero(owner == k)
            xc, yc = self.centres[k]
            c = col_of[k]
            x, y = self.mesh.nodes[nodes, 0] - xc, self.mesh.nodes[nodes, 1] - yc
            one = np.ones(len(nodes))
            rows += [2 * nodes, 2 * nodes, 2 * nodes + 1, 2 * nodes + 1]
            cols += [c + 0 * one, c + 2 + 0 * one, c + 1 + 0 * one, c + 2 + 0 * one]
            vals += [one, -y, one, x]
        rows, cols, vals = (np.concatenate(a) for a in (rows, cols, vals))
        return sp.csr_matrix((vals, (rows, cols.astype(np.int64))), shape=(n, n_free + 3 * len(rigid_ids)))

    @property
    def n_dofs(self) -> int:
        """Reduced DOFs: two per deformable node (in node order), then three per rigid stone (as P numbers them)."""
        if not any(self.rigid):
            return self.mesh.n_dofs
        return 2 * int((self._owner < 0).sum()) + 3 * sum(self.rigid)

    def reduced_index(self, full_dofs: np.ndarray) -> np.ndarray:
        """Reduced DOF numbers of full DOFs that belong to deformable nodes (identity rows of P)."""
        full_dofs = np.asarray(full_dofs)
        if not any(self.rigid):
            return full_dofs
        node, comp = np.divmod(full_dofs, 2)
        if np.any(self._owner[node] >= 0):
            raise ValueError("a requested DOF belongs to a rigid stone")
        rank = np.cumsum(self._owner < 0) - 1                 # deformable nodes numbered in node order
        return 2 * rank[node] + comp

    def partition(self, fixed: np.ndarray) -> Factored:
        """Factor the stiffness with the given reduced DOFs fixed (their values are supplied at solve time)."""
        return Factored(self, np.asarray(fixed, dtype=np.int64))


class Factored:
    """K_ff factorized once; solves for any prescribed values on the fixed DOFs and any load on the free DOFs."""

    def __init__(self, model: Model, fixed: np.ndarray, factorize=None):
        """factorize(K_ff) -> an object with ``solve(rhs)`` (default: SuperLU with a symmetric ordering; the 3D
        model passes CHOLMOD, fem.condense.factorize_spd)."""
        self.model = model
        n = model.n_dofs
        self.fixed = np.unique(fixed)
        mask = np.ones(n, bool)
        mask[self.fixed] = False
        self.free = np.flatnonzero(mask)
        import scipy.sparse.linalg as spla
        K = model.K
        Kff = K[self.free][:, self.free].tocsc()
        self.Kfp = K[self.free][:, self.fixed].tocsc()
        if factorize is not None:
            self.lu = factorize(Kff)
        else:   # symmetric fill-reducing ordering: K_ff is SPD, so no pivoting is needed
            self.lu = spla.splu(Kff, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                options={"SymmetricMode": True})

    def solve(self, prescribed: np.ndarray | None = None, load: np.ndarray | None = None) -> np.ndarray:
        """Reduced displacement vector (n_red,) for fixed values ``prescribed`` and a reduced load vector."""
        n = self.model.n_dofs
        rhs = np.zeros(len(self.free)) if load is None else np.array(load, dtype=float)[self.free]
        u = np.zeros(n)
        if prescribed is not None:
            u[self.fixed] = prescribed
            rhs = rhs - self.Kfp @ prescribed
        u[self.free] = self.lu.solve(rhs)
        return u

    def full(self, u_red: np.ndarray) -> np.ndarray:
        return self.model.P @ u_red


NU_WARN = 0.49   # tissue Poisson ratio above which the displacement formulation warns (volumetric locking)


def warn_if_locking(scene) -> None:
    """Volumetric locking: with nu -> 0.5 displacement elements over-stiffen (P1 badly, P2 in its stresses). The
    warning states only this scene's figures (its Poisson ratio and bulk-to-shear ratio); the error they cause
    depends on the scene (bench/bench_runtime_error.py --locking measures it on the paper scene)."""
    nu = scene.tissue.poisson
    if nu > NU_WARN and getattr(scene.analysis, "formulation", "displacement") == "displacement":
        bulk_to_shear = 2 * (1 + nu) / (3 * (1 - 2 * nu))
        if getattr(scene, "is_3d", False):
            advice = ("3D has the displacement form only: refine (analysis.mesh_size_m, analysis.surface_refine) and "
                      "compare two meshes")
        else:
            advice = ("for load A set [analysis] formulation = \"mixed\" (Taylor-Hood P2/P1); the contact model "
                      "(load B) has the displacement form only: its force converges, its nodal contact pressure "
                      "oscillates (refine analysis.surface_refine)")
        warnings.warn(f"scene {scene.name!r}: tissue poisson = {nu} > {NU_WARN} with the displacement formulation "
                      f"(P{scene.analysis.order}): volumetric locking (bulk modulus {bulk_to_shear:.3g} times the "
                      f"shear modulus) makes stresses untrustworthy; {advice}", stacklevel=3)


ELASTIC_RATIO_WARN = 1.0e8   # an elastic (not rigid) stone stiffer than this loses accuracy to round-off


def warn_if_ill_conditioned(scene, rigid: list[bool]) -> None:
    """An elastic stone E_s/E_t > 1e8 times stiffer than tissue: the sparse solve loses digits (how many depends on
    the scene and mesh; bench/bench_runtime_error.py measures it), while the rigid-body reduction is exact to
    O(E_t/E_s). The warning states only this scene's figures."""
    t = scene.tissue
    for i, (s, r) in enumerate(zip(scene.stones, rigid)):
        ratio = s.youngs_pa / t.youngs_pa
        if not r and ratio > ELASTIC_RATIO_WARN:
            warnings.warn(f"scene {scene.name!r}: stone[{i}] is {ratio:.1e} times stiffer than tissue and meshed "
                          f"elastic: round-off in the solve grows with the ratio; use rigid_stones='auto' (rigid "
                          f"body, exact to {t.youngs_pa / s.youngs_pa:.0e})", stacklevel=3)


def materials_of(scene) -> list[Material]:
    t = scene.tissue
    return [Material(t.youngs_pa, t.poisson)] + [Material(s.youngs_pa, s.poisson) for s in scene.stones]


def build_model(scene, mesh: Mesh | None = None, rigid_stones: str | bool = "auto") -> Model:
    """Discretize a scene. rigid_stones: "auto" (rigid when E_stone >= RIGID_RATIO * E_tissue), True, False."""
    if mesh is None:
        mesh = mesh_for(scene)           # from the disk cache; meshed with gmsh on a miss
    t = scene.tissue
    warn_if_locking(scene)
    if rigid_stones == "auto":
        rigid = [s.youngs_pa >= RIGID_RATIO * t.youngs_pa for s in scene.stones]
    else:
        rigid = [bool(rigid_stones)] * len(scene.stones)
    warn_if_ill_conditioned(scene, rigid)
    centres = [(s.x_m, t.height_m - s.depth_m) for s in scene.stones]
    return Model(mesh=mesh, materials=materials_of(scene), plane=scene.analysis.plane, centres=centres, rigid=rigid)
