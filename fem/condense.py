"""Condensing a large SPD stiffness onto a set of contact DOFs: one sparse Cholesky with those DOFs ordered last.

With P K_ff P^T = L L^T and the contact DOFs c last in P, the trailing diagonal block L_cc of L is the Cholesky
factor of the Schur complement S = K_cc - K_ci K_ii^-1 K_ic, so the condensed compliance is C = S^-1 =
L_cc^-T L_cc^-1 (LAPACK dtrtri then dlauum on L_cc, i.e. dpotri keeping L_cc^-1): no multi-right-hand-side solve,
whose cost (one sparse triangular sweep per contact DOF) dominated in both SuperLU and CHOLMOD on the 3D models
(bench/bench_3d.py measures it).

CHOLMOD (SuiteSparse, from the cvxopt wheel; supernodal, BLAS-3 on its dense fronts) with a fill-reducing ordering
of the interior and the contact DOFs appended: METIS nested dissection (the ``pymetis`` wheel) when it is installed,
else cvxopt's AMD (the wheel's CHOLMOD has no METIS). On block3d's default mesh nested dissection leaves 32 % less
fill than AMD and factorizes several times faster (bench/bench_3d.py waypoints). CHOLMOD's postordering is switched
off so the order is kept (checked). The trailing block is read in place from the supernodal factor (through ctypes
in the CHOLMOD library cvxopt links: ``_CholmodDirect.trailing_block``, its layout checked first); only when that is
not reachable does cvxopt's getfactor hand the whole factor over as a simplicial copy. The factor is then freed (a
model whose stresses are never asked for holds only the dense compliance), and a fresh supernodal factorization is
made (once, lazily) when back-substitutions are asked for (stress fields); with ``compliance=False`` (a model whose
compliance came from the disk cache, factorized for its fields) the factor read in place is kept for them.

Displacements for forces on the contact DOFs only (``solve_contact``): the forward sweep L y = P b of such a
right-hand side touches only the trailing block (y is zero on the interior), so y_c = L_cc^-1 b_c is a dense
product with the kept L_cc^-1 and only the backward sweep L^T x = y goes through the sparse factor: half the work
of a full solve, the same answer to round-off. Without cvxopt: fem.schur_lu.SchurFactor (SuperLU; the 2D surface
model's compliance is always made by it).
"""
from __future__ import annotations

import contextlib
import ctypes
import threading
import time

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .interior_factor import InteriorFactor
from .schur_lu import SchurFactor


def available() -> bool:
    try:
        import cvxopt.cholmod  # noqa: F401  (lazy: an optional compiled dependency)
    except ImportError:
        return False
    return True


def metis_available() -> bool:
    try:
        import pymetis  # noqa: F401  (lazy: an optional compiled dependency)
    except ImportError:
        return False
    return True


