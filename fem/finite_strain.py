"""Total-Lagrangian finite-strain assembly of a 2D model: internal force and consistent tangent stiffness of a
hyperelastic tissue (fem.neohooke) on fem's P1/P2 triangle mesh, in the reduced DOFs of fem.model.Model (rigid
stones stay rigid bodies through its prolongation P).

Everything is integrated over the reference (undeformed) mesh with the quadrature of the linear model (degree
2 (p - 1)), so that at zero displacement the tangent is exactly the linear stiffness K (tests check it): the
finite-strain model differs from the linear one only by what finite strain changes.

    f_int[a, i] = sum_q w_q det_q P_iJ(F_q) dN_a/dX_J            F_q = I + sum_a u_a (x) dN_a/dX
    K_T[(a, i), (b, k)] = sum_q w_q det_q dN_a/dX_J A_iJkL(F_q) dN_b/dX_L

A rigid stone's nodes move with its three reduced DOFs linearly (u = t + theta x r, fem.model): under the tip the
paper stone turns by far less than 1e-3 rad, so the stretch this linearized rotation puts into its boundary, of
order theta^2, is below 1e-6 (stated, not modelled).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .assembly import element_dofs, gradients
from .elements import quadrature
from .model import Model, deformable_elements
from .neohooke import NeoHookean, stress_and_tangent

if TYPE_CHECKING:
    import scipy.sparse as sp


class FiniteStrainModel:
    """Internal force and tangent of a model's tissue (region 0; elastic stones of other regions with their own
    moduli; rigid stones through P) for a reduced displacement vector. The sparsity pattern and its scatter map are
    built once, so an assembly is a few vectorized products and one bincount."""

    def __init__(self, model: Model):
        import scipy.sparse as sp
        mesh = model.mesh
        if model.plane != "strain":
            raise ValueError(f"the neo-Hookean model is plane strain; the scene's analysis.plane is {model.plane!r}")
        self.model = model
        self.elements = deformable_elements(mesh.region, model.rigid)
        pts, w = quadrature(2 * (mesh.order - 1))
        G, det = gradients(mesh, pts)
        self.G = G[self.elements]                                      # (M, q, nen, 2) dN/dX
        self.wdet = (det * w)[self.elements]                           # (M, q)
        self.dofs = element_dofs(mesh)[self.elements]                  # (M, 2 nen)
        mats = [NeoHookean.from_youngs(m.youngs_pa, m.poisson) for m in model.materials]
        reg = mesh.region[self.elements]
        self.mu = np.array([m.mu_pa for m in mats])[reg][:, None]       # (M, 1): per element, broadcast over q
        self.lam = np.array([m.lambda_pa for m in mats])[reg][:, None]
        ne = self.dofs.shape[1]
        n = mesh.n_dofs
        keys = np.repeat(self.dofs, ne, axis=1).ravel() * n + np.tile(self.dofs, (1, ne)).ravel()
        uniq, self._scatter = np.unique(keys, return_inverse=True)       # sorted: CSR order
        rows, cols = np.divmod(uniq, n)
        indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=n))])
        self._pattern = sp.csr_matrix((np.zeros(len(uniq)), cols, indptr), shape=(n, n))
        self.P = model.P
        self.n_full = n

    def deformation_gradients(self, u_full: np.ndarray) -> np.ndarray:
        """F (M, q, 2, 2) at the quadrature points for full displacements u (2N,)."""
        ue = u_full[self.dofs].reshape(len(self.dofs), -1, 2)            # (M, nen, 2)
        return np.eye(2) + np.einsum("mai,mqaJ->mqiJ", ue, self.G)

    def internal_force(self, a: np.ndarray) -> np.ndarray:
        """Reduced internal force vector (n_red,) at reduced displacements ``a``."""
        return self.assemble(a, tangent=False)[0]

    def assemble(self, a: np.ndarray, tangent: bool = True) -> tuple[np.ndarray, sp.csc_matrix | None]:
        """(f_int, K_T) in the reduced DOFs at reduced displacements ``a`` (K_T None without ``tangent``)."""
        u = self.P @ a
        F = self.deformation_gradients(u)
        P, A = stress_and_tangent(F, self.mu, self.lam, tangent)
        fe = np.einsum("mq,mqiJ,mqaJ->mai", self.wdet, P, self.G, optimize=True).reshape(len(self.dofs), -1)
        f = np.bincount(self.dofs.ravel(), weights=fe.ravel(), minlength=self.n_full)
        f = self.P.T @ f
        if not tangent:
            return f, None
        Ke = np.einsum("mq,mqaJ,mqiJkL,mqbL->maibk", self.wdet, self.G, A, self.G, optimize=True)
        ne = self.dofs.shape[1]
        K = self._pattern.copy()
        K.data = np.bincount(self._scatter, weights=Ke.reshape(len(self.dofs), ne * ne).ravel(),
                             minlength=len(K.data))
        if any(self.model.rigid):
            K = self.P.T @ K @ self.P
        return f, K.tocsc()
