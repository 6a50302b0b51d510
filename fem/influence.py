"""Stresses under the tip and the no-inversion check at the cost of forces: influence operators of the top nodes.

Every field of load B is linear in the contact forces on the top nodes: u = Y f, where column j of Y is the
displacement under a unit downward force (per unit thickness) on top node j. Built once per scene (batched
back-substitutions, ``CHUNK`` top nodes at a time) and kept on disk with the surface model, these operators replace
the per-waypoint back-substitution:

- ``A`` (n_top, n_band, 3): the recovered stresses (fem.stress) at the band nodes (within ``band_m`` of the
  surface, sorted by x) per unit force on each top node. A waypoint's stresses are f @ A[window]: only its contact
  window's rows, and only the band nodes within ``window_m`` of the tip in x. The maximum von Mises over that
  window is the maximum over the whole band whenever no node outside it can exceed it: von Mises is a seminorm of
  the stress (the square root of a positive semi-definite quadratic form), so at any node vm(sum_j f_j A_j) <=
  sum_j |f_j| vm(A_j), and ``vm_far[j]`` stores the largest vm(A_j) over the band nodes farther than
  window_m - R from top node j in x (every node outside the window is, since the contact window lies within R of
  the tip). When sum_j |f_j| vm_far[j] reaches the window's maximum, the whole band is evaluated instead.
- ``g`` (n_top, n_elements): for each top node j and element e, the largest Frobenius norm of the displacement
  gradient H_e^j over the element's check points (fem.guards: quadrature points and nodes). The deformed Jacobian
  there is J0 (I + H), and det(I + H) > 0 whenever ||H||_2 < 1 (the singular values of I + H are at least
  1 - ||H||_2); ||H_e(f)||_2 <= ||H_e(f)||_F <= sum_j |f_j| g_je. Elements whose centroid lies within window_m of
  the tip get this bound from their own columns; all others share ``g_far[j]`` (the largest g_je over elements
  farther than window_m - R from top node j). Elements whose bound reaches 1 (under the tip, in practice) are
  checked exactly from their nodes' displacements (``Y_c``: the rows of Y for the nodes of the band's elements),
  and any other flagged element, or a far bound reaching 1, falls back to the exact check on a full
  back-substitution. The check is the plain one (fem.guards.check_not_inverted) at the same check points, never
  weaker.

The answers are those of the batched back-substitution to round-off (tests/test_influence.py). Memory:
(3 n_band + 2 n_closure + n_elements) x n_top doubles (about 70 MB on the paper scene); models whose operators
would exceed ``MAX_OPERATOR_BYTES`` keep the back-substitution (``fits``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .guards import check_points, deformation, det_and_strain, displacement_gradients, inverted_error
from .model import Model
from .stress import components, nodal_poisson, recovery_operator

MAX_OPERATOR_BYTES = 400e6
CHUNK = 32                     # top nodes per back-substitution block while building
WINDOW_R = 2.0                 # the stress and inversion window's half-width, in tip radii


def band_nodes(model: Model, band_m: float) -> np.ndarray:
    """The nodes within band_m of the surface, sorted by x (the order the maximum von Mises is searched in)."""
    mesh = model.mesh
    nodes = np.flatnonzero(mesh.nodes[:, 1] >= mesh.height_m - band_m - 1e-12)
    return nodes[np.argsort(mesh.nodes[nodes, 0], kind="stable")]


def _closure(model: Model, nodes: np.ndarray) -> np.ndarray:
    """The nodes of every element that has a node among ``nodes``."""
    mesh = model.mesh
    mark = np.zeros(mesh.n_nodes, bool)
    mark[nodes] = True
    out = np.zeros(mesh.n_nodes, bool)
    out[mesh.tris[mark[mesh.tris].any(axis=1)]] = True
    return np.flatnonzero(out)          # sorted and unique, as np.unique's (which would load numpy.ma: 7 ms)


def operator_bytes(model: Model, band_m: float, n_top: int) -> float:
    band = band_nodes(model, band_m)
    return 8.0 * n_top * (3 * len(band) + 2 * len(_closure(model, band)) + len(model.mesh.tris))


def fits(model: Model, band_m: float, n_top: int) -> bool:
    return operator_bytes(model, band_m, n_top) <= MAX_OPERATOR_BYTES


def _far_max(values: np.ndarray, x_from: np.ndarray, x_at: np.ndarray, dist_m: float) -> np.ndarray:
    """For each row j: the largest values[j, n] over the columns n with |x_at[n] - x_from[j]| > dist_m (0 if none)."""
    far = np.abs(x_at[None, :] - x_from[:, None]) > dist_m
    return np.where(far, values, 0.0).max(axis=1, initial=0.0)


@dataclass
class Influence:
    """The operators (see the module's docstring) and the per-waypoint evaluations that read them."""
    window_m: float
    band: np.ndarray          # band nodes sorted by x (n_b,)
    A: np.ndarray             # (n_top, n_b, 3) band stresses per unit top-node force
    vm_far: np.ndarray        # (n_top,)
    els: np.ndarray           # elements sorted by centroid x (M,)
    g: np.ndarray             # (n_top, M) gradient bound per unit top-node force, columns in ``els`` order
    g_far: np.ndarray         # (n_top,)
    cnodes: np.ndarray        # the band elements' nodes (n_c,)
    Y_c: np.ndarray           # (n_c, 2, n_top) their displacements per unit top-node force (node-major)
    _geo: dict = field(default_factory=dict, repr=False)     # per-model lookups, made on first use

    def _lookups(self, model: Model) -> dict:
        """Per-model arrays the waypoints read: band x and Poisson ratios, element centroids x, and for the exact
        check of flagged elements their Y_c slots and gradient operators (H = sum_a u_a (x) Bg_a at each check
        point: Bg = the shape gradients through J0^-1, as fem.guards.displacement_gradients computes H)."""
        if not self._geo:
            mesh = model.mesh
            pos = np.full(mesh.n_nodes, -1)
            pos[self.cnodes] = np.arange(len(self.cnodes))
            G, J0 = check_points(mesh, self.els)
            d0 = J0[..., 0, 0] * J0[..., 1, 1] - J0[..., 0, 1] * J0[..., 1, 0]
            inv = np.stack([np.stack([J0[..., 1, 1], -J0[..., 0, 1]], -1),
                            np.stack([-J0[..., 1, 0], J0[..., 0, 0]], -1)], -2) / d0[..., None, None]
            cslot = pos[mesh.tris[self.els]]
            self._geo.update(bx=mesh.nodes[self.band, 0], nu=nodal_poisson(model, self.band),
                             cx=mesh.nodes[mesh.tris[self.els], 0].mean(axis=1), G=G, J0=J0, cslot=cslot,
                             in_closure=(cslot >= 0).all(axis=1), Bg=G[None] @ inv)            # (M, q, a, 2)
        return self._geo

    @classmethod
    def build(cls, model: Model, band_m: float, x_top: np.ndarray, radius_m: float, displacements) -> Influence:
        """``displacements(F_top)``: full displacement vectors (2N, k) for top-node forces (n_top, k)."""
        mesh = model.mesh
        n_top = len(x_top)
        band = band_nodes(model, band_m)
        cnodes = _closure(model, band)
        cd = np.stack([2 * cnodes, 2 * cnodes + 1], axis=1).ravel()
        cx = mesh.nodes[mesh.tris, 0].mean(axis=1)
        els = np.argsort(cx, kind="stable")
        Rb = recovery_operator(model, band)
        G, J0 = check_points(mesh, els)
        A = np.empty((n_top, len(band), 3))
        g = np.empty((n_top, len(els)))
        Y_c = np.empty((len(cnodes), 2, n_top))
        for a in range(0, n_top, CHUNK):
            cols = np.arange(a, min(a + CHUNK, n_top))
            E = np.zeros((n_top, len(cols)))
            E[cols, np.arange(len(cols))] = 1.0
            U = displacements(E)                                                          # (2N, k)
            A[cols] = (Rb @ U).T.reshape(len(cols), len(band), 3)
            Y_c[:, :, cols] = U[cd].reshape(len(cnodes), 2, len(cols))
            H = displacement_gradients(U.reshape(mesh.n_nodes, 2, -1)[mesh.tris[els]], G, J0)  # (k, M, q, 2, 2)
            g[cols] = np.sqrt((H ** 2).sum(axis=(-2, -1))).max(axis=2)
        window_m = WINDOW_R * radius_m
        vm = components(A, nodal_poisson(model, band)[None, :], model.plane)["von_mises_pa"]   # (n_top, n_b)
        vm_far = _far_max(vm, x_top, mesh.nodes[band, 0], window_m - radius_m)
        g_far = _far_max(g, x_top, cx[els], window_m - radius_m)
        return cls(window_m=window_m, band=band, A=A, vm_far=vm_far, els=els, g=g, g_far=g_far, cnodes=cnodes,
                   Y_c=Y_c)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"window_m": np.array(self.window_m), "band": self.band, "A": self.A, "vm_far": self.vm_far,
                "els": self.els, "g": self.g, "g_far": self.g_far, "cnodes": self.cnodes, "Y_c": self.Y_c}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], model: Model, band_m: float, n_top: int) -> Influence:
        band = band_nodes(model, band_m)
        # memory maps as plain arrays (no copy; np.memmap's indexing costs ~20 us a call in Python)
        inf = cls(window_m=float(arrays["window_m"]), **{k: np.asarray(arrays[k]) for k in
                                                          ("band", "A", "vm_far", "els", "g", "g_far", "cnodes",
                                                           "Y_c")})
        M = len(model.mesh.tris)
        if not (np.array_equal(inf.band, band) and inf.A.shape == (n_top, len(band), 3)
                and inf.g.shape == (n_top, M) and inf.Y_c.shape == (len(inf.cnodes), 2, n_top)):
            raise ValueError("influence operators do not fit the model")
        if not (np.all(np.isfinite(inf.vm_far)) and np.all(np.isfinite(inf.g_far))):
            raise ValueError("influence operators are not finite")
        # The large operators arrive memory-mapped (read in part, as waypoints need them): not scanned here; every
        # number that leaves fem is checked finite (fem.guards.check_finite).
        return inf

    @staticmethod
    def loaded(idx: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(idx, f) without the window's unloaded ends (zero forces add exactly nothing: fewer rows to read)."""
        nz = np.flatnonzero(f)
        if not len(nz) or (nz[0] == 0 and nz[-1] == len(f) - 1):
            return idx, f
        return idx[nz[0]:nz[-1] + 1], f[nz[0]:nz[-1] + 1]

    @staticmethod
    def rows(idx: np.ndarray):
        """Top-node indices as a slice when contiguous (the contact window always is: views, no copies)."""
        return slice(int(idx[0]), int(idx[-1]) + 1) if len(idx) and idx[-1] - idx[0] == len(idx) - 1 else idx

    def _span(self, x_sorted: np.ndarray, x0: float) -> slice:
        return slice(int(np.searchsorted(x_sorted, x0 - self.window_m, "left")),
                     int(np.searchsorted(x_sorted, x0 + self.window_m, "right")))

    def band_von_mises(self, model: Model, idx: np.ndarray, f: np.ndarray, x0: float) -> tuple[np.ndarray, slice]:
        """(von Mises (Pa) at the band nodes self.band[span], span) for forces f on top nodes idx at tip x0: the
        window's nodes when they hold the band's maximum for certain, else the whole band."""
        geo = self._lookups(model)
        idx, f = self.loaded(idx, f)
        idx = self.rows(idx)
        span = self._span(geo["bx"], x0)
        W = self.A[idx, span]                                     # (j, b, 3): a view (idx and span are slices)
        S = (f @ W.reshape(len(f), -1)).reshape(-1, 3)            # one BLAS product over the window, no copy
        vm = components(S, geo["nu"][span], model.plane)["von_mises_pa"]
        if vm.size and float(np.abs(f) @ self.vm_far[idx]) < vm.max():
            return vm, span
        S = (f @ self.A[idx].reshape(len(f), -1)).reshape(-1, 3)
        return components(S, geo["nu"], model.plane)["von_mises_pa"], slice(0, len(self.band))

    def check(self, model: Model, idx: np.ndarray, f: np.ndarray, x0: float, full, what: str, hint: str) -> None:
        """InvertedElementsError (naming ``what``) if forces f on top nodes idx fold an element; ``full()``: the
        full displacement vector, for an exact check beyond what the operators cover."""
        mesh = model.mesh
        geo = self._lookups(model)
        idx, f = self.loaded(idx, f)
        a = np.abs(f)
        idx = self.rows(idx)
        span = self._span(geo["cx"], x0)
        flag = np.flatnonzero(a @ self.g[idx, span] >= 1.0) + span.start       # positions in self.els
        if float(a @ self.g_far[idx]) < 1.0 and geo["in_closure"][flag].all():
            if not len(flag):
                return
            slots = geo["cslot"][flag]                                         # (n, a): rows of Y_c
            Y = self.Y_c[slots.ravel(), :, idx] if isinstance(idx, slice) else self.Y_c[slots.ravel()][:, :, idx]
            U_el = (Y @ f).reshape(*slots.shape, 2)
            H = np.swapaxes(U_el, 1, 2)[:, None] @ geo["Bg"][flag]              # (n, q, 2, 2)
            if ((1 + H[..., 0, 0]) * (1 + H[..., 1, 1]) - H[..., 0, 1] * H[..., 1, 0] > 0).all():
                return                                                         # det J = det J0 det(I + H) > 0
            det, strain = det_and_strain(H[None], geo["J0"][flag])
        else:                                                      # beyond the operators: the plain check
            det, strain = deformation(mesh, np.asarray(full()), elements=None)
        bad = ~(det[0] > 0)
        if bad.any():
            raise inverted_error(what, hint, int(bad.sum()), len(mesh.tris), float(strain[0].max()))