class _CholmodDirect:
    """CHOLMOD's own cholmod_l_solve on a cvxopt factor, for many right-hand sides at once.

    cvxopt's cholmod.solve loops over the columns (one memory-bound sweep through the factor per column); CHOLMOD
    itself sweeps once for all of them with BLAS-3 on its supernodes. Reached through ctypes in the library cvxopt's
    extension links (its factor capsule holds a cholmod_factor of the "long" interface). ``get()`` is None when any
    of it is missing: callers then use cvxopt's solve. ctypes releases the GIL, so calls share one cholmod_common
    under a lock."""

    _instance: _CholmodDirect | None = None
    _tried = False

    class Dense(ctypes.Structure):        # cholmod_dense (CHOLMOD 2.x-5.x)
        _fields_ = [("nrow", ctypes.c_size_t), ("ncol", ctypes.c_size_t), ("nzmax", ctypes.c_size_t),
                    ("d", ctypes.c_size_t), ("x", ctypes.c_void_p), ("z", ctypes.c_void_p),
                    ("xtype", ctypes.c_int), ("dtype", ctypes.c_int)]

    def __init__(self):
        import cvxopt.cholmod as chm
        lib = ctypes.CDLL(chm.__file__)           # dlsym also searches the libraries it links (libcholmod)
        lib.cholmod_l_solve.restype = ctypes.POINTER(self.Dense)
        lib.cholmod_l_solve.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.POINTER(self.Dense), ctypes.c_void_p]
        lib.cholmod_l_free_dense.argtypes = [ctypes.POINTER(ctypes.POINTER(self.Dense)), ctypes.c_void_p]
        self._common = ctypes.create_string_buffer(1 << 20)     # cholmod_common is a few kB; kept for the process
        self._lock = threading.Lock()
        if lib.cholmod_l_start(self._common) != 1:
            raise RuntimeError("cholmod_l_start failed")
        self._lib = lib
        self._capsule = ctypes.pythonapi.PyCapsule_GetPointer
        self._capsule.restype = ctypes.c_void_p
        self._capsule.argtypes = [ctypes.py_object, ctypes.c_char_p]

    @classmethod
    def get(cls) -> _CholmodDirect | None:
        if not cls._tried:
            cls._tried = True
            try:
                cls._instance = cls()
            except (OSError, AttributeError, RuntimeError):
                cls._instance = None
        return cls._instance

    class Factor(ctypes.Structure):       # cholmod_factor (CHOLMOD 2.x-3.x; the fields checked before use)
        _fields_ = [("n", ctypes.c_size_t), ("minor", ctypes.c_size_t), ("Perm", ctypes.c_void_p),
                    ("ColCount", ctypes.c_void_p), ("IPerm", ctypes.c_void_p), ("nzmax", ctypes.c_size_t),
                    ("p", ctypes.c_void_p), ("i", ctypes.c_void_p), ("x", ctypes.c_void_p), ("z", ctypes.c_void_p),
                    ("nz", ctypes.c_void_p), ("next", ctypes.c_void_p), ("prev", ctypes.c_void_p),
                    ("nsuper", ctypes.c_size_t), ("ssize", ctypes.c_size_t), ("xsize", ctypes.c_size_t),
                    ("maxcsize", ctypes.c_size_t), ("maxesize", ctypes.c_size_t), ("super", ctypes.c_void_p),
                    ("pi", ctypes.c_void_p), ("px", ctypes.c_void_p), ("s", ctypes.c_void_p),
                    ("ordering", ctypes.c_int), ("is_ll", ctypes.c_int), ("is_super", ctypes.c_int),
                    ("is_monotonic", ctypes.c_int), ("itype", ctypes.c_int), ("xtype", ctypes.c_int),
                    ("dtype", ctypes.c_int), ("useGPU", ctypes.c_int)]

    def layout(self, F, p: np.ndarray) -> tuple[np.ndarray, ...] | None:
        """(super, pi, px, s, x): views of cvxopt's supernodal factor F of an n x n matrix factorized in the order
        p, in place (no copy; valid while F lives). None when F is not a real supernodal LL' "long" factor in the
        order p, or its layout is not the one this reads."""
        try:
            ptr = self._capsule(F, b"CHOLMOD FACTOR D L")
        except ValueError:
            return None
        f = self.Factor.from_address(ptr)
        n = len(p)
        if not (f.n == n and f.minor == n and f.is_super == 1 and f.is_ll == 1 and f.itype == 2 and f.xtype == 1
                and f.dtype == 0 and f.nsuper > 0 and f.Perm and f.super and f.pi and f.px and f.s and f.x):
            return None

        def longs(addr, count):
            return np.ctypeslib.as_array(ctypes.cast(addr, ctypes.POINTER(ctypes.c_int64)), shape=(count,))

        if not np.array_equal(longs(f.Perm, n), p):
            return None
        ns = int(f.nsuper)
        sup, pi, px = longs(f.super, ns + 1), longs(f.pi, ns + 1), longs(f.px, ns + 1)
        if not (sup[0] == 0 and sup[ns] == n and pi[ns] == f.ssize and px[ns] <= f.xsize
                and np.array_equal(np.diff(px), np.diff(pi) * np.diff(sup)) and np.all(np.diff(sup) > 0)):
            return None
        s = longs(f.s, int(f.ssize))
        if s.min() < 0 or s.max() >= n:
            return None
        first, width = pi[:-1], np.diff(sup)      # each supernode's rows start with its own columns
        if not (np.array_equal(s[first], sup[:-1]) and np.array_equal(s[first + width - 1], sup[1:] - 1)):
            return None
        x = np.ctypeslib.as_array(ctypes.cast(f.x, ctypes.POINTER(ctypes.c_double)), shape=(int(f.xsize),))
        return sup, pi, px, s, x

    def trailing_block(self, F, p: np.ndarray, nc: int) -> np.ndarray | None:
        """The trailing nc x nc block of L (lower triangle; Fortran order) read in place from cvxopt's supernodal
        factor F of an n x n matrix factorized in the order p: no copy of the factor. None when F is not a real
        supernodal LL' "long" factor in the order p, or its layout is not the one this reads (the caller then
        converts the factor with cvxopt's getfactor)."""
        n = len(p)
        lay = self.layout(F, p) if 0 < nc <= n else None
        if lay is None:
            return None
        sup, pi, px, s, x = lay
        ns = len(sup) - 1
        c0 = n - nc
        Lcc = np.zeros((nc, nc), order="F")
        for k in range(int(np.searchsorted(sup, c0, side="right")) - 1, ns):   # the supernodes holding columns >= c0
            j0, j1, nr = int(sup[k]), int(sup[k + 1]), int(pi[k + 1] - pi[k])
            rows = s[pi[k]:pi[k + 1]]
            if not np.array_equal(rows[:j1 - j0], np.arange(j0, j1)):
                return None
            block = x[px[k]:px[k] + nr * (j1 - j0)].reshape(j1 - j0, nr).T      # column-major nr x ncols
            # its columns from c0 on, and their rows from c0 on: the diagonal block's rows (its own columns, in order,
            # checked above) from c0, then the rows below it, all beyond its last column (L is lower triangular).
            # Copied as slices where the rows run on without a gap (the contact DOFs, ordered last, are one dense
            # supernode on block3d's mesh: 8039 columns, read in 0.1 s where a 2D fancy index and a mask took 4.3 s)
            a = max(j0, c0) - j0
            a0, b0 = j0 + a - c0, j1 - c0                  # those columns' positions in the trailing block
            r = rows[a:] - c0
            if np.all(np.diff(r) == 1):                    # (ascending, no gap: a slice)
                Lcc[r[0]:r[-1] + 1, a0:b0] = block[a:, a:]
            else:
                Lcc[r, a0:b0] = block[a:, a:]
            for j in range(a0 + 1, b0):                    # the diagonal block's unused upper part (a copy: the
                Lcc[a0:j, j] = 0.0                         # factor itself is left as it is)
        return Lcc

    def solve(self, F, Y: np.ndarray, sys: int) -> np.ndarray | None:
        """X with (system sys) X = Y for a factor F of cvxopt.cholmod; None if F is not a real "long" factor."""
        try:
            L = self._capsule(F, b"CHOLMOD FACTOR D L")
        except ValueError:
            return None
        f = self.Factor.from_address(L)
        if f.minor < f.n:               # (a factorization that failed: cvxopt's solve says so, CHOLMOD's gives NaN)
            raise ArithmeticError(f"the factor is not positive definite (column {f.minor} of {f.n})")
        Y = np.asfortranarray(Y, dtype=float)
        n, k = Y.shape
        B = self.Dense(n, k, n * k, n, Y.ctypes.data, None, 1, 0)           # CHOLMOD_REAL, CHOLMOD_DOUBLE
        with self._lock:
            X = self._lib.cholmod_l_solve(sys, L, ctypes.byref(B), self._common)
            if not X:
                raise RuntimeError("cholmod_l_solve failed")
            x = X.contents
            buf = ctypes.cast(x.x, ctypes.POINTER(ctypes.c_double))
            out = np.ctypeslib.as_array(buf, shape=(x.ncol * x.d,)).reshape(x.ncol, x.d)[:, :n].T.copy()
            self._lib.cholmod_l_free_dense(ctypes.byref(X), self._common)
        return out


