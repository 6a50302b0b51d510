"""Condensing a large SPD stiffness onto a set of contact DOFs: one sparse Cholesky with those DOFs ordered last.

With P K_ff P^T = L L^T and the contact DOFs c last in P, the trailing diagonal block L_cc of L is the Cholesky
factor of the Schur complement S = K_cc - K_ci K_ii^-1 K_ic, so the condensed compliance is C = S^-1 =
L_cc^-T L_cc^-1 (LAPACK dpotri on L_cc): no multi-right-hand-side solve, whose cost (one sparse triangular sweep
per contact DOF) dominated in both SuperLU and CHOLMOD on the 3D models (bench/bench_3d.py measures it).

CHOLMOD (SuiteSparse, from the cvxopt wheel; supernodal, BLAS-3 on its dense fronts) with a fill-reducing AMD
ordering of the interior and the contact DOFs appended; its postordering is switched off so the order is kept
(checked). cvxopt hands the factor over by converting it to a simplicial one, so a fresh supernodal factorization is made
(once, lazily) when back-substitutions are asked for (stress fields). Without cvxopt: fem.contact.SchurFactor (SuperLU).
"""
from __future__ import annotations

import time

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .contact import SchurFactor


def available() -> bool:
    try:
        import cvxopt.cholmod  # noqa: F401  (lazy: an optional compiled dependency)
    except ImportError:
        return False
    return True


class CholmodSchur:
    """K_ff = K[free][:, free] factorized by CHOLMOD with the contact DOFs (positions ``contact`` in the full
    numbering, a subset of ``free``) last. ``compliance``: (n_c, n_c) = S^-1, in the order of ``contact``;
    ``solve``: K_ff^-1 rhs (the factorization is redone on first use, see the module docstring)."""

    def __init__(self, K, free: np.ndarray, contact: np.ndarray):
        import cvxopt
        import cvxopt.amd
        import cvxopt.cholmod as chm
        self._cvx, self._chm = cvxopt, chm
        t0 = time.perf_counter()
        pos = np.full(K.shape[0], -1)
        pos[free] = np.arange(len(free))
        c = pos[contact]
        if np.any(c < 0):
            raise ValueError("a contact DOF is not free")
        Kff = K[free][:, free]
        low = sp.tril(Kff).tocoo()
        n, nc = len(free), len(c)
        self._A = cvxopt.spmatrix(cvxopt.matrix(low.data), cvxopt.matrix(low.row.astype(np.int64)),
                                  cvxopt.matrix(low.col.astype(np.int64)), size=low.shape)
        order = np.asarray(cvxopt.amd.order(self._A), dtype=np.int64).ravel()
        t1 = time.perf_counter()
        is_c = np.zeros(n, bool)
        is_c[c] = True
        p = np.concatenate([order[~is_c[order]], c])
        saved = dict(chm.options)
        chm.options.update({"supernodal": 2, "postorder": False, "nmethods": 1})
        self._p = cvxopt.matrix(p)
        try:
            self._F = chm.symbolic(self._A, p=self._p)
            chm.numeric(self._A, self._F)
            probe = cvxopt.matrix(np.arange(n, dtype=float))
            chm.solve(self._F, probe, sys=7)                      # probe = P (0..n-1): the order used
            if not np.array_equal(np.asarray(probe).ravel().astype(np.int64), p):
                raise RuntimeError("CHOLMOD reordered the Schur factorization; cannot read the Schur complement")
            t2 = time.perf_counter()
            L = chm.getfactor(self._F)                            # converts the factor (see module docstring)
            self._F = None
        finally:
            chm.options.clear()
            chm.options.update(saved)
        colptr, rowind, vals = L.CCS                              # compressed columns; only the trailing
        start = int(colptr[n - nc])                               # nc columns are read (lower triangular:
        ptr = np.asarray(colptr[n - nc:], dtype=np.int64).ravel() - start   # their rows are trailing too)
        rows = np.asarray(rowind[start:], dtype=np.int64).ravel() - (n - nc)
        cols = np.repeat(np.arange(nc), np.diff(ptr))
        Lcc = np.zeros((nc, nc), order="F")
        Lcc[rows, cols] = np.asarray(vals[start:]).ravel()
        del colptr, rowind, vals
        del L
        t3 = time.perf_counter()
        Cinv, info = sla.lapack.dpotri(Lcc, lower=1, overwrite_c=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"dpotri failed (info {info}): the Schur complement is not positive definite")
        C = np.tril(Cinv)
        C += np.tril(C, -1).T
        self.compliance = C
        self.free, self.c = free, c
        self.timings_s = {"order_s": t1 - t0, "factor_s": t2 - t1, "extract_s": t3 - t2,
                          "inverse_s": time.perf_counter() - t3}
        self._factored = False

    def solve(self, rhs_free: np.ndarray) -> np.ndarray:
        """K_ff^-1 rhs for rhs given on the free DOFs (n_free,) or (n_free, k)."""
        chm, cvxopt = self._chm, self._cvx
        if not self._factored:
            saved = dict(chm.options)
            chm.options.update({"supernodal": 2, "postorder": False, "nmethods": 1})
            try:                    # a fresh supernodal factor (the first was converted to a simplicial one)
                self._F = chm.symbolic(self._A, p=self._p)
                chm.numeric(self._A, self._F)
            finally:
                chm.options.clear()
                chm.options.update(saved)
            self._factored = True
        B = cvxopt.matrix(np.asfortranarray(rhs_free, dtype=float))
        chm.solve(self._F, B)
        return np.asarray(B).reshape(rhs_free.shape)


class Cholesky:
    """K = L L' by CHOLMOD (AMD ordering, supernodal) for a sparse SPD K; ``solve(rhs)`` for (n,) or (n, k)."""

    def __init__(self, K):
        import cvxopt
        import cvxopt.cholmod as chm
        low = sp.tril(K).tocoo()
        A = cvxopt.spmatrix(cvxopt.matrix(low.data), cvxopt.matrix(low.row.astype(np.int64)),
                            cvxopt.matrix(low.col.astype(np.int64)), size=low.shape)
        self._chm, self._cvx = chm, cvxopt
        self._F = chm.symbolic(A)
        chm.numeric(A, self._F)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        B = self._cvx.matrix(np.asfortranarray(rhs, dtype=float))
        self._chm.solve(self._F, B)
        return np.asarray(B).reshape(np.shape(rhs))


def factorize_spd(K):
    """A sparse Cholesky of SPD K (CHOLMOD when cvxopt is installed, else SuperLU with a symmetric ordering)."""
    if available():
        return Cholesky(K)
    return spla.splu(sp.csc_matrix(K), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                     options={"SymmetricMode": True})


def schur(K, free: np.ndarray, contact: np.ndarray, method: str = "auto"):
    """The condensation of K_ff onto ``contact``: CholmodSchur ("cholmod", or "auto" when cvxopt is installed) or
    fem.contact.SchurFactor ("superlu"). Both have ``compliance``, ``solve``, ``free`` and ``c``."""
    if method == "cholmod" or (method == "auto" and available()):
        return CholmodSchur(K, free, contact)
    if method in ("superlu", "auto"):
        return SchurFactor(K, free, contact)
    raise ValueError(f"method must be 'auto', 'cholmod' or 'superlu', got {method!r}")
