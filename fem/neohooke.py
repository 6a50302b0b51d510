"""A compressible neo-Hookean material in plane strain: strain energy, first Piola-Kirchhoff stress and its
consistent tangent, vectorized over any number of deformation gradients.

    W(F) = mu/2 (I1 - 3) - mu ln J + lambda/2 (ln J)^2,     I1 = tr(F^T F) + 1 (F_33 = 1),  J = det F

with the Lame constants of the linear model, mu = E / (2 (1 + nu)) and lambda = E nu / ((1 + nu) (1 - 2 nu)): at
small strain W is linear elasticity's energy, so the model reduces to fem's linear plane-strain model (tests check
both the tangent at F = I and the force at small indentation). Why this form: it is polyconvex, its stress is
finite for every J > 0 and infinite as J -> 0 (no element can be squeezed through zero volume), and it has one
parameter pair, the one the scene already gives.

    P = mu (F - F^-T) + lambda ln J F^-T
    A_iJkL = dP_iJ / dF_kL = mu d_ik d_JL + (mu - lambda ln J) F^-1_Li F^-1_Jk + lambda F^-1_Ji F^-1_Lk
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class NeoHookean:
    mu_pa: float          # shear modulus
    lambda_pa: float      # Lame's first constant

    @classmethod
    def from_youngs(cls, youngs_pa: float, poisson: float) -> NeoHookean:
        """The material with the small-strain moduli E, nu (the linear model's)."""
        return cls(youngs_pa / (2 * (1 + poisson)), youngs_pa * poisson / ((1 + poisson) * (1 - 2 * poisson)))

    def energy(self, F: np.ndarray) -> np.ndarray:
        """W (J/m^3) per deformation gradient F (..., 2, 2)."""
        lnJ = np.log(determinant(F))
        I1 = np.einsum("...ij,...ij->...", F, F) + 1.0
        return 0.5 * self.mu_pa * (I1 - 3.0) - self.mu_pa * lnJ + 0.5 * self.lambda_pa * lnJ ** 2

    def stress(self, F: np.ndarray) -> np.ndarray:
        """First Piola-Kirchhoff stress P (..., 2, 2) (force per reference area)."""
        return first_piola(F, self.mu_pa, self.lambda_pa)

    def tangent(self, F: np.ndarray) -> np.ndarray:
        """A (..., 2, 2, 2, 2) = dP_iJ / dF_kL, the consistent tangent of ``stress``."""
        return stress_and_tangent(F, self.mu_pa, self.lambda_pa)[1]

    def cauchy(self, F: np.ndarray) -> np.ndarray:
        """In-plane Cauchy stress sigma = P F^T / J (..., 2, 2)."""
        return np.einsum("...iJ,...kJ->...ik", self.stress(F), F) / determinant(F)[..., None, None]


def first_piola(F: np.ndarray, mu, lam) -> np.ndarray:
    """P (..., 2, 2) for moduli ``mu``, ``lam`` broadcastable against F's leading shape (per element, say)."""
    return stress_and_tangent(F, mu, lam, tangent=False)[0]


def stress_and_tangent(F: np.ndarray, mu, lam, tangent: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """(P (..., 2, 2), A (..., 2, 2, 2, 2) or None) for moduli broadcastable against F's leading shape."""
    mu, lam = np.asarray(mu, float), np.asarray(lam, float)
    Fi = inverse(F)
    FiT = np.swapaxes(Fi, -1, -2)
    lnJ = np.log(determinant(F))
    P = (mu[..., None, None] * (F - FiT)) + (lam * lnJ)[..., None, None] * FiT
    if not tangent:
        return P, None
    eye = np.eye(2)
    e4 = (...,) + (None,) * 4
    A = (mu[e4] * np.einsum("ik,JL->iJkL", eye, eye)
         + (mu - lam * lnJ)[e4] * np.einsum("...Li,...Jk->...iJkL", Fi, Fi)
         + lam[e4] * np.einsum("...Ji,...Lk->...iJkL", Fi, Fi))
    return P, A


def determinant(F: np.ndarray) -> np.ndarray:
    """det F of 2 x 2 matrices (...,); FloatingPointError where it is not positive."""
    J = F[..., 0, 0] * F[..., 1, 1] - F[..., 0, 1] * F[..., 1, 0]
    if np.any(J <= 0):
        raise FloatingPointError(f"{int((J <= 0).sum())} deformation gradient(s) with det F <= 0: the material is "
                                 f"folded over (load step too large or the tissue crushed)")
    return J


def inverse(F: np.ndarray) -> np.ndarray:
    """F^-1 of 2 x 2 matrices (..., 2, 2)."""
    J = determinant(F)
    out = np.empty_like(F)
    out[..., 0, 0], out[..., 1, 1] = F[..., 1, 1] / J, F[..., 0, 0] / J
    out[..., 0, 1], out[..., 1, 0] = -F[..., 0, 1] / J, -F[..., 1, 0] / J
    return out
