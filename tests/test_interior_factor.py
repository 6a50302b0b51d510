"""The factor's interior columns kept for the 3D stresses (fem.interior_factor): the backward sweep against a dense
solve for every split of a small SPD matrix, the arrays' round trip and refusal, and the disk cache: a restored
model's stresses equal the built one's bitwise without assembling, factorizing or building its stress operators
again, forces alone store no factor, and a damaged entry (the factor's or the band operators') is rebuilt or stops
the run with a message naming the cache."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import scipy.sparse as sps

from fem import condense, contact3d, diskcache
from fem import scene as S
from fem.contact3d import surface_model3d
from fem.interior_factor import InteriorFactor

pytestmark = pytest.mark.skipif(condense._CholmodDirect.get() is None,
                                reason="CHOLMOD's factor cannot be read in place here (cvxopt missing)")


def _laplacian(*shape: int) -> sps.csr_matrix:
    """The grid Laplacian on a box of ``shape`` points (any dimension) plus the identity: SPD, sparse, with the
    supernodes of a nested-dissection-like fill."""
    n = math.prod(shape)
    K = sps.identity(n, format="csr")
    for axis, m in enumerate(shape):
        before, after = math.prod(shape[:axis]), math.prod(shape[axis + 1:])
        second = sps.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(m, m))
        K = K + sps.kron(sps.kron(sps.identity(before), second), sps.identity(after))
    return K.tocsr()


def test_sweep_equals_the_dense_solve_for_every_split():
    """x_i = -K_ii^-1 K_ic x_c for the contact rows x_c given: every size of the contact set on a 3D grid Laplacian
    (supernodes that straddle the split included), several right-hand sides at once and one alone."""
    K = _laplacian(4, 5, 6)
    n, Kd = K.shape[0], K.toarray()
    rng = np.random.default_rng(5)
    splits = [np.sort(rng.choice(n, nc, replace=False)) for nc in range(1, n, 3)] + [np.arange(n - 1)]
    for c in splits:
        i = np.setdiff1d(np.arange(n), c)
        f = condense.interior_factor(K, np.arange(n), c)
        assert f.n == n and f.nc == len(c) and f.sup[-1] == n - len(c)
        x_c = rng.standard_normal((len(c), 3))
        X = np.empty((n, 3))
        X[f.p] = f.sweep(x_c)
        ref = -np.linalg.solve(Kd[np.ix_(i, i)], Kd[np.ix_(i, c)] @ x_c)
        assert np.array_equal(X[c], x_c)
        assert np.abs(X[i] - ref).max() < 1e-12 * np.abs(ref).max()
        one = np.empty(n)
        one[f.p] = f.sweep(x_c[:, 1])[:, 0]
        assert np.abs(one - X[:, 1]).max() < 1e-13 * np.abs(X[:, 1]).max()


def test_arrays_round_trip_and_refusal():
    K = _laplacian(7, 7)
    n = K.shape[0]
    f = condense.interior_factor(K, np.arange(n), np.arange(n - 10, n))
    g = InteriorFactor.from_arrays(f.to_arrays())
    x_c = np.random.default_rng(1).standard_normal((10, 2))
    assert np.array_equal(f.sweep(x_c), g.sweep(x_c))
    for key, change in (("px", lambda a: a + 1), ("sup", lambda a: a[:-1]), ("x", lambda a: a[:-1]),
                        ("nc", lambda a: a * 0)):
        arrays = dict(f.to_arrays())
        arrays[key] = change(arrays[key])
        with pytest.raises(ValueError):
            InteriorFactor.from_arrays(arrays)


def _scene():
    return S.Scene(name="t3d-factor", tissue=S.Tissue(width_m=0.03, length_m=0.024, height_m=0.015,
                                                      youngs_pa=2500.0, poisson=0.4),
                   stones=(S.Stone(x_m=0.015, y_m=0.012, depth_m=0.006, diameter_m=0.005),),
                   indenter=S.Indenter(shape="sphere", radius_m=0.004),
                   analysis=S.Analysis(order=2, mesh_size_m=0.006, surface_refine=2.0, patch_m=0.02,
                                       top_displacement_m=0.001))


def _factor_entries(tmp_path, kind: str = "factor3d") -> list:
    return sorted(tmp_path.glob(f"{kind}-*.npz"))


def test_cached_factor_gives_the_same_stresses_without_a_factorization(tmp_path, monkeypatch):
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path))
    sc = _scene()
    pts = [(0.015, 0.012, 0.0006), (0.011, 0.014, 0.0005)]
    contact3d._CACHE.clear()
    a = surface_model3d(sc, cache=True)
    a.force_n(*pts[0])
    assert _factor_entries(tmp_path) == []                # forces alone store no factor
    ra = a.indent_many(pts)
    assert len(_factor_entries(tmp_path)) == len(_factor_entries(tmp_path, "band3d")) == 1
    contact3d._CACHE.clear()
    b = surface_model3d(sc, cache=True)
    for name in ("interior_factor", "point_operator3d", "recovery_operator3d"):
        monkeypatch.setattr(contact3d, name, lambda *a, _n=name, **k: pytest.fail(f"{_n} again"))
    rb = b.indent_many(pts)
    assert b._fac is None and "K" not in vars(b.model)    # no factorization, no assembly
    for x, y in zip(ra, rb):
        assert x.max_von_mises_pa > 0 and x.max_von_mises_pa == y.max_von_mises_pa
        assert x.max_von_mises_at_m == y.max_von_mises_at_m
        assert np.array_equal(x.pressure_pa, y.pressure_pa)
    assert np.array_equal(a.full_field(*pts[1]), b.full_field(*pts[1]))


def _stored_reference(tmp_path, monkeypatch):
    """(scene, waypoint, its maximum von Mises, the factor entry's path) after one stress query in a fresh cache."""
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path))
    sc, pt = _scene(), (0.015, 0.012, 0.0006)
    contact3d._CACHE.clear()
    ref = surface_model3d(sc, cache=True).indent(*pt).max_von_mises_pa
    (path,) = _factor_entries(tmp_path)
    return sc, pt, ref, path


