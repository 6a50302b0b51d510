"""Load B in 3D: frictionless contact of a spherical (or flat circular) tip with the top face, fast per waypoint.

Bottom face u_z = 0 with the rigid-body modes removed minimally (fem.model3d.fixed_bottom), sides and top
traction-free except where the tip presses. Small-strain, small-sliding contact: the tip moves straight down, the gap
at a top node is measured vertically at the node's undeformed (x, y).

As in 2D (fem.contact), per scene: the model is factorized once with the vertical DOFs of the probed patch's top
nodes ordered last (fem.schur_lu.SchurFactor), so the trailing block of the factors is the Schur complement on them
and the condensed compliance C (patch-node downward displacement per downward nodal force) is its inverse. A
waypoint (x, y, depth) is then the LCP  gap = q + C_ww f >= 0, f >= 0, gap . f = 0  over the patch nodes under the
tip's footprint (q: the tip's profile), solved exactly by fem.lcp. Stresses under the tip come from the contact
forces by the backward sweep alone through the factor's interior columns (fem.interior_factor: forces on the patch,
ordered last, give the patch's displacements C f and leave only the interior to sweep), several waypoints in one
sweep. Those columns are kept in the disk cache beside the compliance once stresses have been asked for (1.3 GB
on block3d), so a later process's stresses cost a sweep, not a new factorization.

A tip fem treats as rigid (fem.tip.treated_as_rigid: no modulus, or its Hertz relative compliance below
TIP_TOLERANCE, 4.5e-5 for the 60 MPa tip on 2.5 kPa tissue) is rigid. A softer spherical tip is elastic
(fem.tip3d: its lower half meshed and its surface's vertical compliance condensed once; the LCP's compliance is the
tissue's plus the tip's at the window's nodes); an elastic flat punch is refused. The tissue's compliance does not
depend on the tip: it is cached under the scene with a rigid tip, the elastic tip's under its own key.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from . import diskcache
from .condense import interior_factor, schur
from .contact import STONE_LAYER_MAX, _surface_spec, check_depth, condensed_displacements
from .guards import check_finite
from .interior_factor import InteriorFactor
from .lcp import solve_lcp
from .mesh3d import Mesh3D, patch_bounds
from .model3d import Model3D, build_model3d, fixed_bottom
from .scene import Indenter, SceneError
from .scene_mesh import sources_version
from .scene_mesh3d import code_version3d, mesh_for3d
from .stress3d import components3d, point_operator3d, recovery_operator3d
from .tip import TIP_TOLERANCE, rigid_tip_bound, treated_as_rigid
from .tip3d import TipCompliance3D, load_or_build_tip3d

# The contact model keeps a dense compliance of the patch's top nodes (8 n^2 bytes): 16000 nodes are 2 GB.
MAX_PATCH_NODES = 16_000
# Contact radius over the patch's element size below which the maximum von Mises is not resolved: an independent
# review (session 34; docs/fem.md "3D stresses under a round tip") found it +1 to +12 % above Hertz at >= 3 (nu 0.3-0.49),
# up to +21 % at 2-2.3 and false peaks near the contact's edge at 1.4; forces are not affected.
STRESS_RESOLVED = 3.0


def patch_element_m(scene) -> float:
    """The element size on the probed patch, m (fem.mesh3d: mesh_size_m / surface_refine)."""
    return scene.analysis.mesh_size_m / scene.analysis.surface_refine


@dataclass
class IndentResult3D:
    x_m: float
    y_m: float
    depth_m: float
    force_n: float
    max_von_mises_pa: float     # the maximum over the tissue elements' stress points under the tip
    max_von_mises_at_m: tuple[float, float, float]   # (x_m, y_m, depth below the surface in m) of that point
    contact_radius_m: float     # the contact's mean radius (edge midway between the contact and the next free node)
    contact_x_m: np.ndarray     # patch nodes under the tip's footprint
    contact_y_m: np.ndarray
    pressure_pa: np.ndarray     # contact pressure there (-sigma_zz at the surface, >= 0; zeros without stresses)
    nodal_force_n: np.ndarray   # consistent nodal contact forces there
    gap_m: np.ndarray           # gaps there (0 where in contact)
    rigid_tip: bool
    tip_note: str = ""
    contact_radius_over_element: float = 0.0   # contact_radius_m / the patch's element size (STRESS_RESOLVED)

    def to_dict(self) -> dict:
        """JSON-ready values (keys as in 2D plus y_m); NonFiniteResultError if any is NaN or infinite."""
        x, y, dz = self.max_von_mises_at_m
        return check_finite({
            "x_m": self.x_m, "y_m": self.y_m, "depth_m": self.depth_m, "force_n": self.force_n,
            "max_von_mises_pa": self.max_von_mises_pa, "max_von_mises_at": {"x_m": x, "y_m": y, "depth_m": dz},
            "contact_radius_m": self.contact_radius_m, "rigid_tip": self.rigid_tip, "tip_note": self.tip_note,
            "contact_radius_over_element": self.contact_radius_over_element,
            "contact": {"x_m": self.contact_x_m.tolist(), "y_m": self.contact_y_m.tolist(),
                        "pressure_pa": self.pressure_pa.tolist(), "gap_m": self.gap_m.tolist(),
                        "nodal_force_n": self.nodal_force_n.tolist()}},
            f"indentation at x_m={self.x_m}, y_m={self.y_m}, depth_m={self.depth_m}")


def tip_profile3d(indenter, x_m: float, y_m: float, depth_m: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height of the tip's lower surface above the undeformed top face at (x, y) (inf where the tip is absent)."""
    r2 = (x - x_m) ** 2 + (y - y_m) ** 2
    R = indenter.radius_m
    out = np.full(len(x), np.inf)
    inside = r2 <= R * R
    if indenter.shape == "sphere":
        out[inside] = -depth_m + (R - np.sqrt(np.maximum(R * R - r2[inside], 0.0)))
    else:  # flat circular punch of radius R
        out[inside] = -depth_m
    return out


