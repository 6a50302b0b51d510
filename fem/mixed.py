"""Locking-free load A: mixed displacement-pressure (u-p) Taylor-Hood triangles, P2 displacement / P1 pressure.

As nu -> 0.5 the bulk modulus grows without bound and displacement elements lock: P1 triangles cannot represent
near-incompressible deformation at all, P2 deformations are fine but their pressures (hence stresses) oscillate.
The mixed form keeps the pressure p = kappa div u as its own field (3D bulk modulus kappa = E / (3 (1 - 2 nu)),
plane strain):

    [ A   B^T ] [u]   [f]      A = int 2G dev(eps(u)) : dev(eps(v)),   B = int q div v,   M = int p q / kappa
    [ B   -M  ] [p] = [0]      sigma = 2G dev(eps) + p I  (in-plane),  sigma_zz = -2G tr(eps)/3 + p

which stays well posed at nu = 0.5 (M -> 0) and satisfies the inf-sup condition (Taylor-Hood). Pressure is
continuous within each region and independent across a tissue/stone interface (it jumps there). Rigid stones are
reduced exactly as in fem.model (the prolongation P). Selected by ``[analysis] formulation = "mixed"`` (needs
order 2 and plane strain); fem.uniform.solve_uniform dispatches here. Load B (contact) uses the displacement
formulation only.
"""
from __future__ import annotations

import time
import warnings

import numpy as np

from .assembly import element_dofs, gradients, stiffness, strain_matrices
from .elements import quadrature, shape
from .model import Model, build_model, deformable_elements
from .results import Profile, UniformResult
from .rigid_stress import stone_fields
from .stress import components, nodal_poisson, recovery_operator

_M = np.array([1.0, 1.0, 0.0])
# above this stiffness ratio an elastic stone's stresses lose digits in the saddle-point solve (measured on a paper-like
# scene against the displacement formulation: within 3 Pa of 500 up to 1e5, 6.6 kPa off at 2e6); the tissue's do not
MIXED_ELASTIC_STONE_WARN = 1e5
_DEV = np.array([[2 / 3, -1 / 3, 0.0], [-1 / 3, 2 / 3, 0.0], [0.0, 0.0, 0.5]])   # times 2G


def moduli(material) -> tuple[float, float]:
    """(shear modulus G, 3D bulk modulus kappa)."""
    E, nu = material.youngs_pa, material.poisson
    return E / (2 * (1 + nu)), E / (3 * (1 - 2 * nu))


