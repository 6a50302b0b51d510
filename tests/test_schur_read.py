"""fem.condense reads the trailing (contact) block of CHOLMOD's supernodal factor in place
(``_CholmodDirect.trailing_block``): bitwise what cvxopt's getfactor conversion gives, whether the block's rows run
on without a gap (copied as slices, the usual case: contact DOFs ordered last make one dense supernode) or not (row
index arrays), and its compliance is the inverse of the Schur complement formed densely."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from fem import condense

pytestmark = pytest.mark.skipif(not condense.available() or condense._CholmodDirect.get() is None,
                                reason="cvxopt's CHOLMOD factor cannot be read in place here")


def _grid_spd(m: int) -> sp.csr_matrix:
    T = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(m, m))
    return (sp.kron(sp.eye(m), T) + sp.kron(T, sp.eye(m))).tocsr()


def _both(K, contact, monkeypatch, kinds: dict):
    read = condense._CholmodDirect.trailing_block

    def counted(self, F, p, nc):
        sup, pi, _, s, _ = self.layout(F, p)
        c0 = len(p) - nc
        for k in range(int(np.searchsorted(sup, c0, side="right")) - 1, len(sup) - 1):
            r = s[pi[k]:pi[k + 1]][max(int(sup[k]), c0) - int(sup[k]):]
            kinds["slice" if np.all(np.diff(r) == 1) else "gaps"] += 1
        return read(self, F, p, nc)
    free = np.arange(K.shape[0])
    with monkeypatch.context() as m:
        m.setattr(condense._CholmodDirect, "trailing_block", counted)
        direct = condense.schur(K, free, contact)
    with monkeypatch.context() as m:
        m.setattr(condense._CholmodDirect, "trailing_block", lambda self, F, p, nc: None)
        converted = condense.schur(K, free, contact)
    assert direct.extract == "in place" and converted.extract == "getfactor"
    assert np.array_equal(direct.compliance, converted.compliance)
    assert np.array_equal(direct._Linv, converted._Linv)
    return direct


def test_a_dense_trailing_block_read_as_slices(monkeypatch):
    K = _grid_spd(40)
    contact = np.sort(np.random.default_rng(0).choice(K.shape[0], 120, replace=False))
    kinds = {"slice": 0, "gaps": 0}
    d = _both(K, contact, monkeypatch, kinds)
    assert kinds["slice"] >= 1 and kinds["gaps"] == 0
    Kd = K.toarray()
    inner = np.setdiff1d(np.arange(K.shape[0]), contact)
    S = Kd[np.ix_(contact, contact)] - Kd[np.ix_(contact, inner)] @ np.linalg.solve(Kd[np.ix_(inner, inner)],
                                                                                   Kd[np.ix_(inner, contact)])
    Sinv = np.linalg.inv(S)
    assert np.abs(d.compliance - Sinv).max() < 1e-12 * np.abs(Sinv).max()      # (measured 1.3e-15)


def test_a_trailing_block_with_gaps_read_with_row_indices(monkeypatch):
    """Two unconnected blocks whose contact DOFs are interleaved: the Schur complement couples every other one, so
    the trailing factor's rows have gaps."""
    n = 40 * 40
    K = sp.block_diag([_grid_spd(40), _grid_spd(40)]).tocsr()
    rng = np.random.default_rng(1)
    contact = np.ravel(np.column_stack([np.sort(rng.choice(n, 60, replace=False)),
                                        n + np.sort(rng.choice(n, 60, replace=False))]))
    kinds = {"slice": 0, "gaps": 0}
    _both(K, contact, monkeypatch, kinds)
    assert kinds["gaps"] > 10


@pytest.mark.parametrize("n, block", [(1, 512), (5, 2), (513, 512), (700, 64), (300, 1000)])
def test_the_compliance_is_symmetrized_in_place_as_before(n, block):
    """``_symmetrized`` (a block of columns at a time, in place) gives what np.tril(C) + np.tril(C, -1).T gave."""
    A = np.asfortranarray(np.random.default_rng(n).standard_normal((n, n)))
    before = np.tril(A)
    before += np.tril(before, -1).T
    after = condense._symmetrized(A, block=block)
    assert after is A and np.array_equal(after, before)