def interior_order(Kff, interior: np.ndarray, A=None, ordering: str = "auto") -> np.ndarray:
    """A fill-reducing order of the ``interior`` positions of Kff (the others to be appended after them):
    "metis" (nested dissection of the interior's graph, pymetis; seeded, so the same every run), "amd" (cvxopt's
    AMD of the whole matrix ``A``, a cvxopt spmatrix of Kff's lower triangle, restricted to the interior), or
    "auto" (METIS when pymetis is installed, else AMD)."""
    if ordering == "auto":
        ordering = "metis" if metis_available() else "amd"
    if len(interior) < 3:                           # METIS divides by zero on an empty graph
        return np.asarray(interior, dtype=np.int64)
    if ordering == "metis":
        import pymetis
        G = sp.csr_matrix(Kff)[interior][:, interior]
        G = sp.csr_matrix((np.ones(G.nnz), G.indices, G.indptr), shape=G.shape)
        G.setdiag(0)
        G.eliminate_zeros()
        G.sort_indices()
        opts = pymetis.Options(seed=1)
        if hasattr(pymetis, "CSRAdjacency"):        # pymetis >= 2025
            perm, _ = pymetis.nested_dissection(pymetis.CSRAdjacency(G.indptr, G.indices), options=opts)
        else:
            perm, _ = pymetis.nested_dissection(xadj=G.indptr, adjncy=G.indices, options=opts)
        return interior[np.asarray(perm, dtype=np.int64)]
    if ordering == "amd":
        import cvxopt.amd
        order = np.asarray(cvxopt.amd.order(A), dtype=np.int64).ravel()
        keep = np.zeros(Kff.shape[0], bool)
        keep[interior] = True
        return order[keep[order]]
    raise ValueError(f"ordering must be 'auto', 'metis' or 'amd', got {ordering!r}")


