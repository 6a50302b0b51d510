"""A condensation without CHOLMOD: K_ff factorized by SuperLU with the contact DOFs ordered last, whose trailing block
is the Schur complement on them (its inverse: the condensed compliance). fem.condense.schur falls back to it without
cvxopt (until session 60 it built every 2D compliance; CHOLMOD's now does, about five times as fast, the two
agreeing to about 5e-14 relative, 1.7e-12 at nu 0.499: tests/test_force_grid.py). Imports numpy only; scipy is
loaded when a model is factorized."""
from __future__ import annotations

import numpy as np


class SchurFactor:
    """K_ff factorized with the contact DOFs ordered last, so that the trailing block of L U is the Schur
    complement S = K_cc - K_ci K_ii^-1 K_ic and the condensed compliance is exactly S^-1: no multi-right-hand-side
    solve. The interior keeps SuperLU's fill-reducing ordering (taken from a first factorization)."""

    def __init__(self, K, free: np.ndarray, contact: np.ndarray):
        import scipy.sparse.linalg as spla  # scipy only when a model is factorized
        Kff = K[free][:, free].tocsc()
        pos = np.full(K.shape[0], -1)
        pos[free] = np.arange(len(free))
        c = pos[contact]
        opts = {"diag_pivot_thresh": 0.0, "options": {"SymmetricMode": True}}   # SPD: no pivoting
        order = np.argsort(spla.splu(Kff, permc_spec="MMD_AT_PLUS_A", **opts).perm_c)
        is_c = np.zeros(len(free), bool)
        is_c[c] = True
        self.p = np.concatenate([order[~is_c[order]], c])
        self.lu = spla.splu(Kff[self.p][:, self.p].tocsc(), permc_spec="NATURAL", **opts)
        n, nc = len(free), len(c)
        if not (np.array_equal(self.lu.perm_r, np.arange(n)) and np.array_equal(self.lu.perm_c, np.arange(n))):
            raise RuntimeError("SuperLU reordered the Schur factorization; cannot read the Schur complement")
        L = self.lu.L.tocsc()[n - nc:, n - nc:].toarray()
        U = self.lu.U.tocsc()[n - nc:, n - nc:].toarray()
        S = L @ U
        self.compliance = np.linalg.inv(0.5 * (S + S.T))
        self.free, self.c = free, c

    def solve(self, rhs_free: np.ndarray) -> np.ndarray:
        """K_ff^-1 rhs for rhs given on the free DOFs (n_free,) or (n_free, k)."""
        x = np.empty_like(rhs_free, dtype=float)
        x[self.p] = self.lu.solve(np.asfortranarray(rhs_free[self.p]))
        return x
