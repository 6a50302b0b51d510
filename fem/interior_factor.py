"""The interior part of a supernodal Cholesky factor with the contact DOFs last, kept as plain arrays (so the disk
cache can hold it), and the backward sweep that gives the displacements of forces on the contact DOFs from it.

With P K_ff P^T = L L^T and the contact DOFs c last (fem.condense.CholmodSchur), a right-hand side b on c alone
has y = L^-1 P b zero on the interior, so the solution is x_c = S^-1 b_c = C b_c on the contact DOFs (C: the
condensed compliance the surface model already holds) and, on the interior, the backward sweep
L_ii^T x_i = -L_ci^T x_c (L_ii L_ii^T = K_ii: x_i = -K_ii^-1 K_ic x_c). That needs only the factor's columns before
the contact DOFs: on block3d's mesh 1.27 GB of the supernodal factor's 1.98 GB (the dense trailing block is not
kept; the compliance stands for it). The sweep runs supernode by supernode in reverse with two BLAS calls each (the
off-diagonal product and the triangular solve), for all right-hand sides at once.

``InteriorFactor.from_layout`` copies those columns out of a supernodal factor's arrays (fem.condense reads
CHOLMOD's in place, its layout checked: ``interior_factor``); ``to_arrays``/``from_arrays`` store and restore them
(the arrays may be read-only memory maps). A restored factor makes a stress query after a reload cost a sweep, not the
assembly, ordering and numeric factorization a fresh one needs (tens of seconds on block3d).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg.blas import dtrsm


@dataclass(frozen=True)
class InteriorFactor:
    """The supernodes of L holding its first n - nc columns (the last of them may also hold contact columns):
    ``sup`` their first columns (and the end), ``pi``/``s`` their row indices, ``px``/``x`` their values (each
    supernode's (rows x columns) block stored column-major, its diagonal block's upper part unused), all in the
    factor's order; ``p`` that order (positions in the free numbering), ``nc`` the number of contact DOFs last."""
    p: np.ndarray
    nc: int
    sup: np.ndarray
    pi: np.ndarray
    px: np.ndarray
    s: np.ndarray
    x: np.ndarray

    @property
    def n(self) -> int:
        return len(self.p)

    @classmethod
    def from_layout(cls, p: np.ndarray, nc: int, sup: np.ndarray, pi: np.ndarray, px: np.ndarray, s: np.ndarray,
                    x: np.ndarray) -> InteriorFactor:
        """Copy the interior columns out of a whole supernodal factor's arrays (CHOLMOD's layout: each supernode's
        values column by column, its rows first its own columns). A supernode holding both interior and contact
        columns keeps its interior ones: they come first and are contiguous."""
        n = len(p)
        c0 = n - nc
        ks = int(np.searchsorted(sup, c0, side="left"))        # supernodes 0..ks-1 start before c0
        if ks == 0 or not 0 < nc < n:
            raise ValueError("no interior columns in the factor")
        sup_i, px_i = np.array(sup[:ks + 1], dtype=np.int64), np.array(px[:ks + 1], dtype=np.int64)
        sup_i[ks] = c0                                          # the last one ends at c0 (it may straddle it)
        px_i[ks] = px_i[ks - 1] + (c0 - sup_i[ks - 1]) * (int(pi[ks]) - int(pi[ks - 1]))
        return cls(p=np.array(p, dtype=np.int64), nc=int(nc), sup=sup_i, pi=np.array(pi[:ks + 1], dtype=np.int64),
                   px=px_i, s=np.array(s[:pi[ks]], dtype=np.int64), x=np.array(x[:px_i[ks]], dtype=float))

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"p": self.p, "nc": np.array([self.nc]), "sup": self.sup, "pi": self.pi, "px": self.px, "s": self.s,
                "x": self.x}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> InteriorFactor:
        """Restored from ``to_arrays``' arrays (memory maps are used as they are); ValueError when they do not
        describe a factor of this layout: the order a permutation, the supernodes' bounds and value counts
        consistent, each supernode's rows its own columns first, then strictly increasing, all within the matrix
        (what the sweep indexes; the values themselves are checked by the callers' finite-result checks)."""
        a = {k: np.asarray(arrays[k]) for k in ("p", "nc", "sup", "pi", "px", "s", "x")}
        if not (all(a[k].ndim == 1 and a[k].dtype.kind in "iu" for k in ("p", "nc", "sup", "pi", "px", "s"))
                and a["nc"].shape == (1,) and a["x"].ndim == 1 and a["x"].dtype == np.float64):
            raise ValueError("the stored interior factor's arrays have the wrong types or shapes")
        nc, n = int(a["nc"][0]), len(a["p"])
        sup, pi, px, s = a["sup"], a["pi"], a["px"], a["s"]
        ks = len(sup) - 1
        if not (ks >= 1 and len(pi) == len(px) == ks + 1 and sup[0] == 0 and 0 < nc < n and pi[0] == px[0] == 0
                and sup[ks] == n - nc and pi[ks] == len(s) and px[ks] == len(a["x"])
                and np.all(np.diff(sup) > 0) and np.all(np.diff(pi) >= np.diff(sup))
                and np.array_equal(np.diff(px), np.diff(pi) * np.diff(sup))):
            raise ValueError("the stored interior factor's arrays do not fit together")
        if not np.array_equal(np.sort(a["p"]), np.arange(n)):
            raise ValueError("the stored interior factor's order is not a permutation")
        seg = np.repeat(np.arange(ks), np.diff(pi))              # each row entry's supernode
        local = np.arange(len(s)) - pi[seg]
        own = local < np.diff(sup)[seg]
        same = seg[1:] == seg[:-1]
        if not (len(s) == 0 or (s.min() >= 0 and s.max() < n and np.array_equal(s[own], sup[seg[own]] + local[own])
                                and np.all(np.diff(s)[same] > 0))):
            raise ValueError("the stored interior factor's row indices do not describe a factor")
        return cls(p=a["p"], nc=nc, sup=sup, pi=pi, px=px, s=s, x=a["x"])

    def sweep(self, x_c: np.ndarray) -> np.ndarray:
        """Z (n, k) in the factor's order with L^T Z = Y, Y zero on the interior, given Z's contact rows x_c
        (nc, k) (= C b_c): the interior rows by the backward sweep, supernode by supernode in reverse."""
        x_c = np.asarray(x_c, dtype=float).reshape(self.nc, -1)
        n, nc, k = self.n, self.nc, x_c.shape[1]
        c0 = n - nc
        Z = np.empty((n, k))
        Z[c0:] = x_c
        sup, pi, px, s, x = self.sup, self.pi, self.px, self.s, self.x
        for j in range(len(sup) - 2, -1, -1):
            j0, j1 = int(sup[j]), int(sup[j + 1])
            r0, r1 = int(pi[j]), int(pi[j + 1])
            m, nr = j1 - j0, r1 - r0
            A = x[px[j]:px[j] + nr * m].reshape(m, nr)    # A[c, r] = L[rows[r], j0 + c]
            if nr > m:                                    # the rows below its diagonal block: all known
                rhs = np.asfortranarray(A[:, m:] @ Z[s[r0 + m:r1]])
            else:
                rhs = np.zeros((m, k), order="F")
            Z[j0:j1] = dtrsm(-1.0, A[:, :m].T, rhs, lower=1, trans_a=1, overwrite_b=1)
        return Z