_OPTIONS = {"supernodal": 2, "postorder": False, "nmethods": 1}


@contextlib.contextmanager
def _cholmod_options():
    """CHOLMOD's options for the condensing factorizations (supernodal, the given order kept), restored after."""
    import cvxopt.cholmod as chm
    saved = dict(chm.options)
    chm.options.update(_OPTIONS)
    try:
        yield
    finally:
        chm.options.clear()
        chm.options.update(saved)


def _ordered(K, free: np.ndarray, contact: np.ndarray, ordering: str):
    """(A: K_ff's lower triangle as a cvxopt spmatrix, p: the factor's order with the contact DOFs last, c: the
    contact DOFs' positions in ``free``, the ordering's name) for K_ff = K[free][:, free]."""
    import cvxopt
    pos = np.full(K.shape[0], -1)
    pos[free] = np.arange(len(free))
    c = pos[contact]
    if np.any(c < 0):
        raise ValueError("a contact DOF is not free")
    Kff = K[free][:, free]
    low = sp.tril(Kff).tocoo()
    A = cvxopt.spmatrix(cvxopt.matrix(low.data), cvxopt.matrix(low.row.astype(np.int64)),
                        cvxopt.matrix(low.col.astype(np.int64)), size=low.shape)
    is_c = np.zeros(len(free), bool)
    is_c[c] = True
    name = ordering if ordering != "auto" else ("metis" if metis_available() else "amd")
    return A, np.concatenate([interior_order(Kff, np.flatnonzero(~is_c), A, name), c]), c, name


def _symmetrized(C: np.ndarray, block: int = 512) -> np.ndarray:
    """C (square) made symmetric from its lower triangle, in place, a block of columns at a time: the upper part
    above each diagonal block copied from the lower part left of it (no full-size temporaries: two copies of an
    8039-square compliance, 1 GB, were made before session 57)."""
    n = C.shape[0]
    for b0 in range(0, n, block):
        b1 = min(b0 + block, n)
        C[:b0, b0:b1] = C[b0:b1, :b0].T
        D = C[b0:b1, b0:b1]
        D[...] = np.tril(D) + np.tril(D, -1).T
    return C


