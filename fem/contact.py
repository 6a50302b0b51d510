"""Frictionless unilateral contact of a probe tip with the top surface, fast for many waypoints.

Load case B: bottom edge u_y = 0, bottom-left corner u_x = 0, sides and top traction-free except where the tip
presses. Small-strain, small-sliding contact: the tip moves straight down, the gap at a top node is measured
vertically at the node's undeformed x, and frictionless contact lets the surface slide freely.

The fast path (``SurfaceModel``): the scene is meshed and K factorized once; the vertical DOFs of the top edge are
condensed once into a compliance matrix C (top-node y-displacement per unit downward nodal force). A waypoint
(x0, depth) is then the LCP  gap = q + C_cc f >= 0, f >= 0, gap . f = 0  over the top nodes under the tip (q: the
tip's profile minus the surface), solved exactly by fem.lcp. Stresses are linear in the contact forces, so
influence matrices give the stresses under the tip without another solve.

``indent_full`` is the plain path: a full finite-element solve with the contact nodes as Dirichlet conditions and
its own active-set loop, refactorizing every iteration. The two must agree to round-off (tests check it).

``surface_model`` keeps SurfaceModels in memory and on disk (fem.diskcache, keyed by the scene's content, the
options and the code version). What is stored is the compliance C of the top surface (and an elastic tip's arc
compliance), see ``SurfaceModel.to_arrays``; a restored SurfaceModel answers force queries (the LCP needs only C) at
once. C is the inverse of the Schur complement read from CHOLMOD's factor of K_ff with the top last (fem.condense, as
in 3D; SuperLU's, fem.schur_lu, without cvxopt). Fields (stresses without the influence operators, displacements)
need the interior of a factorization: the first request makes one (CHOLMOD, with the top last) and stores its
interior columns beside C (kind ``factor``, fem.interior_factor), so a later process sweeps through them with no
assembly and no factorization; without cvxopt the SuperLU factorization serves, made again in each process. The
restored C is bitwise the C a fresh build computes (tests check it).
"""
from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass

import numpy as np

from . import diskcache
from .guards import check_finite, check_not_inverted
from .influence import Influence, band_nodes, fits
from .lcp import solve_lcp
from .model import Model, build_model
from .scene import STRAIN_MAX, STRAIN_WARN, SceneError
from .scene_mesh import check_surface_budget, code_version, mesh_for, sources_version
from .stress import components, nodal_poisson, recovery_operator
from .tip import TIP_TOLERANCE, TipCompliance, contact_scene, rigid_tip_bound

INFLUENCE_MIN_WAYPOINTS = 50   # a batch this large builds the influence operators (a smaller one uses them if cached)
INVERSION_HINT = "indent less deep (the tissue above a stone or the tissue height is too thin)"


@dataclass
class IndentResult:
    x_m: float
    depth_m: float
    force_n_per_m: float
    force_n: float
    max_von_mises_pa: float
    max_von_mises_at_m: tuple[float, float]     # (x_m, depth below the surface in m) of the maximum
    half_width_m: float                          # half the extent of the contact (to within half a node spacing)
    contact_x_m: np.ndarray                      # top nodes under the tip
    pressure_pa: np.ndarray                      # contact pressure there (-sigma_yy at the surface, >= 0)
    nodal_force_n_per_m: np.ndarray              # consistent nodal contact forces there
    gap_m: np.ndarray                            # gaps there (0 where in contact)
    rigid_tip: bool
    tip_note: str = ""

    def to_dict(self) -> dict:
        """The result as JSON-ready values; NonFiniteResultError (fem.guards) if any is NaN or infinite."""
        return check_finite(self._dict(), f"indentation at x_m={self.x_m}, depth_m={self.depth_m}")

    def _dict(self) -> dict:
        return {"x_m": self.x_m, "depth_m": self.depth_m, "force_n_per_m": self.force_n_per_m,
                "force_n": self.force_n, "max_von_mises_pa": self.max_von_mises_pa,
                "max_von_mises_at": {"x_m": self.max_von_mises_at_m[0], "depth_m": self.max_von_mises_at_m[1]},
                "half_width_m": self.half_width_m, "rigid_tip": self.rigid_tip, "tip_note": self.tip_note,
                "contact": {"x_m": self.contact_x_m.tolist(), "pressure_pa": self.pressure_pa.tolist(),
                            "gap_m": self.gap_m.tolist()}}


