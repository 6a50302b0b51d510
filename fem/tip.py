"""The probe tip's own deformation, and when it can be skipped.

An elastic cylindrical tip is meshed once (the lower half-disk, gripped along its flat top) and its arc's vertical
compliance condensed once. At a waypoint the contact forces act on the tip at the contact nodes' positions relative
to the tip axis; a piecewise-linear interpolation along the arc carries forces to the tip's nodes and displacements
back, so the tip adds  Phi C_tip Phi^T  to the tissue compliance in the contact LCP.

Skipping it: in the plane-strain Hertz combination 1/E* = (1 - nu_t^2)/E_t + (1 - nu^2)/E, the tip contributes the
relative compliance  rho = E (1 - nu_t^2) / (E_t (1 - nu^2))  (plane stress: E / E_t). Treating the tip as rigid
over-estimates the force at a given depth by a relative amount of order rho; for the study's 60 MPa tip on 2.5 kPa
tissue rho = 4.5e-5. The tests and the bench measure the actual change against this bound.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .assembly import Material, element_D, stiffness
from .mesh import mesh_tip
from .scene import Indenter

TIP_TOLERANCE = 1e-3   # an elastic tip whose rigid_tip_bound is below this is treated as rigid (SurfaceModel "auto")


def rigid_tip_bound(scene) -> float:
    """The relative change of the force from treating the scene's tip as rigid (Hertz estimate rho, module doc)."""
    ind, t = scene.indenter, scene.tissue
    if ind.youngs_pa is None:
        return 0.0
    if scene.analysis.plane == "strain":
        return t.youngs_pa * (1 - ind.poisson ** 2) / (ind.youngs_pa * (1 - t.poisson ** 2))
    return t.youngs_pa / ind.youngs_pa


def treated_as_rigid(scene, rigid_tip: str | bool = "auto", tip_tolerance: float = TIP_TOLERANCE) -> bool:
    """Whether fem models the scene's tip as rigid (no modulus given, forced, or within ``tip_tolerance``)."""
    if scene.indenter.youngs_pa is None or rigid_tip is True:
        return True
    return rigid_tip == "auto" and rigid_tip_bound(scene) < tip_tolerance


def tip_too_soft(scene) -> bool:
    """Whether the scene's tip is too soft for the finite-strain model, whose tip is rigid: one fem's linear model
    does not treat as rigid either (fem.tip.treated_as_rigid) and below 1000 times the tissue's modulus. The rule of
    fem.hyperindent and planner.finite_strain_response (session 58: each had the 1000 times alone, while a tip fem
    treats as rigid, its Hertz bound below 1e-3, which a tip below 1000 times can be when its Poisson ratio is the
    higher, lost its modulus on the way in and passed). robot.truth, which may not ask fem, keeps the 1000 times
    alone for a neo-Hookean truth: a tip in that narrow band is refused there, with its own message."""
    e = scene.indenter.youngs_pa
    return e is not None and not treated_as_rigid(scene) and e < 1e3 * scene.tissue.youngs_pa


def contact_scene(scene, rigid_tip: str | bool = "auto", tip_tolerance: float = TIP_TOLERANCE):
    """The scene with only what changes a contact answer: a tip fem treats as rigid loses its modulus (and its
    Poisson ratio), so a 60 MPa tip on 2.5 kPa tissue shares the rigid tip's cached operators and tables."""
    if scene.indenter.youngs_pa is None or not treated_as_rigid(scene, rigid_tip, tip_tolerance):
        return scene
    rigid = dataclasses.replace(scene.indenter, youngs_pa=None, poisson=Indenter().poisson)
    return dataclasses.replace(scene, indenter=rigid)


@dataclass
class TipCompliance:
    """The condensed vertical compliance of an elastic tip's arc (``build``), or restored (``from_arrays``)."""
    C: np.ndarray    # (n_arc, n_arc) upward displacement per upward force
    s: np.ndarray    # (n_arc,) abscissa of the arc nodes (tip axis at 0), increasing

    @classmethod
    def build(cls, scene) -> TipCompliance:
        """Mesh the scene's tip and condense its arc's compliance."""
        ind = scene.indenter
        if ind.shape != "cylinder":
            raise ValueError("an elastic tip is modelled for shape='cylinder' only; give no youngs_pa for a rigid "
                             "flat punch")
        R = ind.radius_m
        size = min(scene.analysis.mesh_size_m, R / 4)
        mesh = mesh_tip(R, size, order=scene.analysis.order)
        D = element_D(mesh, [Material(ind.youngs_pa, ind.poisson)], scene.analysis.plane)
        K = stiffness(mesh, D).tocsc()
        grip = mesh.top                                           # flat top edge, y = R: held by the holder
        fixed = np.concatenate([2 * grip, 2 * grip + 1])
        free = np.setdiff1d(np.arange(mesh.n_dofs), fixed)
        tol = 1e-9 * R
        on_arc = np.abs(np.hypot(mesh.nodes[:, 0], mesh.nodes[:, 1] - R) - R) < 1e-6 * R
        arc = np.flatnonzero(on_arc & (mesh.nodes[:, 1] < R - tol))
        arc = arc[np.argsort(mesh.nodes[arc, 0])]
        import scipy.sparse.linalg as spla
        lu = spla.splu(K[free][:, free].tocsc())
        pos = np.searchsorted(free, 2 * arc + 1)
        unit = np.zeros((len(free), len(arc)))
        unit[pos, np.arange(len(arc))] = 1.0                      # unit upward force on the tip at each arc node
        X = lu.solve(np.asfortranarray(unit))
        C = X[pos, :]
        return cls(C=0.5 * (C + C.T), s=mesh.nodes[arc, 0])

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"C": self.C, "s": self.s}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> TipCompliance:
        """The tip ``to_arrays`` wrote; ValueError if the arrays do not fit together."""
        C, s = arrays["C"], arrays["s"]
        if s.ndim != 1 or len(s) < 2 or C.shape != (len(s), len(s)) or not np.all(np.isfinite(C)):
            raise ValueError(f"tip compliance of shape {C.shape} for {s.shape} arc nodes")
        return cls(C=C, s=s)

    def interpolation(self, s: np.ndarray) -> np.ndarray:
        """(len(s), n_arc) piecewise-linear interpolation from arc nodes to abscissae s."""
        k = np.clip(np.searchsorted(self.s, s) - 1, 0, len(self.s) - 2)
        t = np.clip((s - self.s[k]) / (self.s[k + 1] - self.s[k]), 0.0, 1.0)
        Phi = np.zeros((len(s), len(self.s)))
        rows = np.arange(len(s))
        Phi[rows, k] = 1 - t
        Phi[rows, k + 1] = t
        return Phi

    def compliance(self, s: np.ndarray) -> np.ndarray:
        Phi = self.interpolation(s)
        return Phi @ self.C @ Phi.T