def _numeric(A, p: np.ndarray):
    """CHOLMOD's supernodal factor of A in the order p (under CholmodSchur's options), the order checked kept."""
    import cvxopt
    import cvxopt.cholmod as chm
    F = chm.symbolic(A, p=cvxopt.matrix(p))
    chm.numeric(A, F)
    probe = cvxopt.matrix(np.arange(len(p), dtype=float))
    chm.solve(F, probe, sys=7)                      # probe = P (0..n-1): the order used
    if not np.array_equal(np.asarray(probe).ravel().astype(np.int64), p):
        raise RuntimeError("CHOLMOD reordered the Schur factorization; cannot read the Schur complement")
    return F


class CholmodSchur:
    """K_ff = K[free][:, free] factorized by CHOLMOD with the contact DOFs (positions ``contact`` in the full
    numbering, a subset of ``free``) last. ``compliance``: (n_c, n_c) = S^-1, in the order of ``contact``;
    ``solve``: K_ff^-1 rhs; ``solve_contact``: the same for a right-hand side on the contact DOFs only, by the
    backward sweep alone (the factorization for both is redone on first use, see the module docstring).
    ``ordering``: the interior's, see ``interior_order``; ``compliance=False`` skips forming it (None: a model whose
    compliance came from the disk cache needs only the factor for its fields). ``interior``: also copy the factor's
    interior columns out (``interior``: fem.interior_factor, for stresses without a second factorization; None
    when not asked or not readable in place)."""

    def __init__(self, K, free: np.ndarray, contact: np.ndarray, ordering: str = "auto", compliance: bool = True,
                 interior: bool = False):
        import cvxopt
        import cvxopt.cholmod as chm
        self._cvx, self._chm = cvxopt, chm
        t0 = time.perf_counter()
        self._A, p, c, self.ordering = _ordered(K, free, contact, ordering)
        n, nc = len(free), len(c)
        t1 = time.perf_counter()
        self._p = cvxopt.matrix(p)
        self.p = p
        with self._options():
            self._F = _numeric(self._A, p)
            t2 = time.perf_counter()
            direct = _CholmodDirect.get()
            layout = direct.layout(self._F, p) if interior and direct is not None else None
            self.interior = None if layout is None else InteriorFactor.from_layout(p, nc, *layout)
            del layout
            Lcc = direct.trailing_block(self._F, p, nc) if direct is not None else None
            self.extract = "in place" if Lcc is not None else "getfactor"
            if Lcc is None:
                Lcc = self._trailing_by_conversion(n, nc)
                self._F = None                                    # converted: refactorized when solves are asked
            elif compliance:
                self._F = None        # forces only, as a rule: the factor is freed (made again if solves are asked)
        t3 = time.perf_counter()
        Linv, info = sla.lapack.dtrtri(Lcc, lower=1, overwrite_c=1)     # dpotri = dtrtri, then dlauum
        if info != 0:
            raise np.linalg.LinAlgError(f"dtrtri failed (info {info}): the Schur complement is not positive definite")
        self._Linv = Linv       # L_cc^-1 (Fortran order, zero above the diagonal), for solve_contact's columns
        self.compliance = None
        if compliance:
            Cinv, info = sla.lapack.dlauum(Linv, lower=1, overwrite_c=0)    # L_cc^-T L_cc^-1 (lower triangle)
            if info != 0:
                raise np.linalg.LinAlgError(f"dlauum failed (info {info})")
            self.compliance = _symmetrized(Cinv)
        del Linv
        self.free, self.c = free, c
        self.timings_s = {"order_s": t1 - t0, "factor_s": t2 - t1, "extract_s": t3 - t2,
                          "inverse_s": time.perf_counter() - t3}
        self._factored = self._F is not None       # kept (compliance=False: made for solves) or made again on use

    def _trailing_by_conversion(self, n: int, nc: int) -> np.ndarray:
        """L's trailing nc x nc block through cvxopt's getfactor (a simplicial copy of the whole factor: about
        twice the factor's memory for a moment), when the supernodal factor cannot be read in place."""
        L = self._chm.getfactor(self._F)
        colptr, rowind, vals = L.CCS                              # compressed columns; only the trailing
        start = int(colptr[n - nc])                               # nc columns are read (lower triangular:
        ptr = np.asarray(colptr[n - nc:], dtype=np.int64).ravel() - start   # their rows are trailing too)
        rows = np.asarray(rowind[start:], dtype=np.int64).ravel() - (n - nc)
        cols = np.repeat(np.arange(nc), np.diff(ptr))
        Lcc = np.zeros((nc, nc), order="F")
        Lcc[rows, cols] = np.asarray(vals[start:]).ravel()
        return Lcc

    def _options(self):
        return _cholmod_options()

    def _factor(self):
        if not self._factored:
            with self._options():   # a fresh supernodal factor (the first was converted to a simplicial one)
                self._F = self._chm.symbolic(self._A, p=self._p)
                self._chm.numeric(self._A, self._F)
            self._factored = True
        return self._F

    def solve(self, rhs_free: np.ndarray) -> np.ndarray:
        """K_ff^-1 rhs for rhs given on the free DOFs (n_free,) or (n_free, k): the full solve."""
        F = self._factor()
        B = self._cvx.matrix(np.asfortranarray(rhs_free, dtype=float))
        self._chm.solve(F, B)
        return np.asarray(B).reshape(rhs_free.shape)

    def solve_contact(self, rhs_c: np.ndarray) -> np.ndarray:
        """K_ff^-1 rhs (n_free, k) for a right-hand side (n_c, k) on the contact DOFs (order of ``contact``), zero
        elsewhere: y_c = L_cc^-1 rhs_c from the kept dense inverse (only rhs_c's nonzero rows are read), then the
        backward sweep L^T x = y through the sparse factor (CHOLMOD, sys = Lt; several columns in one sweep,
        ``_CholmodDirect``), then x in the free numbering."""
        F = self._factor()
        rhs_c = np.asarray(rhs_c, dtype=float).reshape(len(self.c), -1)
        n, nc, k = len(self.free), len(self.c), rhs_c.shape[1]
        nz = np.flatnonzero(np.any(rhs_c != 0, axis=1))
        Y = np.zeros((n, k), order="F")
        Y[n - nc:] = self._Linv[:, nz] @ rhs_c[nz]
        direct = _CholmodDirect.get() if k > 1 else None
        Z = direct.solve(F, Y, sys=5) if direct is not None else None     # L^T x = y, in the factor's order
        if Z is None:
            B = self._cvx.matrix(Y)
            self._chm.solve(F, B, sys=5)
            Z = np.asarray(B)
        X = np.empty((n, k))
        X[self.p] = Z
        return X