def tip_profile(indenter, x_m: float, depth_m: float, x: np.ndarray) -> np.ndarray:
    """Height of the tip's lower surface above the undeformed top surface at x (inf where the tip is absent)."""
    d = x - x_m
    R = indenter.radius_m
    out = np.full(len(x), np.inf)
    inside = np.abs(d) <= R
    if indenter.shape == "cylinder":
        out[inside] = -depth_m + (R - np.sqrt(np.maximum(R * R - d[inside] ** 2, 0.0)))
    else:  # flat punch of half-width R
        out[inside] = -depth_m
    return out


def condensation(K, free: np.ndarray, contact: np.ndarray):
    """K_ff factorized with the top's vertical DOFs last, and its condensed compliance: CHOLMOD's supernodal
    factorization (fem.condense.CholmodSchur, as in 3D, but in AMD's order: on a 2D model METIS's nested dissection
    took longer than the factorization it orders) when cvxopt is installed, else SuperLU's (fem.schur_lu.SchurFactor).
    Since session 60; SuperLU's before, whose two factorizations (one for the ordering, one with the top last) took
    about five times as long on a paper-sized model; the compliances agree to about 5e-14 relative
    (1.7e-12 at nu 0.499, its conditioning: a review's six scenes)."""
    from .condense import schur  # scipy and CHOLMOD: loaded only to factorize
    return schur(K, free, contact, ordering="amd")                 # method "auto": SuperLU without cvxopt


def _load_b_fixed(model: Model) -> np.ndarray:
    mesh = model.mesh
    return model.reduced_index(np.concatenate([2 * mesh.bottom + 1, [2 * mesh.bottom[0]]]))


def condensed_displacements(model, fac, F: np.ndarray) -> np.ndarray:
    """Full displacement vectors (k columns) for downward nodal forces F (n_c, k) on the condensed DOFs of a Schur
    factorization ``fac`` (SchurFactor or fem.condense.CholmodSchur) of ``model``: the backward sweep alone when
    ``fac`` has ``solve_contact`` (CholmodSchur), else a full solve."""
    Y = np.zeros((model.n_dofs, F.shape[1]))
    if hasattr(fac, "solve_contact"):
        Y[fac.free] = fac.solve_contact(-F)
    else:
        rhs = np.zeros((len(fac.free), F.shape[1]))
        rhs[fac.c] = -F
        Y[fac.free] = fac.solve(rhs)
    return model.P @ Y


