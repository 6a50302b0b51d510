"""An elastic spherical tip in 3D: its lower half meshed once, its surface's vertical compliance condensed once.

The tip is the lower half of a ball of radius R (P1 or P2 tetrahedra, as the scene's ``analysis.order``), gripped
along its flat equatorial face by the holder (every DOF held there), made of the indenter's ``youngs_pa`` and
``poisson``. Its spherical surface's vertical DOFs are condensed (fem.condense.schur: the same Schur-complement path
as the tissue's patch), giving C_tip: the upward displacement of each surface node per unit upward force on each.

At a waypoint the contact forces act between the tissue's patch nodes and the tip at the nodes' horizontal
positions relative to the tip axis; a piecewise-linear interpolation over the Delaunay triangulation of the surface
nodes' horizontal projections (the lower half-sphere is a graph over its disk) carries the forces to the tip's
nodes and the tip's displacements back, so the tip adds  Phi C_tip Phi^T  to the tissue compliance in the contact
LCP (as fem.tip does for a 2D cylinder). The gap stays vertical (small strain, small slope, as for the rigid tip).

What this does not model: friction, the tip's own finite strain, the holder's compliance beyond the gripped face.
Checked (tests/test_tip3d.py): the tip alone pressed on a rigid flat against Hertz's sphere on a rigid plane, the
tip on a tissue block of the same material against Hertz's combined modulus (force half the rigid tip's), a stiff
tip against the rigid one within the Hertz bound ``fem.tip.rigid_tip_bound``.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import Delaunay

from . import diskcache
from .assembly import Material
from .assembly3d import element_D3d, stiffness3d
from .condense import schur
from .mesh import _GMSH_LOCK, _start
from .mesh3d import Mesh3D, _extract
from .scene_mesh3d import code_version3d

FINE_TIP_FRACTION = 0.05    # element size at the tip's lowest point, in tip radii
COARSE_TIP_FRACTION = 0.25  # element size at its gripped face, in tip radii
TIP_GRADE = 0.25            # growth of the element size per unit distance from the lowest point


def mesh_tip3d(radius_m: float, order: int = 2, fine_m: float | None = None) -> Mesh3D:
    """The lower half of a ball of radius_m: its lowest point at the origin, its flat face at z = radius_m (the
    mesh's ``top``, where the holder grips it). Element size ``fine_m`` (default R * FINE_TIP_FRACTION) at the lowest
    point, growing with slope TIP_GRADE to R * COARSE_TIP_FRACTION."""
    import gmsh  # lazy: a heavy import, only needed on a cache miss
    R = radius_m
    fine = FINE_TIP_FRACTION * R if fine_m is None else fine_m
    coarse = max(COARSE_TIP_FRACTION * R, fine)
    with _GMSH_LOCK:
        _start(gmsh)
        try:
            occ = gmsh.model.occ
            ball = occ.addSphere(0.0, 0.0, R, R, angle1=-math.pi / 2, angle2=0.0)
            occ.synchronize()
            f = gmsh.model.mesh.field
            me = f.add("MathEval")
            f.setString(me, "F", f"Min({coarse}, {fine} + {TIP_GRADE} * Sqrt(x^2 + y^2 + z^2))")
            f.setAsBackgroundMesh(me)
            gmsh.option.setNumber("Mesh.MeshSizeMax", coarse)
            gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
            gmsh.option.setNumber("Mesh.Algorithm", 6)
            gmsh.option.setNumber("Mesh.Algorithm3D", 10)
            gmsh.model.mesh.generate(3)
            if order == 2:
                gmsh.model.mesh.setOrder(2)
            return _extract(gmsh, [[ball]], order, 2 * R, 2 * R, R)
        finally:
            gmsh.finalize()


def surface_nodes(mesh: Mesh3D, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(the nodes on the tip's spherical surface below its gripped face, those on its gripped rim)."""
    R = radius_m
    p = mesh.nodes
    on = np.abs(np.sqrt(p[:, 0] ** 2 + p[:, 1] ** 2 + (p[:, 2] - R) ** 2) - R) < 1e-6 * R
    below = p[:, 2] < R * (1 - 1e-9)
    return np.flatnonzero(on & below), np.flatnonzero(on & ~below)


@dataclass
class TipCompliance3D:
    """The condensed vertical compliance of an elastic spherical tip's surface (``build``), or restored."""
    C: np.ndarray     # (n, n) upward displacement per upward force on the surface nodes (zero on the gripped rim)
    xy: np.ndarray    # (n, 2) the surface and rim nodes' horizontal positions relative to the tip axis
    radius_m: float

    def __post_init__(self):
        self._tri = Delaunay(self.xy)

    @classmethod
    def build(cls, indenter, order: int = 2, fine_m: float | None = None) -> TipCompliance3D:
        """Mesh the tip (``mesh_tip3d``), assemble it and condense its surface's vertical DOFs."""
        if indenter.shape != "sphere" or indenter.youngs_pa is None:
            raise ValueError("an elastic 3D tip is a 'sphere' with a youngs_pa")
        R = indenter.radius_m
        if indenter.poisson > 0.49:
            warnings.warn(f"indenter.poisson = {indenter.poisson:g}: the tip's displacement-based elements lock near "
                          f"0.5 (its compliance comes out low; not measured for the tip)", stacklevel=2)
        mesh = mesh_tip3d(R, order=order, fine_m=fine_m)
        K = stiffness3d(mesh, element_D3d(mesh, [Material(indenter.youngs_pa, indenter.poisson)])).tocsc()
        grip = mesh.top
        fixed = np.concatenate([3 * grip, 3 * grip + 1, 3 * grip + 2])
        free = np.setdiff1d(np.arange(mesh.n_dofs), fixed)
        surf, rim = surface_nodes(mesh, R)
        n = len(surf)
        C = np.zeros((n + len(rim), n + len(rim)))      # the gripped rim does not move: its rows stay zero, and the
        C[:n, :n] = schur(K, free, 3 * surf + 2).compliance     # interpolation reaches the tip's whole disk
        return cls(C=0.5 * (C + C.T), xy=mesh.nodes[np.concatenate([surf, rim]), :2].copy(), radius_m=R)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"C": self.C, "xy": self.xy, "radius_m": np.float64(self.radius_m)}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> TipCompliance3D:
        """The tip ``to_arrays`` wrote; ValueError if the arrays do not fit together."""
        C, xy = np.asarray(arrays["C"]), np.asarray(arrays["xy"])
        if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) < 4 or C.shape != (len(xy), len(xy)) \
                or not np.all(np.isfinite(C)):
            raise ValueError(f"tip compliance of shape {C.shape} for surface nodes of shape {xy.shape}")
        return cls(C=np.array(C), xy=np.array(xy), radius_m=float(arrays["radius_m"]))

    def interpolation(self, rel_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The piecewise-linear interpolation from the surface nodes to horizontal positions relative to the tip
        axis (within the tip's radius; a point a rounding error outside takes its nearest node's triangle): for each
        position, the three surface nodes of its triangle (m, 3) and their weights (m, 3)."""
        rel_xy = np.atleast_2d(np.asarray(rel_xy, dtype=float))
        tri = self._tri
        simplex = tri.find_simplex(rel_xy, tol=1e-9)
        out = simplex < 0
        if out.any():
            near = np.argmin(((rel_xy[out, None, :] - self.xy[None]) ** 2).sum(-1), axis=1)
            simplex[out] = tri.vertex_to_simplex[near]
        T = tri.transform[simplex]
        b = np.einsum("kij,kj->ki", T[:, :2], rel_xy - T[:, 2])
        w = np.column_stack([b, 1 - b.sum(1)])
        if out.any():
            w[out] = np.clip(w[out], 0.0, None)
            w[out] /= w[out].sum(1, keepdims=True)
        return tri.simplices[simplex], w

    def interpolation_matrix(self, rel_xy: np.ndarray) -> np.ndarray:
        """Phi (m, n): the interpolation as a dense matrix (for checks; ``compliance`` does not form it)."""
        v, w = self.interpolation(rel_xy)
        Phi = np.zeros((len(v), len(self.xy)))
        np.add.at(Phi, (np.repeat(np.arange(len(v)), 3), v.ravel()), w.ravel())
        return Phi

    def compliance(self, rel_xy: np.ndarray, cols: np.ndarray | None = None) -> np.ndarray:
        """Phi C_tip Phi^T at horizontal positions relative to the tip axis (the tip's share of the gap); with
        ``cols`` (positions too) the block Phi_rows C_tip Phi_cols^T."""
        return self.window(rel_xy).block(None, None) if cols is None else \
            _block(self.sparse_interpolation(rel_xy), self.C, self.sparse_interpolation(cols))

    def sparse_interpolation(self, rel_xy: np.ndarray):
        """Phi (m, n) as a scipy CSR matrix (three entries a row)."""
        v, w = self.interpolation(rel_xy)
        return sp.csr_matrix((w.ravel(), v.ravel(), np.arange(0, 3 * len(v) + 1, 3)), shape=(len(v), len(self.xy)))

    def window(self, rel_xy: np.ndarray) -> TipWindow:
        """The tip's compliance between any of these positions, as blocks on demand (an LCP needs few of them)."""
        return TipWindow(self.sparse_interpolation(rel_xy), self.C)


def _block(Pr, C: np.ndarray, Pc) -> np.ndarray:
    A = np.asarray(Pr @ C)                      # sparse rows times the dense compliance: 3 rows of C a position
    return np.asarray((Pc @ A.T).T)


@dataclass
class TipWindow:
    Phi: object          # scipy CSR (m, n): the window's positions from the tip's surface nodes
    C: np.ndarray

    def block(self, rows: np.ndarray | None, cols: np.ndarray | None) -> np.ndarray:
        """Phi[rows] C_tip Phi[cols]^T (None: every position)."""
        Pr = self.Phi if rows is None else self.Phi[rows]
        Pc = self.Phi if cols is None else self.Phi[cols]
        return _block(Pr, self.C, Pc)


def tip_spec(scene) -> dict:
    """What an elastic 3D tip's compliance depends on (the disk cache's key)."""
    ind = scene.indenter
    return {"shape": ind.shape, "radius_m": ind.radius_m, "youngs_pa": ind.youngs_pa, "poisson": ind.poisson,
            "order": scene.analysis.order, "fine": FINE_TIP_FRACTION, "coarse": COARSE_TIP_FRACTION,
            "grade": TIP_GRADE}


def load_or_build_tip3d(scene, use: bool | None = None) -> TipCompliance3D:
    """The scene's elastic tip from the disk cache, else built and stored."""
    return diskcache.load_or_build(
        "tip3d", {**tip_spec(scene), "code": code_version3d()},
        build=lambda: TipCompliance3D.build(scene.indenter, order=scene.analysis.order),
        to_arrays=TipCompliance3D.to_arrays, from_arrays=TipCompliance3D.from_arrays, use=use)