def test_damaged_factor_entry_is_rebuilt_or_named(tmp_path, monkeypatch):
    sc, pt, ref, path = _stored_reference(tmp_path, monkeypatch)
    good = diskcache.read(path)
    small = condense.interior_factor(_laplacian(5, 5), np.arange(25), np.arange(20, 25))
    diskcache.write(path, small.to_arrays())                 # another model's factor under this key
    contact3d._CACHE.clear()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        again = surface_model3d(sc, cache=True).indent(*pt).max_von_mises_pa
    assert again == ref and any("ignoring entry" in str(w.message) for w in caught)
    bad = dict(good)
    bad["x"] = good["x"].copy()
    bad["x"][-1] = np.nan                                   # the last column's last row: always read
    diskcache.write(path, bad)
    contact3d._CACHE.clear()
    with pytest.raises(FloatingPointError, match="cache"):
        surface_model3d(sc, cache=True).indent(*pt)
    diskcache.write(path, good)
    (band,) = _factor_entries(tmp_path, "band3d")
    arrays = diskcache.read(band)
    diskcache.write(band, {**arrays, "Rt_indptr": arrays["Rt_indptr"][:-1]})    # does not fit: rebuilt
    contact3d._CACHE.clear()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert surface_model3d(sc, cache=True).indent(*pt).max_von_mises_pa == ref
    assert any("ignoring entry" in str(w.message) for w in caught)
    diskcache.write(band, {**arrays, "Rb_data": np.full_like(arrays["Rb_data"], np.nan)})
    contact3d._CACHE.clear()
    with pytest.raises(FloatingPointError, match="cache"):
        surface_model3d(sc, cache=True).indent(*pt)