class SurfaceModel:
    """A scene's condensed top-surface response: build once, then ``indent`` any waypoint in about a millisecond.

    rigid_tip: "auto" treats an elastic tip as rigid when that changes the force by less than ``tip_tolerance``
    (relative, bound from fem.tip.rigid_tip_bound), True always rigid, False always elastic (if a modulus is given).
    stress_band_m: depth below the surface over which the maximum von Mises stress is searched (default 2 R).
    compliance, tip: operators restored from disk (``from_arrays``); K is then factorized only when fields are
    asked for.
    """

    def __init__(self, scene, model: Model | None = None, rigid_tip: str | bool = "auto",
                 tip_tolerance: float = TIP_TOLERANCE, stress_band_m: float | None = None,
                 rigid_stones: str | bool = "auto", use_influence: bool = True, *, compliance: np.ndarray | None = None,
                 tip: TipCompliance | None = None):
        t0 = time.perf_counter()
        if scene.analysis.formulation != "displacement":
            raise SceneError("analysis.formulation = 'mixed' covers load A only; contact (load B) uses the "
                             "displacement formulation: set formulation = \"displacement\" for indentation")
        self.scene = scene
        check_surface_budget(scene)
        self.model = model or build_model(scene, rigid_stones=rigid_stones)
        mesh = self.model.mesh
        t1 = time.perf_counter()
        keep = np.ones(self.model.n_dofs, bool)
        keep[_load_b_fixed(self.model)] = False
        free = np.flatnonzero(keep)          # (np.unique / np.setdiff1d would load numpy.ma: 7 ms of start-up)
        self.top = mesh.top
        self.x = mesh.nodes[self.top, 0]
        if np.diff(self.x).max() > scene.indenter.radius_m:   # a tip could fall between two top nodes
            raise SceneError(f"the top-surface node spacing {np.diff(self.x).max() * 1e3:.3g} mm exceeds the tip "
                             f"radius {scene.indenter.radius_m * 1e3:.3g} mm: contact would go unseen; refine the "
                             f"surface (smaller mesh_size_m or larger surface_refine)")
        self.top_red = self.model.reduced_index(2 * self.top + 1)
        self._free, self._fac = free, None
        self._interior, self._interior_tried = None, False
        self.interior_cache: tuple[dict, bool | None] | None = None     # (spec, use): where ``interior`` is kept
        if compliance is None:
            self._fac = condensation(self.model.K, free, self.top_red)
            compliance = self._fac.compliance
        if not np.all(np.isfinite(compliance)):
            raise FloatingPointError(f"the condensed surface compliance of scene {scene.name!r} is not finite")
        self.C = compliance                  # top-node downward displacement per downward nodal force (m per N/m)
        ind = scene.indenter
        self.tip_bound = rigid_tip_bound(scene)
        if ind.youngs_pa is None:
            self.rigid_tip, self.tip_note = True, "rigid tip (no modulus given)"
        elif rigid_tip is True or (rigid_tip == "auto" and self.tip_bound < tip_tolerance):
            self.rigid_tip = True
            self.tip_note = (f"tip treated as rigid: its deformation changes the force by about "
                             f"{self.tip_bound:.1e} (relative, Hertz estimate; measured in tests)")
        else:
            self.rigid_tip = False
            self.tip_note = "elastic tip (condensed tip compliance added)"
        self.tip = None if self.rigid_tip else (tip if tip is not None else TipCompliance.build(scene))
        self.band_m = stress_band_m if stress_band_m is not None else 2 * ind.radius_m
        self._band_ops = None
        self.use_influence = use_influence
        self._influence: Influence | bool | None = None
        self._influence_cache = None         # set by load_or_build_surface: the disk cache's entry for them
        self._gap_m: float | None = None     # the top nodes' widest spacing (a warm start's margin; _reach)
        self._cache_probed = False
        self.timings_s = {"mesh_assemble_s": t1 - t0, "factor_condense_s": time.perf_counter() - t1}

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The condensed operators: the surface compliance ``C`` and an elastic tip's (``tip_C``, ``tip_s``)."""
        arrays = {"C": self.C}
        if self.tip is not None:
            arrays.update({f"tip_{k}": v for k, v in self.tip.to_arrays().items()})
        return arrays

    @classmethod
    def from_arrays(cls, scene, arrays: dict[str, np.ndarray], model: Model, **options) -> SurfaceModel:
        """The SurfaceModel of ``scene`` on ``model`` with the operators ``to_arrays`` wrote (no factorization);
        ValueError if they do not fit the model."""
        C = arrays["C"]
        n_top = len(model.mesh.top)
        if C.shape != (n_top, n_top) or not np.all(np.isfinite(C)):
            raise ValueError(f"compliance of shape {C.shape}, expected ({n_top}, {n_top}) and finite")
        tip = None
        if "tip_C" in arrays:
            tip = TipCompliance.from_arrays({"C": arrays["tip_C"], "s": arrays["tip_s"]})
        return cls(scene, model=model, compliance=C, tip=tip, **options)

    @property
    def fac(self):
        """The condensation's factorization (``condensation``; made on first use when the compliance came from the
        disk cache): the fields' solver when the factor's interior columns cannot be had (``interior``)."""
        if self._fac is None:
            self._fac = condensation(self.model.K, self._free, self.top_red)
        return self._fac

    def interior(self):
        """The interior columns of K_ff's Cholesky factor with the top's vertical DOFs last (fem.interior_factor):
        from memory, the disk cache (kind ``factor``, keyed by the tissue: ``interior_cache``, set by
        load_or_build_surface) or one CHOLMOD factorization, then stored. A restored model's fields then cost
        C f and one backward sweep, with no assembly and no factorization. None without cvxopt or when CHOLMOD's
        factor cannot be read in place (tried once): the fields then come from ``fac``."""
        if self._interior is None and not self._interior_tried:
            self._interior_tried = True
            from .interior_factor import InteriorFactor  # scipy.linalg: only when a field is asked for
            pos = np.full(self.model.n_dofs, -1)
            pos[self._free] = np.arange(len(self._free))
            c = pos[self.top_red]

            def restore(arrays):
                f = InteriorFactor.from_arrays(arrays)
                if f.n != len(self._free) or not np.array_equal(f.p[f.n - f.nc:], c):
                    raise ValueError(f"a factor of {f.n} DOFs ({f.nc} on the top) that does not fit this model "
                                     f"({len(self._free)}, {len(c)})")
                if not np.isfinite(f.x).all():
                    raise ValueError("a factor with values that are not finite")
                return f

            def build():
                from .condense import interior_factor  # CHOLMOD: only to factorize
                f = interior_factor(self.model.K, self._free, self.top_red, ordering="amd")   # as condensation
                if f is None:
                    raise _NoFactor
                return f
            spec, use = self.interior_cache if self.interior_cache is not None else (None, False)
            try:
                self._interior = build() if spec is None else diskcache.load_or_build(
                    "factor", spec, build, to_arrays=InteriorFactor.to_arrays, from_arrays=restore, use=use)
            except _NoFactor:
                self._interior = None
        return self._interior

    # -- fields from contact forces (one back-substitution per waypoint, batched when many) ----------------------
    def displacements(self, F_top: np.ndarray) -> np.ndarray:
        """Full displacement vectors (2N, k) for downward nodal forces F_top (n_top, k) on the top nodes: the top's
        own from the compliance (-C F), the interior's by the stored factor's backward sweep (``interior``); else
        by the condensation's factorization (``fac``)."""
        F_top = np.asarray(F_top, dtype=float).reshape(len(self.top), -1)
        itf = self.interior()
        if itf is None:
            return condensed_displacements(self.model, self.fac, F_top)
        X = np.empty((itf.n, F_top.shape[1]))
        X[itf.p] = itf.sweep(-(self.C @ F_top))
        if not np.isfinite(X).all():
            raise FloatingPointError(f"scene {self.scene.name!r}: the displacements are not finite (a damaged disk "
                                     f"cache entry? delete it, or set PALPATE_CACHE=0)")
        Y = np.zeros((self.model.n_dofs, F_top.shape[1]))
        Y[self._free] = X
        return self.model.P @ Y

    def _band(self) -> tuple[np.ndarray, np.ndarray, object, object]:
        """(band nodes, their Poisson ratios, recovery operators on the full displacements: band, top)."""
        if self._band_ops is None:
            nodes = band_nodes(self.model, self.band_m)
            self._band_ops = (nodes, nodal_poisson(self.model, nodes), recovery_operator(self.model, nodes),
                              recovery_operator(self.model, self.top))
        return self._band_ops

    def influence(self, build: bool = True) -> Influence | None:
        """The influence operators (fem.influence): from the disk cache when this model came from it, else built
        (when ``build``); None when they would exceed fem.influence.MAX_OPERATOR_BYTES, are switched off, or are
        neither cached nor to be built. Building them costs about one back-substitution per top node (a few
        seconds on the paper scene, once per scene): worth it for INFLUENCE_MIN_WAYPOINTS waypoints or more."""
        if self._influence is None:
            if not (self.use_influence and fits(self.model, self.band_m, len(self.top))):
                self._influence = False
            elif self._influence_cache is not None and not self._cache_probed:
                self._cache_probed = True
                self._influence = self._influence_cache(None)
            if self._influence is None and build:
                make = lambda: Influence.build(self.model, self.band_m, self.x, self.scene.indenter.radius_m,  # noqa: E731
                                               self.displacements)
                self._influence = self._influence_cache(make) if self._influence_cache else make()
        return self._influence or None

    def _tip_stresses(self, sols, x0s, depths) -> list[tuple[float, int, np.ndarray] | None]:
        """Per waypoint with contact: (max von Mises over the band (Pa), the node where, sigma_yy at the window's
        top nodes), after the no-inversion check; None without contact. From the influence operators when the
        model has them, else from one batched back-substitution."""
        out: list = [None] * len(sols)
        hit = [k for k, (_, f, _) in enumerate(sols) if (f > 0).any()]
        if not hit:
            return out
        inf = self.influence(build=len(hit) >= INFLUENCE_MIN_WAYPOINTS)
        if inf is not None:
            where = {int(n): i for i, n in enumerate(inf.band)}
            top_rows = np.array([where[int(n)] for n in self.top])       # the top nodes lie in the band
            for k in hit:
                idx, f, _ = sols[k]
                inf.check(self.model, idx, f, float(x0s[k]), full=lambda: self._field(idx, f),
                          what=self._where([x0s[k]], [depths[k]]), hint=INVERSION_HINT)
                vm, span = inf.band_von_mises(self.model, idx, f, float(x0s[k]))
                j = int(np.argmax(vm))
                il, fl = inf.loaded(idx, f)
                syy = fl @ inf.A[inf.rows(il)][:, top_rows[idx], 1]
                out[k] = (float(vm[j]), int(inf.band[span][j]), syy)
            return out
        F = np.zeros((len(self.top), len(hit)))
        for c, k in enumerate(hit):
            idx, f, _ = sols[k]
            F[idx, c] = f
        nodes, nu, Rb, Rt = self._band()
        U = self.displacements(F)
        self.check_deformation(U, x0s[hit], depths[hit])
        vm = components(np.moveaxis((Rb @ U).reshape(len(nodes), 3, -1), 2, 0), nu[None, :],
                        self.model.plane)["von_mises_pa"]                                         # (k, n_band)
        St = (Rt @ U).reshape(len(self.top), 3, -1)
        for c, k in enumerate(hit):
            j = int(np.argmax(vm[c]))
            out[k] = (float(vm[c, j]), int(nodes[j]), St[sols[k][0], 1, c])
        return out

    def _field(self, idx: np.ndarray, f: np.ndarray) -> np.ndarray:
        F = np.zeros((len(self.top), 1))
        F[idx, 0] = f
        return self.displacements(F)[:, 0]

    # -- one waypoint --------------------------------------------------------------------------------------------
    def _window(self, x_m: float) -> np.ndarray:
        R = self.scene.indenter.radius_m
        return np.flatnonzero(np.abs(self.x - x_m) <= R)

    def contact_forces(self, x_m: float, depth_m: float, reach_m: float | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(window top-node indices, nodal forces per unit thickness (N/m), gaps (m)) for one waypoint. ``reach_m``:
        a guess of the contact's half-width (a neighbouring waypoint's at the same depth), the LCP's warm start
        within the overlap; the answer does not depend on it (the solver is exact from any start), only its
        iterations (5.5 -> about 2 on the paper scene)."""
        check_waypoint(self.scene, x_m, depth_m)
        idx = self._window(x_m)
        q = tip_profile(self.scene.indenter, x_m, depth_m, self.x[idx])
        if depth_m == 0.0 or not np.any(q < 0):
            return idx, np.zeros(len(idx)), q
        M = self.C[idx[0]:idx[-1] + 1, idx[0]:idx[-1] + 1]            # the window is contiguous (x sorted)
        if self.tip is not None:
            M = M + self.tip.compliance(self.x[idx] - x_m)
        start = q < 0
        if reach_m is not None:
            start &= np.abs(self.x[idx] - x_m) <= reach_m
        r = solve_lcp(M, q, start=start)
        return idx, r.z, r.w

    def force_n_per_m(self, x_m: float, depth_m: float) -> float:
        return check_finite(float(self.contact_forces(x_m, depth_m)[1].sum()),
                            f"scene {self.scene.name!r}: force at x_m={x_m}, depth_m={depth_m}")

    def force_n(self, x_m: float, depth_m: float) -> float:
        return self.force_n_per_m(x_m, depth_m) * self.scene.indenter.thickness_m

    def force_curve_n(self, x_m: float, depths_m) -> np.ndarray:
        """``force_n`` at one position for each of ``depths_m``: each depth's LCP starts from the contact the one
        before it reached (the same answers as one ``force_n`` per depth: the solver is exact from any start; the
        active-set steps fall about 3-fold on a rising depth sweep)."""
        out, reach = [], None
        for d in depths_m:
            idx, f, _ = self.contact_forces(float(x_m), float(d), reach)
            reach = self._reach(idx, f, x_m)
            out.append(check_finite(float(f.sum()), f"scene {self.scene.name!r}: force at x_m={x_m}, depth_m={d}"))
        return np.array(out) * self.scene.indenter.thickness_m

    def force_grid_n(self, x_m, depths_m) -> np.ndarray:
        """``force_n`` on a grid, (len(depths_m), len(x_m)), NaN where ``check_waypoint`` refuses the waypoint. Each
        position's depths run as ``force_curve_n``'s sweep, each LCP starting from the contact the depth before it
        reached: the same forces bit for bit as one ``force_n`` per waypoint (the same final active set solved the
        same way), in about a third of the active-set steps."""
        xs, ds = np.atleast_1d(np.asarray(x_m, float)), np.atleast_1d(np.asarray(depths_m, float))
        out = np.full((len(ds), len(xs)), np.nan)
        for b, x in enumerate(xs):
            reach = None
            for a, d in enumerate(ds):
                try:
                    idx, f, _ = self.contact_forces(float(x), float(d), reach)
                except ValueError:
                    reach = None
                    continue
                reach = self._reach(idx, f, float(x))
                out[a, b] = check_finite(float(f.sum()), f"scene {self.scene.name!r}: force at x_m={x}, depth_m={d}")
        return out * self.scene.indenter.thickness_m

    def _reach(self, idx: np.ndarray, f: np.ndarray, x_m: float) -> float | None:
        """A solved contact's half-width from the tip plus the top nodes' widest spacing (the next LCP's warm start
        for a neighbouring waypoint or a deeper indentation); None without contact."""
        on = f > 0
        if not on.any():
            return None
        if self._gap_m is None:
            self._gap_m = float(np.diff(self.x).max(initial=0.0))
        return float(np.abs(self.x[idx][on] - x_m).max()) + self._gap_m

    def indent(self, x_m: float, depth_m: float, stresses: bool = True) -> IndentResult:
        return self.indent_many([x_m], [depth_m], stresses=stresses)[0]

    def indent_many(self, x_m, depth_m, stresses: bool = True) -> list[IndentResult]:
        """Several waypoints; stresses from the influence operators (fem.influence), else one batched back-substitution."""
        x0s = np.atleast_1d(np.asarray(x_m, float))
        depths = np.broadcast_to(np.asarray(depth_m, float), x0s.shape)
        sols, reach = [], None
        for k, (x, d) in enumerate(zip(x0s, depths)):
            sols.append(self.contact_forces(float(x), float(d), reach if k and d == depths[k - 1] else None))
            reach = self._reach(sols[-1][0], sols[-1][1], x)
        tip = self._tip_stresses(sols, x0s, depths) if stresses else [None] * len(sols)
        out = []
        H = self.model.mesh.height_m
        for (idx, f, gap), x0, d, t in zip(sols, x0s, depths, tip):
            active = f > 0
            vm_max, at, pressure = 0.0, (float(x0), 0.0), np.zeros(len(idx))
            if t is not None:
                vm_max, node, syy = t
                at = (float(self.model.mesh.nodes[node, 0]), float(H - self.model.mesh.nodes[node, 1]))
                pressure = np.where(active, np.maximum(-syy, 0.0), 0.0)
            P = float(f.sum())
            out.append(IndentResult(x_m=float(x0), depth_m=float(d), force_n_per_m=P,
                                    force_n=P * self.scene.indenter.thickness_m, max_von_mises_pa=vm_max,
                                    max_von_mises_at_m=at, half_width_m=_half_width(self.x[idx], active),
                                    contact_x_m=self.x[idx], pressure_pa=pressure, nodal_force_n_per_m=f,
                                    gap_m=gap, rigid_tip=self.rigid_tip, tip_note=self.tip_note))
        return out

    def check_deformation(self, U: np.ndarray, x_m, depth_m) -> np.ndarray:
        """InvertedElementsError if the displacements U (2N,) or (2N, k) of the waypoints fold an element over;
        else the largest principal strain of each. A few ms on the paper scene; the force-only path (force_n)
        computes no displacements and relies on check_waypoint."""
        return check_not_inverted(self.model.mesh, U, self._where(x_m, depth_m), INVERSION_HINT)

    def _where(self, x_m, depth_m) -> str:
        where = ", ".join(f"(x_m={float(x):.4g}, depth_m={float(d):.4g})"
                          for x, d in zip(np.atleast_1d(x_m), np.atleast_1d(depth_m)))
        return f"scene {self.scene.name!r}: indentation at {where}"

    def depth_for_force(self, x_m: float, force_n: float, depth_max_m: float) -> float:
        """The depth at which the tip force reaches ``force_n`` (force is monotone in depth); depth_max_m if never."""
        if self.force_n(x_m, depth_max_m) <= force_n:
            return depth_max_m
        lo, hi = 0.0, depth_max_m
        while hi - lo > 1e-9 * depth_max_m:
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if self.force_n(x_m, mid) <= force_n else (lo, mid)
        return lo

    def full_field(self, x_m: float, depth_m: float) -> np.ndarray:
        """Full displacement vector (2N,) for one waypoint: one more back-substitution."""
        idx, f, _ = self.contact_forces(x_m, depth_m)
        F = np.zeros((len(self.top), 1))
        F[idx, 0] = f
        u = self.displacements(F)[:, 0]
        self.check_deformation(u, [x_m], [depth_m])
        return check_finite(u, f"scene {self.scene.name!r}: displacements at x_m={x_m}, depth_m={depth_m}")


def _half_width(xs: np.ndarray, active: np.ndarray) -> float:
    """Half the contact extent, edges placed midway between the outermost contact node and the next free one."""
    if not active.any():
        return 0.0
    lo, hi = np.flatnonzero(active)[[0, -1]]
    left = 0.5 * (xs[lo] + xs[lo - 1]) if lo > 0 else xs[lo]
    right = 0.5 * (xs[hi] + xs[hi + 1]) if hi < len(xs) - 1 else xs[hi]
    return 0.5 * (right - left)


# The tissue layer above a stone under the tip (its top depth, depth_m - radius) must keep at least a quarter of its
# thickness: an indentation deeper than STONE_LAYER_MAX times that layer is refused. Measured on the paper tissue
# with a rigid 10 mm stone under a 5 mm tip (fem.guards.deformation): at depth = the layer the largest strain is
# 24-39 % (layers 1-6 mm), at 0.75 of it below ~30 % (STRAIN_MAX); a 0.2 mm layer indented 4 mm folds elements over.
STONE_LAYER_MAX = 0.75


def check_depth(scene, depth_m: float) -> None:
    """ValueError unless depth_m lies in [0, STRAIN_MAX * height] and, for a round tip (a cylinder in 2D, a sphere
    in 3D), below its radius."""
    H = scene.tissue.height_m
    if not (isinstance(depth_m, (int, float)) and math.isfinite(depth_m)) or depth_m < 0.0:
        raise ValueError(f"depth_m={depth_m!r} must be a finite depth of 0 m or more")
    R = scene.indenter.radius_m
    round_tip = scene.indenter.shape in ("cylinder", "sphere")
    if round_tip and R <= STRAIN_MAX * H and depth_m >= R:      # the tighter bound first: the one to name
        raise ValueError(f"depth_m={depth_m} must be below the tip radius {R} m: deeper, tissue would wrap the "
                         f"tip's sides, which this contact model does not represent")
    if depth_m > STRAIN_MAX * H:
        raise ValueError(f"depth_m={depth_m} is {depth_m / H:.0%} of the tissue height {H} m: the linear model "
                         f"allows at most {STRAIN_MAX:.0%} (depth_m <= {STRAIN_MAX * H:.4g} m; stated for up to "
                         f"{STRAIN_WARN:.0%})")
    if round_tip and depth_m >= R:
        raise ValueError(f"depth_m={depth_m} must be below the tip radius {R} m: deeper, tissue would wrap the "
                         f"tip's sides, which this contact model does not represent")


def check_waypoint(scene, x_m: float, depth_m: float) -> None:
    """ValueError unless (x_m, depth_m) is a waypoint the contact model covers: x_m on the surface, depth in
    [0, STRAIN_MAX * height] (the linear model's range), for a cylinder below the tip radius, and for every stone
    under the tip's footprint (|x_stone - x_m| < tip radius + stone radius) at most STONE_LAYER_MAX times the
    tissue layer above it."""
    if not (isinstance(x_m, (int, float)) and math.isfinite(x_m)) or not (0.0 <= x_m <= scene.tissue.width_m):
        raise ValueError(f"x_m={x_m!r} must lie on the surface [0, {scene.tissue.width_m}] m")
    check_depth(scene, depth_m)
    R = scene.indenter.radius_m
    for i, s in enumerate(scene.stones):
        layer = s.depth_m - s.radius_m
        if abs(s.x_m - x_m) < R + s.radius_m and depth_m > STONE_LAYER_MAX * layer:
            raise ValueError(f"depth_m={depth_m} at x_m={x_m}: stone[{i}] under the tip lies {layer * 1e3:.3g} mm "
                             f"below the surface; the indentation must stay within {STONE_LAYER_MAX:.0%} of that "
                             f"layer (depth_m <= {STONE_LAYER_MAX * layer:.4g} m): deeper, the tissue is crushed "
                             f"against the stone, which the linear model does not represent")


def _surface_spec(scene, options: dict, code: str | None = None) -> dict:
    """What a SurfaceModel's operators depend on: the scene's content without what cannot change them (a tip fem
    treats as rigid shares the rigid tip's entry: fem.tip.contact_scene), the options, the code version (``code``,
    default fem.scene_mesh.code_version(); fem.contact3d gives its own)."""
    tip = {k: options[k] for k in ("rigid_tip", "tip_tolerance") if k in options}
    return {"scene": contact_scene(scene, **tip).key(), "options": options, "code": code or code_version()}


def surface_key(scene, options: dict) -> str:
    """The disk-cache key of a scene's SurfaceModel: the scene's content (not its name), options, code version."""
    return diskcache.digest(_surface_spec(scene, options))


def load_or_build_surface(scene, options: dict, use: bool | None = None) -> SurfaceModel:
    """A SurfaceModel restored from the disk cache (compliance, tip), else built and stored. use: None follows
    $PALPATE_CACHE, False skips the disk cache."""
    check_surface_budget(scene)
    model = build_model(scene, mesh=mesh_for(scene, use=use), rigid_stones=options.get("rigid_stones", "auto"))
    spec = _surface_spec(scene, options)
    sm = diskcache.load_or_build(
        "surface", spec, build=lambda: SurfaceModel(scene, model=model, **options),
        to_arrays=SurfaceModel.to_arrays,
        from_arrays=lambda arrays: SurfaceModel.from_arrays(scene, arrays, model=model, **options), use=use)
    ispec = {"surface": spec, "band_m": sm.band_m}
    read = lambda arrays: Influence.from_arrays(arrays, model, sm.band_m, len(sm.top))  # noqa: E731

    def influence_cache(build):
        """The influence operators from the disk cache (memory-mapped), else ``build()`` and stored; with
        build=None only what the cache holds (or None)."""
        if build is None:
            return diskcache.load("influence", ispec, read, use=use, mmap=True)
        return diskcache.load_or_build("influence", ispec, build=build, to_arrays=Influence.to_arrays,
                                       from_arrays=read, use=use, mmap=True)
    sm._influence_cache = influence_cache                                  # noqa: SLF001 (the cache's hook)
    sm.interior_cache = (_factor_spec(scene, options), use)                # the fields' factor (kind "factor")
    return sm


def _factor_spec(scene, options: dict) -> dict:
    """What the fields' factor depends on: the tissue and its stones (the stiffness and the top), whether stones are
    made rigid, fem's code and the factor's own (not the tip, the stress band or the use of influence operators:
    ``simulate`` and ``predict`` share one entry). The scene's content without its tip, as a dictionary: a scene
    with another tip would be validated against that tip (until session 60 the default 5 mm one, which refused every
    section under 10 mm wide)."""
    tissue = scene.to_dict()
    tissue.pop("name")
    tissue.pop("indenter")
    return {"tissue": tissue, "rigid_stones": options.get("rigid_stones", "auto"), "code": code_version(),
            "factor": _factor_version()}


@functools.lru_cache(maxsize=1)
def _factor_version() -> str:
    """The stored factor's own sources (not in the 2D code version, which keys the compliance): a key part of the
    ``factor`` entries."""
    return sources_version(("condense.py", "interior_factor.py"), "factor 1")


class _NoFactor(Exception):
    """CHOLMOD's factor cannot be had here (no cvxopt, or its layout unreadable): nothing to store."""


_CACHE: dict[tuple, SurfaceModel] = {}


def cached_keys() -> set:
    """The in-memory cache's keys now (for ``forget_except``)."""
    return set(_CACHE)


def forget_except(keys: set) -> None:
    """Drop the in-memory surface models not among ``keys`` (one-off scenes, e.g. a study's simulated truths:
    hundreds of MB otherwise)."""
    for k in list(_CACHE):
        if k not in keys:
            del _CACHE[k]


def surface_model(scene, cache: bool | None = None, **options) -> SurfaceModel:
    """The SurfaceModel of a scene, built once per scene content and options (in-memory cache), and kept on disk
    keyed by the scene's content (fem.diskcache; cache=None follows $PALPATE_CACHE, False: memory only)."""
    key = (scene.key(), tuple(sorted(options.items())))
    if key not in _CACHE:
        _CACHE[key] = load_or_build_surface(scene, options, use=cache)
    return _CACHE[key]


def indent_full(scene, x_m: float, depth_m: float, model: Model | None = None, max_iter: int = 50) -> dict:
    """The plain path: the full system solved with the contact nodes as Dirichlet conditions (u_y = tip profile),
    refactorized at every iteration of its own primal-dual active-set loop (add penetrating nodes, release nodes
    pulled by tension). No condensation and no LCP solver; rigid tip only. Used to check the fast path and as the
    "full re-solve per waypoint" baseline of the benchmark."""
    import scipy.sparse.linalg as spla
    check_waypoint(scene, x_m, depth_m)
    model = model or build_model(scene)
    mesh = model.mesh
    x = mesh.nodes[mesh.top, 0]
    q = tip_profile(scene.indenter, x_m, depth_m, x)
    top_red = model.reduced_index(2 * mesh.top + 1)
    base_fixed = _load_b_fixed(model)
    active = q < 0
    K = model.K
    for it in range(1, max_iter + 1):
        fixed = np.concatenate([base_fixed, top_red[active]])
        values = np.concatenate([np.zeros(len(base_fixed)), q[active]])
        free = np.setdiff1d(np.arange(model.n_dofs), fixed)
        u = np.zeros(model.n_dofs)
        u[fixed] = values
        lu = spla.splu(K[free][:, free].tocsc())
        u[free] = lu.solve(-(K[free][:, fixed] @ values))
        force = -(K @ u)[top_red]                 # downward force the tip applies at each top node
        force[~active] = 0.0
        gap = q - u[top_red]
        new = (active & (force >= 0)) | (~active & (gap < 0))
        if np.array_equal(new, active):
            break
        active = new
    else:
        raise RuntimeError(f"full contact solve did not settle in {max_iter} iterations")
    u_full = model.P @ u
    check_not_inverted(mesh, u_full, f"scene {scene.name!r}: indentation at (x_m={x_m}, depth_m={depth_m})",
                       INVERSION_HINT)
    check_finite(u_full, f"scene {scene.name!r}: displacements at x_m={x_m}, depth_m={depth_m}")
    P = float(force.sum())
    return {"x_m": x_m, "depth_m": depth_m, "force_n_per_m": P, "force_n": P * scene.indenter.thickness_m,
            "nodal_force_n_per_m": force, "gap_m": gap, "active": active, "u": u_full, "iterations": it}