def check_waypoint3d(scene, x_m: float, y_m: float, depth_m: float) -> None:
    """ValueError unless (x_m, y_m, depth_m) is a waypoint the 3D contact model covers: the tip's footprint (a disk
    of the tip radius) on the probed patch, depth in [0, STRAIN_MAX * height], for a sphere below its radius, and
    for every stone under the footprint at most STONE_LAYER_MAX times the tissue layer above it."""
    t, a, ind = scene.tissue, scene.analysis, scene.indenter
    R = ind.radius_m
    x0, x1, y0, y1 = patch_bounds(t.width_m, t.length_m, a.patch_m)
    for name, v, lo, hi in (("x_m", x_m, x0, x1), ("y_m", y_m, y0, y1)):
        if not (isinstance(v, (int, float)) and math.isfinite(v)) or not (lo + R - 1e-12 <= v <= hi - R + 1e-12):
            raise ValueError(f"{name}={v!r} must lie in [{lo + R:.6g}, {hi - R:.6g}] m: the tip's footprint (radius "
                             f"{R:g} m) must stay on the probed patch [{lo:.6g}, {hi:.6g}] m (analysis.patch_m = "
                             f"{a.patch_m})")
    check_depth(scene, depth_m)
    for i, s in enumerate(scene.stones):
        layer = s.depth_m - s.radius_m
        if math.hypot(s.x_m - x_m, s.y_m - y_m) < R + s.radius_m and depth_m > STONE_LAYER_MAX * layer:
            raise ValueError(f"depth_m={depth_m} at (x_m={x_m}, y_m={y_m}): stone[{i}] under the tip lies "
                             f"{layer * 1e3:.3g} mm below the surface; the indentation must stay within "
                             f"{STONE_LAYER_MAX:.0%} of that layer (depth_m <= {STONE_LAYER_MAX * layer:.4g} m)")


def patch_nodes(mesh, patch_m: float | None) -> np.ndarray:
    """Top-face node indices on the probed patch (all top nodes when patch_m is None)."""
    x0, x1, y0, y1 = patch_bounds(mesh.width_m, mesh.length_m, patch_m)
    tol = 1e-9 * max(mesh.width_m, mesh.length_m)
    p = mesh.nodes[mesh.top]
    on = (p[:, 0] >= x0 - tol) & (p[:, 0] <= x1 + tol) & (p[:, 1] >= y0 - tol) & (p[:, 1] <= y1 + tol)
    return mesh.top[on]