class MixedSystem:
    """The assembled Taylor-Hood system of a model (order 2, plane strain), rigid stones reduced."""

    def __init__(self, model: Model):
        mesh = model.mesh
        if mesh.order != 2 or model.plane != "strain":
            raise ValueError("the mixed formulation needs P2 triangles and plane strain")
        self.model = model
        self.els = deformable_elements(mesh.region, model.rigid)
        tris, region = mesh.tris[self.els], mesh.region[self.els]
        G_, k_ = np.array([moduli(m) for m in model.materials]).T
        G, kappa = G_[region], k_[region]
        # pressure DOFs: one per (region, vertex)
        vkey = region[:, None] * mesh.n_nodes + tris[:, :3]
        self.pkeys, pdof = np.unique(vkey, return_inverse=True)
        pdof = pdof.reshape(-1, 3)
        self.pdof = pdof
        self.n_p = len(self.pkeys)
        pts, w = quadrature(2)
        sub = type(mesh)(nodes=mesh.nodes, tris=tris, region=region, order=2, width_m=mesh.width_m,
                         height_m=mesh.height_m, top=mesh.top, bottom=mesh.bottom)
        Gr, det = gradients(sub, pts)
        Bm = strain_matrices(Gr)                                            # (m, q, 3, 12)
        wd = det * w                                                        # (m, q)
        Ae = np.einsum("mq,m,mqki,kl,mqlj->mij", wd, 2 * G, Bm, _DEV, Bm, optimize=True)
        Np = shape(1, pts)                                                  # (q, 3)
        divB = np.einsum("k,mqki->mqi", _M, Bm)                             # (m, q, 12)
        Be = np.einsum("mq,qa,mqi->mai", wd, Np, divB, optimize=True)       # (m, 3, 12)
        Me = np.einsum("mq,m,qa,qb->mab", wd, 1.0 / kappa, Np, Np, optimize=True)
        import scipy.sparse as sp
        udof = element_dofs(sub)
        n = mesh.n_dofs
        A = sp.csr_matrix((Ae.ravel(), (np.repeat(udof, 12, 1).ravel(), np.tile(udof, (1, 12)).ravel())), (n, n))
        B = sp.csr_matrix((Be.ravel(), (np.repeat(pdof, 12, 1).ravel(), np.tile(udof, (1, 3)).ravel())),
                          (self.n_p, n))
        M = sp.csr_matrix((Me.ravel(), (np.repeat(pdof, 3, 1).ravel(), np.tile(pdof, (1, 3)).ravel())),
                          (self.n_p, self.n_p))
        P = model.P
        self.A_full, self.B_full = A, B          # the tissue's internal force at full DOFs (fem.rigid_stress)
        self.A = (P.T @ A @ P).tocsr()
        self.B = (B @ P).tocsr()
        self.M = M
        self.K = sp.bmat([[self.A, self.B.T], [self.B, -M]], format="csc")  # symmetric indefinite
        self.G_node, self.kappa = G_, k_

    @property
    def n_u(self) -> int:
        return self.A.shape[0]

    def solve(self, fixed: np.ndarray, values: np.ndarray, load: np.ndarray | None = None):
        """(u_red, p) with reduced displacement DOFs ``fixed`` prescribed to ``values``; also the relative residual."""
        n = self.n_u + self.n_p
        fixed = np.asarray(fixed)
        mask = np.ones(n, bool)
        mask[fixed] = False
        free = np.flatnonzero(mask)
        x = np.zeros(n)
        import scipy.sparse.linalg as spla
        x[fixed] = values
        rhs = -(self.K @ x)
        if load is not None:
            rhs[: self.n_u] += load
        Kff = self.K[free][:, free].tocsc()
        b = rhs[free]
        nb = max(np.linalg.norm(b), 1e-300)
        # Symmetric fill-reducing order without pivoting (3x less fill than COLAMD with pivoting), one step of
        # iterative refinement, and the pivoting factorization as a fallback if the residual says so.
        for spec, opts in (("MMD_AT_PLUS_A", {"diag_pivot_thresh": 0.0, "options": {"SymmetricMode": True}}),
                           ("COLAMD", {})):
            with np.errstate(all="ignore"):
                lu = spla.splu(Kff, permc_spec=spec, **opts)
                y = lu.solve(b)
                y += lu.solve(b - Kff @ y)
                res = np.linalg.norm(Kff @ y - b) / nb
            if np.all(np.isfinite(y)) and res < 1e-10:
                break
        if not np.all(np.isfinite(y)):
            raise FloatingPointError("the mixed u-p solve produced non-finite values")
        x[free] = y
        self.residual = float(res)
        return x[: self.n_u], x[self.n_u:]

    def nodal_pressure(self, p: np.ndarray, nodes: np.ndarray) -> np.ndarray:
        """P1 pressure interpolated at the nodes (vertices and mid-edges) from each node's primary region."""
        mesh = self.model.mesh
        tris, region = mesh.tris[self.els], mesh.region[self.els]
        primary = np.full(mesh.n_nodes, np.iinfo(np.int64).max)
        np.minimum.at(primary, mesh.tris.ravel(), np.repeat(mesh.region, mesh.tris.shape[1]))
        pv = p[self.pdof]                                                     # (m, 3) vertex pressures
        local = np.column_stack([pv, 0.5 * (pv[:, 0] + pv[:, 1]), 0.5 * (pv[:, 1] + pv[:, 2]),
                                 0.5 * (pv[:, 2] + pv[:, 0])])               # (m, 6)
        out = np.full(mesh.n_nodes, np.nan)
        ok = region[:, None] == primary[tris]
        out[tris[ok]] = local[ok]
        return out[nodes]

    def stresses(self, u_full: np.ndarray, p: np.ndarray, nodes: np.ndarray) -> dict[str, np.ndarray]:
        """Nodal stresses at ``nodes``: sigma = 2G dev(eps) + p I, from the node's primary region."""
        model = self.model
        eps = (recovery_operator(model, nodes, strain=True) @ u_full).reshape(-1, 3)
        nu = nodal_poisson(model, nodes)
        mesh = model.mesh
        primary = np.full(mesh.n_nodes, np.iinfo(np.int64).max)
        np.minimum.at(primary, mesh.tris.ravel(), np.repeat(mesh.region, mesh.tris.shape[1]))
        G = self.G_node[primary[nodes]]
        pn = self.nodal_pressure(p, nodes)
        s = 2 * G[:, None] * (eps @ _DEV.T) + pn[:, None] * _M
        tr = eps[:, 0] + eps[:, 1]
        szz = -2 * G * tr / 3 + pn
        sxx, syy, sxy = s.T
        vm = np.sqrt(0.5 * ((sxx - syy) ** 2 + (syy - szz) ** 2 + (szz - sxx) ** 2) + 3.0 * sxy ** 2)
        out = {"sxx_pa": sxx, "syy_pa": syy, "sxy_pa": sxy, "szz_pa": szz, "von_mises_pa": vm, "p_pa": pn}
        out["nu"] = nu
        return out