def test_corrupt_structure_is_refused():
    """Finite but inconsistent arrays are refused (the cache then rebuilds): an order that is no permutation, a row
    index outside the matrix, a supernode whose rows do not start with its own columns."""
    K = _laplacian(3, 4, 5)
    n = K.shape[0]
    f = condense.interior_factor(K, np.arange(n), np.arange(n - 12, n))
    good = f.to_arrays()
    wide = int(np.argmax(np.diff(f.pi) > np.diff(f.sup)))        # a supernode with rows below its own columns
    below = int(f.pi[wide] + f.sup[wide + 1] - f.sup[wide])
    for key, index, value in (("p", 0, good["p"][1]), ("s", below, n), ("s", below, -1),
                              ("s", int(f.pi[wide]), int(f.sup[wide]) + 1)):
        arrays = {k: np.array(v) for k, v in good.items()}
        arrays[key][index] = value
        with pytest.raises(ValueError):
            InteriorFactor.from_arrays(arrays)
    for key, bad in (("nc", np.array(12)), ("s", good["s"].astype(float)), ("x", good["x"].astype(np.float32)),
                     ("p", good["p"].reshape(1, -1))):                    # wrong types or shapes: not an IndexError
        with pytest.raises(ValueError, match="types or shapes"):
            InteriorFactor.from_arrays({**good, key: bad})


def test_a_factor_from_another_model_is_rebuilt(tmp_path, monkeypatch):
    """An entry whose order puts other DOFs last than this model's patch (same sizes): refused and rebuilt."""
    sc, pt, ref, path = _stored_reference(tmp_path, monkeypatch)
    arrays = diskcache.read(path)
    p = arrays["p"].copy()
    p[[0, -1]] = p[[-1, 0]]                    # an interior DOF swapped with a patch DOF
    diskcache.write(path, {**arrays, "p": p})
    contact3d._CACHE.clear()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert surface_model3d(sc, cache=True).indent(*pt).max_von_mises_pa == ref
    assert any("does not fit this model" in str(w.message) for w in caught)


def test_a_build_asked_for_stresses_keeps_its_own_factor(tmp_path, monkeypatch):
    """``stresses=True``: the build's own factorization gives the interior columns (no second one), stored, and its
    stresses equal those of a model factorized again for them."""
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path))
    sc = _scene()
    pts = [(0.015, 0.012, 0.0006), (0.011, 0.014, 0.0005)]
    ref = contact3d.SurfaceModel3D(sc).indent_many(pts)              # no cache: factorized again for its stresses
    monkeypatch.setattr(contact3d, "interior_factor", lambda *a, **k: pytest.fail("factorized again"))
    contact3d._CACHE.clear()
    got = surface_model3d(sc, cache=True, stresses=True).indent_many(pts)
    assert len(_factor_entries(tmp_path)) == 1
    for x, y in zip(got, ref):
        assert x.max_von_mises_pa == pytest.approx(y.max_von_mises_pa, rel=1e-12)
        assert x.max_von_mises_at_m == y.max_von_mises_at_m


def test_an_unreadable_factor_is_tried_once(monkeypatch):
    """When CHOLMOD's factor cannot be read in place, the stresses fall back to the condensing factorization's own
    sweep, and the interior columns are not tried again on every query (each try is a factorization)."""
    calls = []
    numeric = condense._numeric
    monkeypatch.setattr(condense, "_numeric", lambda *a: calls.append(1) or numeric(*a))
    monkeypatch.setattr(condense._CholmodDirect, "layout", lambda self, F, p: None)
    m = contact3d.SurfaceModel3D(_scene())
    assert len(calls) == 1                                            # the compliance's factorization
    first = [m.indent(0.015, 0.012, 0.0006).max_von_mises_pa for _ in range(3)]
    assert len(calls) == 2 and m.interior() is None and m._interior_unreadable
    assert first[0] > 0 and first[0] == first[1] == first[2]