class Cholesky:
    """K = L L' by CHOLMOD (supernodal; ordering as ``interior_order``: METIS when pymetis is installed, else
    CHOLMOD's own AMD) for a sparse SPD K; ``solve(rhs)`` for (n,) or (n, k); ``refactor(K)`` for new values on the
    same pattern (a Newton iteration's tangents)."""

    def __init__(self, K, order: np.ndarray | None = None, reusable: bool = False):
        """``order``: a fill-reducing order of K's rows to use (``Cholesky.order_for(K)``; a Newton iteration's
        tangents share their pattern, so one order serves them all); None: computed here. ``reusable``: keep K's
        pattern and its lower triangle's map for ``refactor`` (about 16 bytes per nonzero of K, kept)."""
        import cvxopt
        import cvxopt.cholmod as chm
        self._chm, self._cvx = chm, cvxopt
        K = sp.csc_matrix(K)
        cols = np.repeat(np.arange(K.shape[1]), np.diff(K.indptr))
        low = np.flatnonzero(K.indices >= cols)                 # K's lower triangle, in K.data's order
        rows, cols = cvxopt.matrix(K.indices[low].astype(np.int64)), cvxopt.matrix(cols[low].astype(np.int64))
        self._reuse = (K.shape, K.indptr.copy(), K.indices.copy(), low, rows, cols) if reusable else None
        A = cvxopt.spmatrix(cvxopt.matrix(K.data[low]), rows, cols, size=K.shape)
        del low, rows, cols
        if order is None:
            order = self.order_for(K)
        self._F = chm.symbolic(A) if order is None else chm.symbolic(A, p=cvxopt.matrix(np.asarray(order, np.int64)))
        chm.numeric(A, self._F)

    @staticmethod
    def order_for(K) -> np.ndarray | None:
        """METIS nested dissection of K's graph (None without pymetis: CHOLMOD's own AMD then)."""
        return interior_order(K, np.arange(K.shape[0]), ordering="metis") if metis_available() else None

    def refactor(self, K) -> bool:
        """Factor K's values into this factor's symbolic analysis (its order and supernodes: a refactorization took
        7-12 ms where a new factorization in the same order took 23-34 ms, on the paper section's correction mesh;
        the factor the same bit for bit) when this was made ``reusable`` for K's pattern, and say so; False
        (nothing done) otherwise. ArithmeticError when K is not positive definite: solves then raise
        ArithmeticError until a positive definite K is factorized into it."""
        if self._reuse is None:
            return False
        shape, indptr, indices, low, rows, cols = self._reuse
        if not (getattr(K, "format", None) == "csc" and K.shape == shape and np.array_equal(K.indptr, indptr)
                and np.array_equal(K.indices, indices)):
            return False
        self._chm.numeric(self._cvx.spmatrix(self._cvx.matrix(K.data[low]), rows, cols, size=shape), self._F)
        return True

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        B = self._cvx.matrix(np.asfortranarray(rhs, dtype=float))
        self._chm.solve(self._F, B)
        return np.asarray(B).reshape(np.shape(rhs))

    def solve_columns(self, rhs: np.ndarray) -> np.ndarray:
        """``solve`` for an (n, k) right-hand side in one sweep through the factor for all its columns (CHOLMOD's
        own solve: BLAS-3 on its supernodes, where cvxopt's sweeps once per column; 17-23 ms against 33-35 ms for 50
        columns of the paper section's correction mesh); the same to round-off. ``solve`` where that is not
        available."""
        direct = _CholmodDirect.get() if np.ndim(rhs) == 2 and np.shape(rhs)[1] > 1 else None
        X = direct.solve(self._F, rhs, sys=0) if direct is not None else None
        return self.solve(rhs) if X is None else X