def solve_uniform_mixed(scene, model: Model | None = None, full_field: bool = True,
                        rigid_stones: str | bool = "auto") -> UniformResult:
    """Load A with the mixed formulation; returns fem.results.UniformResult (surface profile from the mixed
    stresses; ``timings_s['residual']`` is the relative residual of the saddle-point solve)."""
    t0 = time.perf_counter()
    model = model or build_model(scene, rigid_stones=rigid_stones)
    sysm = MixedSystem(model)
    t1 = time.perf_counter()
    mesh = model.mesh
    top, bot = mesh.top, mesh.bottom
    fixed_full = np.concatenate([2 * top + 1, 2 * bot + 1, [2 * bot[0]]])
    values = np.concatenate([np.full(len(top), -scene.analysis.top_displacement_m), np.zeros(len(bot) + 1)])
    fixed = model.reduced_index(fixed_full)
    u_red, p = sysm.solve(fixed, values)
    u = model.P @ u_red
    t2 = time.perf_counter()
    react = -(sysm.A @ u_red + sysm.B.T @ p)[model.reduced_index(2 * top + 1)].sum()
    surf = sysm.stresses(u, p, top)
    surf.pop("nu")
    nodal = None
    if full_field:
        nodal = sysm.stresses(u, p, np.arange(mesh.n_nodes))
        nu = nodal.pop("nu")
        eps = (recovery_operator(model, strain=True) @ u).reshape(-1, 3)
        got = stone_fields(model, u, stiffness, recovery_operator, 2, sysm.A_full @ u + sysm.B_full.T @ p)
        if got is not None:     # a rigid stone's inside (no pressure unknowns there): fem.rigid_stress
            nodes, s3, e3 = got
            eps[nodes] = e3
            c = components(s3, nu[nodes], model.plane)
            c["p_pa"] = (c["sxx_pa"] + c["syy_pa"] + c["szz_pa"]) / 3.0
            for k, v in c.items():
                nodal[k][nodes] = v
        ratio = max((m.youngs_pa / model.materials[0].youngs_pa for m, r in zip(model.materials[1:], model.rigid)
                     if not r), default=0.0)
        if ratio > MIXED_ELASTIC_STONE_WARN:
            warnings.warn(f"scene {scene.name!r}: an elastic stone {ratio:.1e}x stiffer than the tissue in the mixed "
                          f"formulation: the stone's own stresses lose digits (measured: 13x off at 2e6 against "
                          f"the displacement formulation; the tissue's within 1e-4); the default stones='auto' makes "
                          f"it rigid and recovers them exactly", stacklevel=3)
        nodal.update({"exx": eps[:, 0], "eyy": eps[:, 1], "gxy": eps[:, 2]})
    t3 = time.perf_counter()
    surf_fields = {k: v for k, v in surf.items() if k != "p_pa"}
    return UniformResult(model=model, u=u, surface=Profile(mesh.nodes[top, 0], surf_fields), nodal=nodal,
                         timings_s={"mesh_assemble_s": t1 - t0, "solve_s": t2 - t1, "recover_s": t3 - t2,
                                    "residual": sysm.residual},
                         reaction_n_per_m=float(react), residual=sysm.residual)