class SurfaceModel3D:
    """A 3D scene's condensed probed-patch response: build once, then ``indent`` any waypoint in milliseconds.

    stress_band_m: depth below the surface (and horizontal reach from the tip axis) over which the maximum von
    Mises stress in the tissue is searched (default 2 R), over the elements' stress points
    (fem.stress3d.point_operator3d). compliance: restored from disk (``from_arrays``); K is then factorized
    only when fields are asked for. tip: an elastic tip's compliance (default: fem.tip3d's, from the disk cache)."""

    def __init__(self, scene, model: Model3D | None = None, rigid_tip: str | bool = "auto",
                 tip_tolerance: float = TIP_TOLERANCE, stress_band_m: float | None = None,
                 rigid_stones: str | bool = "auto", solver: str = "auto", *, compliance: np.ndarray | None = None,
                 mesh: Mesh3D | None = None, tip: TipCompliance3D | None = None, keep_interior: bool = False):
        t0 = time.perf_counter()
        if not scene.is_3d:
            raise SceneError(f"scene {scene.name!r} is 2D (no tissue.length_m): use fem.contact.SurfaceModel")
        self.scene = scene
        self.rigid_tip = treated_as_rigid(scene, rigid_tip, tip_tolerance)
        self.tip: TipCompliance3D | None = None
        if not self.rigid_tip:
            if scene.indenter.shape != "sphere":
                raise SceneError(f"indenter.youngs_pa = {scene.indenter.youngs_pa!r} with indenter.shape = "
                                 f"{scene.indenter.shape!r}: an elastic flat punch is not modelled in 3D (its edge "
                                 f"is singular); give no youngs_pa (rigid) or shape = 'sphere'")
            self.tip = tip if tip is not None else load_or_build_tip3d(scene)
            self.tip_note = (f"elastic tip (E = {scene.indenter.youngs_pa:g} Pa, nu = {scene.indenter.poisson:g}): "
                             f"its lower half meshed and gripped at its flat face; Hertz relative compliance "
                             f"{rigid_tip_bound(scene):.3g}")
        else:
            self.tip_note = ("rigid tip (no modulus given)" if scene.indenter.youngs_pa is None else
                             "tip treated as rigid: its deformation changes the force by a relative amount below "
                             f"{tip_tolerance:g} (Hertz estimate)")
        self._rigid_stones, self._solver = rigid_stones, solver
        self._model = model if compliance is None else None     # restored: the model is built when fields are asked
        if compliance is None and model is None:
            self._model = build_model3d(scene, mesh=mesh, rigid_stones=rigid_stones)
        self.mesh = self._model.mesh if self._model is not None else (mesh if mesh is not None else model.mesh)
        self.patch = patch_nodes(self.mesh, scene.analysis.patch_m)
        if len(self.patch) > MAX_PATCH_NODES:      # (refused before the stiffness is assembled: 18 s on a 2 mm mesh)
            raise SceneError(f"scene {scene.name!r}: the probed patch has {len(self.patch)} top nodes (a dense "
                             f"{8 * len(self.patch) ** 2 / 1e9:.3g} GB compliance), above {MAX_PATCH_NODES}: "
                             f"lower analysis.patch_m or analysis.surface_refine")
        if compliance is None:
            self._model.K                                       # assembled here (timed as the set-up's)
        t1 = time.perf_counter()
        self.xy = self.mesh.nodes[self.patch, :2]
        self._fac = None
        self._band = None
        self._interior: InteriorFactor | None = None
        self._interior_unreadable = False       # CHOLMOD's factor could not be read in place: not tried again
        self._keep_interior = keep_interior
        self.interior_cache: tuple[dict, bool | None] | None = None   # (spec, use): where the factor is kept
        if compliance is None:
            compliance = self.fac.compliance
            if not np.all(np.isfinite(compliance)):
                raise FloatingPointError(f"the condensed surface compliance of scene {scene.name!r} is not finite")
        self.C = compliance
        self.band_m = stress_band_m if stress_band_m is not None else 2 * scene.indenter.radius_m
        self.timings_s = {"mesh_assemble_s": t1 - t0, "factor_condense_s": time.perf_counter() - t1}
        if self._fac is not None and hasattr(self._fac, "timings_s"):
            self.timings_s["condense_parts_s"] = dict(self._fac.timings_s)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"C": self.C}

    @classmethod
    def from_arrays(cls, scene, arrays: dict[str, np.ndarray], mesh: Mesh3D, **options) -> SurfaceModel3D:
        """The SurfaceModel3D of ``scene`` on ``mesh`` with the compliance ``to_arrays`` wrote (no assembly, no
        factorization until fields are asked for); ValueError if it does not fit the mesh. The compliance arrives
        memory-mapped (``load_or_build_surface3d``: a run reads the rows of the windows it probes, not the whole
        dense matrix, 0.5 GB on the block3d scene) and is not scanned here: each block is checked finite as a contact
        solve reads it (``window_compliance``)."""
        C = np.asarray(arrays["C"])          # a memory map as a plain array: no copy (np.memmap's indexing is slow)
        n = len(patch_nodes(mesh, scene.analysis.patch_m))
        if C.shape != (n, n):
            raise ValueError(f"compliance of shape {C.shape}, expected ({n}, {n})")
        return cls(scene, mesh=mesh, compliance=C, **options)

    @property
    def model(self) -> Model3D:
        """The assembled model (built on first use when the compliance came from the disk cache)."""
        if self._model is None:
            self._model = build_model3d(self.scene, mesh=self.mesh, rigid_stones=self._rigid_stones)
        return self._model

    def _free_contact(self) -> tuple[np.ndarray, np.ndarray]:
        """(the model's free reduced DOFs, the patch nodes' vertical reduced DOFs)."""
        model = self.model
        return (np.setdiff1d(np.arange(model.n_dofs), np.unique(fixed_bottom(model))),
                model.reduced_index(3 * self.patch + 2))

    @property
    def fac(self):
        """The condensing factorization (fem.condense.schur; made on first use after a cache restore)."""
        if self._fac is None:
            free, contact = self._free_contact()
            self._fac = schur(self.model.K, free, contact, self._solver,
                              compliance=not hasattr(self, "C"),      # restored from disk: the factor only
                              interior=self._keep_interior and self._interior is None)
            if getattr(self._fac, "interior", None) is not None:    # taken over (kept here, not twice)
                self._interior, self._fac.interior = self._interior or self._fac.interior, None
        return self._fac

    def interior(self) -> InteriorFactor | None:
        """The factor's interior columns for the stresses' backward sweep (fem.interior_factor): from memory (kept
        from the compliance's factorization with ``keep_interior``), the disk cache (``interior_cache``, set by
        load_or_build_surface3d) or one new factorization, then stored; None with the SuperLU solver, without
        cvxopt, or when CHOLMOD's factor cannot be read in place."""
        if self._interior is None and self._solver != "superlu" and not self._interior_unreadable:
            spec, use = self.interior_cache if self.interior_cache is not None else (None, False)
            free, contact = self._free_contact()
            c = np.searchsorted(free, contact)                  # the contact DOFs' positions among the free ones

            def restore(arrays):
                f = InteriorFactor.from_arrays(arrays)
                if f.n != len(free) or not np.array_equal(f.p[f.n - f.nc:], c):
                    raise ValueError(f"a factor of {f.n} DOFs ({f.nc} on the patch) that does not fit this model "
                                     f"({len(free)}, {len(c)})")
                return f
            if spec is not None:
                self._interior = diskcache.load("factor3d", spec, restore, use=use, mmap=True)
            if self._interior is None:
                self._interior = interior_factor(self.model.K, free, contact)
                self._interior_unreadable = self._interior is None
                if self._interior is not None and spec is not None:
                    self._interior = _stored(self._interior, spec, use, restore)
        return self._interior

    # -- one waypoint --------------------------------------------------------------------------------------------
    def _window(self, x_m: float, y_m: float) -> np.ndarray:
        R = self.scene.indenter.radius_m
        return np.flatnonzero((self.xy[:, 0] - x_m) ** 2 + (self.xy[:, 1] - y_m) ** 2 <= R * R)

    def contact_forces(self, x_m: float, y_m: float, depth_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(window patch-node indices, downward nodal forces (N), gaps (m)) for one waypoint."""
        check_waypoint3d(self.scene, x_m, y_m, depth_m)
        idx = self._window(x_m, y_m)
        q = tip_profile3d(self.scene.indenter, x_m, y_m, depth_m, self.xy[idx, 0], self.xy[idx, 1])
        if depth_m == 0.0 or not np.any(q < 0):
            return idx, np.zeros(len(idx)), q
        return (idx, *self._solve_window(idx, q, self.window_compliance(idx, x_m, y_m)))

    def window_compliance(self, idx: np.ndarray, x_m: float, y_m: float):
        """``block(rows, cols)``: the gap's compliance between window nodes idx[rows] and idx[cols] (None: all) with
        the tip at (x_m, y_m): the tissue's, plus an elastic tip's at the nodes' positions relative to its axis."""
        C, name = self.C, self.scene.name

        def tissue(r, c):       # checked as read: a restored compliance is memory-mapped, not scanned whole
            b = C[np.ix_(idx if r is None else idx[r], idx if c is None else idx[c])]
            if not np.isfinite(b).all():
                raise FloatingPointError(f"scene {name!r}: the surface compliance holds non-finite numbers (a "
                                         f"damaged disk cache entry? delete it, or set PALPATE_CACHE=0)")
            return b
        if self.tip is None:
            return tissue
        tw = self.tip.window(self.xy[idx] - (x_m, y_m))
        return lambda r, c: tissue(r, c) + tw.block(r, c)

    def _solve_window(self, idx: np.ndarray, q: np.ndarray, block) -> tuple[np.ndarray, np.ndarray]:
        """The exact LCP over the window (compliance blocks ``block(rows, cols)``), solved on the nodes the tip
        overlaps (q < 0) first: a node with q >= 0 is out of contact whenever the compliance couples it
        non-negatively to the contact nodes (a downward push lowers the surface around it). The complementarity
        conditions are then checked on every window node and the whole window is solved when any fails. Warm start:
        the nodes overlapped by more than half the deepest overlap (Hertz: a^2 = R d is where the sphere's overlap
        is d / 2)."""
        inner = np.flatnonzero(q < 0)
        r = solve_lcp(block(inner, inner), q[inner], start=q[inner] < 0.5 * q.min())
        z = np.zeros(len(idx))
        z[inner] = r.z
        act = inner[r.z > 0]
        w = q + block(None, act) @ z[act]
        if np.all(w >= -1e-12 * np.abs(q).max()):
            w[inner] = r.w
            return z, w
        full = solve_lcp(block(None, None), q, start=z > 0)
        return full.z, full.w

    def force_n(self, x_m: float, y_m: float, depth_m: float) -> float:
        return check_finite(float(self.contact_forces(x_m, y_m, depth_m)[1].sum()),
                            f"scene {self.scene.name!r}: force at x_m={x_m}, y_m={y_m}, depth_m={depth_m}")

    def displacements(self, F_patch: np.ndarray) -> np.ndarray:
        """Full displacement vectors (3N, k) for downward nodal forces F_patch (n_patch, k) on the patch nodes: the
        patch's own from the compliance (C f, reading the rows of the nodes each column loads), the rest by the
        interior sweep (``interior``); without it by the condensing factorization (``fac``)."""
        F_patch = np.asarray(F_patch, dtype=float).reshape(len(self.patch), -1)
        itf = self.interior()
        if itf is None:
            return condensed_displacements(self.model, self.fac, F_patch)
        x_c = np.zeros(F_patch.shape)
        for k in range(F_patch.shape[1]):
            nz = np.flatnonzero(F_patch[:, k])
            x_c[:, k] = -(F_patch[nz, k] @ self.C[nz])          # C is symmetric: its rows are its columns
        X = np.empty((itf.n, F_patch.shape[1]))
        X[itf.p] = itf.sweep(x_c)
        if not np.isfinite(X).all():
            raise FloatingPointError(f"scene {self.scene.name!r}: the displacements are not finite (a damaged disk "
                                     f"cache entry? delete it, or set PALPATE_CACHE=0)")
        free, _ = self._free_contact()
        Y = np.zeros((self.model.n_dofs, F_patch.shape[1]))
        Y[free] = X
        return self.model.P @ Y

    def _band_op(self):
        """(stress-point positions X, their stress operator, the patch nodes' stress operator): the stress points
        (fem.stress3d.point_operator3d) of the tissue's elements whose centre lies within band_m below the probed
        patch (grown by band_m sideways), and the nodal stresses of the patch's top nodes (the contact pressure);
        built once, then each waypoint takes the rows under its tip. Kept in the disk cache beside the factor (kind
        ``band3d``, 0.2 GB on block3d; its key adds the stress recovery's sources), memory-mapped."""
        if self._band is None:
            if self.interior_cache is None:
                self._band = self._build_band()
            else:
                spec, use = self.interior_cache
                n_rows, n_cols = 6 * len(self.patch), 3 * self.mesh.n_nodes
                self._band = diskcache.load_or_build(
                    "band3d", {**spec, "band_m": self.band_m, "recovery": _recovery_version()}, self._build_band,
                    to_arrays=_band_arrays, from_arrays=lambda a: _band_from(a, n_rows, n_cols), use=use, mmap=True)
        return self._band

    def _build_band(self) -> tuple[np.ndarray, sp.csr_matrix, sp.csr_matrix]:
        mesh, b = self.mesh, self.band_m
        x0, x1, y0, y1 = patch_bounds(mesh.width_m, mesh.length_m, self.scene.analysis.patch_m)
        c = mesh.nodes[mesh.tets[:, :4]].mean(axis=1)
        els = np.flatnonzero((mesh.region == 0) & (c[:, 2] >= mesh.height_m - b) & (c[:, 0] >= x0 - b)
                             & (c[:, 0] <= x1 + b) & (c[:, 1] >= y0 - b) & (c[:, 1] <= y1 + b))
        Rp, X = point_operator3d(self.model, els)
        return X, Rp.tocsr(), recovery_operator3d(self.model, self.patch).tocsr()

    def indent(self, x_m: float, y_m: float, depth_m: float, stresses: bool = True) -> IndentResult3D:
        return self.indent_many([(x_m, y_m, depth_m)], stresses=stresses)[0]

    def indent_many(self, waypoints, stresses: bool = True) -> list[IndentResult3D]:
        """Several waypoints (x_m, y_m, depth_m); their displacement fields come from one batched solve."""
        return self._indent_batch(waypoints, stresses)[0]

    def indent_with_field(self, x_m: float, y_m: float, depth_m: float) -> tuple[IndentResult3D, np.ndarray]:
        """One waypoint with its stresses and its full displacement vector (3N,), both from one sweep (``indent``
        then ``full_field`` would sweep twice)."""
        (r,), U = self._indent_batch([(x_m, y_m, depth_m)], stresses=True)
        u = U[:, 0] if U is not None else np.zeros(self.model.P.shape[0])
        return r, check_finite(u, f"scene {self.scene.name!r}: displacements")

    def _indent_batch(self, waypoints, stresses: bool) -> tuple[list[IndentResult3D], np.ndarray | None]:
        """``indent_many``'s results and the displacement fields (3N, k) they came from (None: none needed)."""
        pts = [tuple(float(v) for v in w) for w in waypoints]
        sols = [self.contact_forces(*p) for p in pts]
        U = None
        if stresses and any(f.any() for _, f, _ in sols):
            F = np.zeros((len(self.patch), len(sols)))
            for k, (idx, f, _) in enumerate(sols):
                F[idx, k] = f
            U = self.displacements(F)
            X, Rb, Rtop = self._band_op()
        out = []
        mesh, b = self.mesh, self.band_m
        h = patch_element_m(self.scene)
        for k, ((idx, f, gap), (x_m, y_m, depth_m)) in enumerate(zip(sols, pts)):
            active = f > 0
            vm_max, at, pressure = 0.0, (x_m, y_m, 0.0), np.zeros(len(idx))
            near = np.zeros(0, dtype=np.int64)
            if U is not None and active.any():
                near = np.flatnonzero((np.abs(X[:, 0] - x_m) <= b) & (np.abs(X[:, 1] - y_m) <= b))
            if len(near):               # (none only if no tissue element lies under the tip within the band)
                vm = components3d(_stress_at(Rb, near, U[:, k]))["von_mises_pa"]
                szz = _stress_at(Rtop, idx, U[:, k])[:, 2]
                if not (np.isfinite(vm).all() and np.isfinite(szz).all()):
                    raise FloatingPointError(f"scene {self.scene.name!r}: the stresses under the tip are not finite "
                                             f"(a damaged disk cache entry? delete it, or set PALPATE_CACHE=0)")
                j = int(np.argmax(vm))
                vm_max = float(vm[j])
                at = (float(X[near[j], 0]), float(X[near[j], 1]), float(mesh.height_m - X[near[j], 2]))
            a = _contact_radius(self.xy[idx], (x_m, y_m), active)
            if len(near):
                # within the contact radius, not only where a node carries force: under a uniform pressure a P2
                # face's corner nodes take none, and the contact solve leaves about a fifth of them at zero force,
                # a micrometre off the tip, where the tissue is as compressed as around them (session 45's review
                # read 0 there where Hertz gives about p0)
                inside = np.hypot(self.xy[idx, 0] - x_m, self.xy[idx, 1] - y_m) <= a
                pressure = np.where(inside, np.maximum(-szz, 0.0), 0.0)
            out.append(IndentResult3D(
                x_m=x_m, y_m=y_m, depth_m=depth_m,
                force_n=check_finite(float(f.sum()), f"scene {self.scene.name!r}: force"),
                max_von_mises_pa=vm_max, max_von_mises_at_m=at,
                contact_radius_m=a, contact_radius_over_element=a / h, contact_x_m=self.xy[idx, 0],
                contact_y_m=self.xy[idx, 1], pressure_pa=pressure, nodal_force_n=f, gap_m=gap,
                rigid_tip=self.rigid_tip, tip_note=self.tip_note))
        return out, U

    def full_field(self, x_m: float, y_m: float, depth_m: float) -> np.ndarray:
        """Full displacement vector (3N,) for one waypoint: one more back-substitution."""
        idx, f, _ = self.contact_forces(x_m, y_m, depth_m)
        F = np.zeros((len(self.patch), 1))
        F[idx, 0] = f
        return check_finite(self.displacements(F)[:, 0], f"scene {self.scene.name!r}: displacements")


@functools.lru_cache(maxsize=1)
def _recovery_version() -> str:
    """The stress recovery's own sources (not in the 3D code version): a key part of the band operators' entry."""
    return sources_version(("stress3d.py", "elements3d.py", "assembly3d.py"), "band3d 1")


def _band_arrays(band) -> dict[str, np.ndarray]:
    X, Rb, Rt = band
    return {"X": X, **{f"{name}_{part}": getattr(R, part) for name, R in (("Rb", Rb), ("Rt", Rt))
                       for part in ("data", "indices", "indptr")}}


def _band_from(a: dict[str, np.ndarray], n_top_rows: int, n_cols: int):
    """The band operators from ``_band_arrays``' arrays (memory maps used as they are); ValueError when they do not
    fit the model (``n_top_rows``: 6 per patch node; ``n_cols``: 3 per mesh node)."""
    X = np.asarray(a["X"])
    ops = []
    for name, rows in (("Rb", 6 * len(X)), ("Rt", n_top_rows)):
        data, ind, ptr = (np.asarray(a[f"{name}_{p}"]) for p in ("data", "indices", "indptr"))
        if (X.ndim != 2 or X.shape[1] != 3 or len(ptr) != rows + 1 or ptr[0] != 0 or ptr[-1] != len(data)
                or len(ind) != len(data) or (len(ind) and (ind.min() < 0 or ind.max() >= n_cols))):
            raise ValueError(f"the stored {name} operator does not fit the model")
        ops.append(sp.csr_matrix((data, ind, ptr), shape=(rows, n_cols)))
    return X, ops[0], ops[1]


def _stress_at(R, node_pos: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(n, 6) stresses at the points (nodes) in rows ``node_pos`` of the stress operator R, for displacement u."""
    return (R[(6 * node_pos[:, None] + np.arange(6)).ravel()] @ u).reshape(-1, 6)


def _contact_radius(xy: np.ndarray, centre, active: np.ndarray) -> float:
    """The mean contact radius: midway between the farthest contact node and the nearest free node beyond it."""
    if not active.any():
        return 0.0
    r = np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1])
    inner = r[active].max()
    beyond = r[~active & (r > inner)]
    return float(0.5 * (inner + beyond.min())) if len(beyond) else float(inner)


def _surface3d_spec(scene, options: dict) -> dict:
    tissue = dataclasses.replace(scene, indenter=dataclasses.replace(scene.indenter, youngs_pa=None,
                                                                      poisson=Indenter().poisson))
    return _surface_spec(tissue, options, code_version3d())     # the tissue's compliance does not depend on the tip


def surface3d_cached(scene, **options) -> bool:
    """Whether ``surface_model3d(scene, **options)`` would come from memory or the disk cache (no assembly and no
    factorization for forces): what a command tells its user before a long build."""
    key = (scene.key(), tuple(sorted(options.items())))
    return key in _CACHE or (diskcache.enabled() and diskcache.entry_path("surface3d",
                                                                           _surface3d_spec(scene, options)).exists())


def load_or_build_surface3d(scene, options: dict, use: bool | None = None,
                            stresses: bool = False) -> SurfaceModel3D:
    """A SurfaceModel3D restored from the disk cache (its compliance; the model is assembled only when fields are
    asked for), else built and stored. ``stresses``: a build keeps its factorization's interior columns and stores
    them (the stresses then need no second factorization)."""
    mesh = mesh_for3d(scene, use=use)
    spec = _surface3d_spec(scene, options)
    m = diskcache.load_or_build(
        "surface3d", spec, build=lambda: SurfaceModel3D(scene, mesh=mesh, keep_interior=stresses, **options),
        to_arrays=SurfaceModel3D.to_arrays,
        from_arrays=lambda arrays: SurfaceModel3D.from_arrays(scene, arrays, mesh=mesh, **options), use=use,
        mmap=True)
    m.interior_cache = (spec, use)      # the stresses' factor is kept under the same key (kind "factor3d")
    if m._interior is not None:
        m._interior = _stored(m._interior, spec, use, InteriorFactor.from_arrays)
    return m


def _stored(f: InteriorFactor, spec: dict, use: bool | None, restore) -> InteriorFactor:
    """``f`` written to the disk cache (kind "factor3d") and read back memory-mapped, so the process does not keep
    its copy (1.3 GB on block3d) in memory; ``f`` itself when the cache is off or the write failed."""
    if not diskcache.enabled(use):
        return f
    diskcache.write(diskcache.entry_path("factor3d", spec), f.to_arrays())
    return diskcache.load("factor3d", spec, restore, use=use, mmap=True) or f


def factor3d_cached(scene, **options) -> bool:
    """Whether the stresses of ``surface_model3d(scene, **options)`` would come without a factorization (the
    factor's interior columns in memory or the disk cache): what a command tells its user before a long build."""
    key = (scene.key(), tuple(sorted(options.items())))
    if key in _CACHE and _CACHE[key]._interior is not None:
        return True
    return diskcache.enabled() and diskcache.entry_path("factor3d", _surface3d_spec(scene, options)).exists()


_CACHE: dict[tuple, SurfaceModel3D] = {}


def surface_model3d(scene, cache: bool | None = None, stresses: bool = False, **options) -> SurfaceModel3D:
    """The SurfaceModel3D of a scene, built once per scene content and options (in memory), kept on disk.
    ``stresses``: the caller will ask for stresses (a build then keeps what they need: load_or_build_surface3d)."""
    key = (scene.key(), tuple(sorted(options.items())))
    if key not in _CACHE:
        _CACHE[key] = load_or_build_surface3d(scene, options, use=cache, stresses=stresses)
    return _CACHE[key]