def factorize_spd(K):
    """A sparse Cholesky of SPD K (CHOLMOD when cvxopt is installed, else SuperLU with a symmetric ordering)."""
    if available():
        return Cholesky(K)
    return spla.splu(sp.csc_matrix(K), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                     options={"SymmetricMode": True})


def schur(K, free: np.ndarray, contact: np.ndarray, method: str = "auto", ordering: str = "auto",
          compliance: bool = True, interior: bool = False):
    """The condensation of K_ff onto ``contact``: CholmodSchur ("cholmod", or "auto" when cvxopt is installed; its
    interior ``ordering``, see ``interior_order``; ``compliance=False``: not formed) or fem.schur_lu.SchurFactor
    ("superlu"). Both have ``compliance``, ``solve``, ``free`` and ``c``; CholmodSchur also ``solve_contact``."""
    if method == "cholmod" or (method == "auto" and available()):
        return CholmodSchur(K, free, contact, ordering, compliance, interior)
    if method in ("superlu", "auto"):
        return SchurFactor(K, free, contact)
    raise ValueError(f"method must be 'auto', 'cholmod' or 'superlu', got {method!r}")


def interior_factor(K, free: np.ndarray, contact: np.ndarray, ordering: str = "auto") -> InteriorFactor | None:
    """The interior columns (fem.interior_factor) of K_ff's Cholesky factor with ``contact`` last: one ordering
    and numeric factorization by CHOLMOD, the columns copied out of the supernodal factor read in place, the factor
    freed. None without cvxopt or when the factor's layout cannot be read in place (callers then solve with
    CholmodSchur or SuperLU). Displacements for forces on ``contact`` then need the condensed compliance for the
    contact rows (``InteriorFactor.sweep``)."""
    direct = _CholmodDirect.get() if available() else None
    if direct is None:
        return None
    A, p, c, _ = _ordered(K, free, contact, ordering)
    with _cholmod_options():
        F = _numeric(A, p)
    layout = direct.layout(F, p)
    return None if layout is None else InteriorFactor.from_layout(p, len(c), *layout)

