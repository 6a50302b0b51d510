"""Session 58: the finite-strain sweeps' tangent factor and the finite-strain shape's key.

fem.hyperindent keeps CHOLMOD's symbolic analysis of the material tangent between Newton steps (its sparsity pattern
is the mesh's) and solves a step's right-hand sides in one sweep through the factor (fem.condense.Cholesky.refactor,
solve_columns). Checked against the plain path it replaced (a new factorization every step, solved column by column):
the same Newton iterations and forces to round-off. And a tip fem treats as rigid is keyed without its modulus, so a
scene with the paper's tissue and the default rigid tip finds the shipped shape of the paper's 60 MPa tip."""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import scipy.sparse as sp

import fem.hyperindent as hyperindent
import planner.finite_strain_response as fsr
from fem.condense import Cholesky, available
from fem.hypertruth import HyperelasticForce, sweep_depths
from fem.scene import load
from fem.tip import TIP_TOLERANCE, rigid_tip_bound, tip_too_soft

pytestmark = pytest.mark.skipif(not available(), reason="needs CHOLMOD (cvxopt)")


def _spd(n: int, seed: int):
    """A sparse SPD matrix (a 2D Laplacian-like band with random weights), CSC."""
    rng = np.random.default_rng(seed)
    off = -rng.uniform(0.5, 1.0, n - 1)
    far = -rng.uniform(0.1, 0.3, n - 7)
    A = sp.diags([off, far], [1, 7], shape=(n, n))
    A = A + A.T
    return sp.csc_matrix(A + sp.diags(-np.asarray(A.sum(axis=1)).ravel() + rng.uniform(0.1, 1.0, n)))


def test_refactor_is_a_new_factorization_bit_for_bit_and_refuses_another_pattern():
    K1, K2 = _spd(400, 1), _spd(400, 2)
    assert np.array_equal(K1.indptr, K2.indptr) and np.array_equal(K1.indices, K2.indices)
    order = Cholesky.order_for(K1)
    assert not Cholesky(K1, order).refactor(K2)            # not made reusable: nothing kept, nothing done
    chol = Cholesky(K1, order, reusable=True)
    B = np.random.default_rng(3).standard_normal((400, 5))
    assert chol.refactor(K2)
    fresh = Cholesky(K2, order)
    assert np.array_equal(chol.solve(B), fresh.solve(B))
    X = chol.solve_columns(B)                      # all columns in one sweep: the same to round-off
    assert np.abs(X - fresh.solve(B)).max() <= 1e-12 * np.abs(X).max()
    assert np.abs(K2 @ X - B).max() < 1e-10
    other = sp.csc_matrix(K2 + sp.diags(np.full(400 - 3, -1e-3), 3) + sp.diags(np.full(400 - 3, -1e-3), -3))
    assert not chol.refactor(other)                # another pattern: nothing done, the factor still K2's
    assert np.array_equal(chol.solve(B), fresh.solve(B))
    assert not chol.refactor(sp.csr_matrix(K2))    # (the pattern is compared in compressed columns)
    with pytest.raises(ArithmeticError):
        chol.refactor(sp.csc_matrix(K2 - 10.0 * sp.identity(400, format="csc").multiply(K2 != 0)))
    with pytest.raises(ArithmeticError):           # both solves say so (CHOLMOD's own would give NaN)
        chol.solve_columns(B)
    with pytest.raises(ArithmeticError):
        chol.solve(B)
    assert chol.refactor(K2)                       # a positive definite K factorized into it again: usable
    assert np.array_equal(chol.solve(B), fresh.solve(B))


def _plain_factorize(self, Kt):
    """The path before session 58: a new CHOLMOD factorization every Newton step, cvxopt's solve (column by
    column)."""
    return Cholesky(Kt, self._order_for(Kt)).solve


class _Counted(Cholesky):
    """Cholesky counting its factorizations and refactorizations (what the sweep's speed rests on)."""
    made = 0
    refactored: list = []

    def __init__(self, *a, **k):
        type(self).made += 1
        super().__init__(*a, **k)

    def refactor(self, K):
        ok = super().refactor(K)
        type(self).refactored.append(ok)
        return ok


def test_a_sweep_with_the_kept_factor_is_the_plain_sweep(monkeypatch):
    """The paper section on a coarse mesh (tip 10 mm from the side and in the middle): the same Newton iteration
    counts at every depth and the same forces to 1e-12; and the speed's reason: one factorization per indenter,
    every later step a refactorization into it."""
    sc = load("paper").prior().with_analysis(mesh_size_m=0.005, surface_refine=2.5)
    depths = sweep_depths(sc)[:6]
    monkeypatch.setattr(hyperindent, "Cholesky", _Counted)
    monkeypatch.setattr(_Counted, "refactored", [])
    fast = [hyperindent.HyperIndenter(sc).sweep(x, depths) for x in (0.010, 0.035)]
    steps = sum(int(sw.newton_iterations.sum()) for sw in fast)
    assert _Counted.made == 2 and len(_Counted.refactored) == steps - 2 and all(_Counted.refactored)
    monkeypatch.setattr(hyperindent.HyperIndenter, "_factorize", _plain_factorize)
    plain = [hyperindent.HyperIndenter(sc).sweep(x, depths) for x in (0.010, 0.035)]
    for a, b in zip(fast, plain):
        assert not a.stopped and not b.stopped
        assert np.array_equal(a.newton_iterations, b.newton_iterations)
        assert np.array_equal(a.depth_m, b.depth_m)
        assert np.abs(a.force_n / b.force_n - 1).max() < 1e-12, (a.force_n, b.force_n)


def _with(scene, youngs_pa=None, tip_pa=None, tip_poisson=None):
    t = scene.tissue if youngs_pa is None else dataclasses.replace(scene.tissue, youngs_pa=youngs_pa)
    ind = dataclasses.replace(scene.indenter, youngs_pa=tip_pa,
                              poisson=scene.indenter.poisson if tip_poisson is None else tip_poisson)
    return dataclasses.replace(scene, tissue=t, indenter=ind)


def test_a_rigid_treated_tip_shares_the_shape_key_and_an_elastic_one_does_not():
    paper = load("paper").prior()
    assert paper.indenter.youngs_pa == 60e6
    rigid = _with(paper, tip_pa=None)
    assert fsr.at_shape_modulus(paper).key() == fsr.at_shape_modulus(rigid).key()
    assert HyperelasticForce(paper).corr.key() == HyperelasticForce(rigid).corr.key()
    # a tip just stiff enough for the finite-strain model (1000 x the tissue) but not treated as rigid by fem's
    # linear model (its Hertz bound above TIP_TOLERANCE): the linear force differs, so the key must too
    soft = _with(paper, tip_pa=1.05e3 * 2500.0)
    assert not fsr.unsupported(soft) and rigid_tip_bound(soft) > TIP_TOLERANCE
    assert fsr.at_shape_modulus(soft).key() != fsr.at_shape_modulus(rigid).key()
    # at another tissue modulus an elastic tip is scaled with it: the same ratio, the same decision, the same key
    # (it kept its modulus at 2500 Pa before, where fem's decision could differ: 6000 Pa and 6.3 MPa is elastic,
    # 2500 Pa and 6.3 MPa rigid)
    stiff = _with(paper, youngs_pa=6000.0, tip_pa=6.3e6)
    assert rigid_tip_bound(stiff) > TIP_TOLERANCE and not fsr.unsupported(stiff)
    shaped = fsr.at_shape_modulus(stiff)
    assert shaped.tissue.youngs_pa == fsr.SHAPE_YOUNGS_PA
    assert rigid_tip_bound(shaped) == pytest.approx(rigid_tip_bound(stiff), rel=1e-12)
    assert shaped.key() == fsr.at_shape_modulus(_with(paper, youngs_pa=1000.0, tip_pa=1.05e6)).key()
    assert shaped.key() != fsr.at_shape_modulus(rigid).key()
    # the same ratio gives the same key whatever the product's rounding (1100 Pa x 1050 scaled to 2500 Pa came out
    # 2625000.0000000005 before the scaled modulus was rounded to 12 digits: another key, another 20 s build)
    keys = {fsr.at_shape_modulus(_with(paper, youngs_pa=e, tip_pa=1050.0 * e)).key()
            for e in (0.3, 1000.0, 1100.0, 1234.5, 2500.0, 3300.0, 4321.7, 7000.0, 1e5)}
    assert len(keys) == 1


def test_a_failed_shape_is_said_once_and_not_built_again(monkeypatch):
    """A prior whose sweeps do not reach depth: the localizer runs without the term, warned once per process (each
    fit asked again, built the shape again and warned again before session 58)."""
    calls = []

    def fails(prior):
        calls.append(prior)
        raise ValueError("the finite-strain sweeps reached depth at only 2 positions")
    monkeypatch.setattr(fsr, "build_shape", fails)
    monkeypatch.setattr(fsr, "_MEM", {})
    monkeypatch.setenv("PALPATE_CACHE", "0")
    paper = load("paper").prior()
    prior = _with(dataclasses.replace(paper, tissue=dataclasses.replace(paper.tissue, height_m=0.045)), tip_pa=None)
    with pytest.warns(UserWarning, match="without its finite-strain term"):
        assert fsr.prior_finite_strain(prior) is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fsr.prior_finite_strain(prior) is None and fsr.prior_finite_strain(prior, build=False) is None
    assert len(calls) == 1


def test_one_rule_for_a_tip_too_soft_for_the_finite_strain_model():
    """Below 1000 x the tissue and not treated as rigid by fem: refused (the prior's shape and the indenter); a tip
    below 1000 x that fem treats as rigid (a tip's Poisson ratio above the tissue's lowers its Hertz bound) is a
    rigid tip to both, and accepted by both (before session 58 the shape refused it and the truth took it)."""
    paper = load("paper").prior()
    soft = _with(paper, tip_pa=920 * 2500.0, tip_poisson=0.3)             # bound 1.18e-3: elastic
    rigidish = _with(paper, tip_pa=920 * 2500.0, tip_poisson=0.49)        # bound 0.98e-3: rigid to fem
    assert rigid_tip_bound(soft) > TIP_TOLERANCE > rigid_tip_bound(rigidish)
    assert tip_too_soft(soft) and not tip_too_soft(rigidish) and not tip_too_soft(paper)
    assert fsr.unsupported(soft) == "the finite-strain model needs a rigid-treated tip"
    assert fsr.unsupported(rigidish) == ""
    with pytest.raises(ValueError, match="tip is soft"):
        hyperindent.HyperIndenter(soft.with_analysis(mesh_size_m=0.01, surface_refine=2.0))
    hyperindent.HyperIndenter(rigidish.with_analysis(mesh_size_m=0.01, surface_refine=2.0))


def test_a_scene_with_the_papers_tissue_and_the_default_tip_finds_the_shipped_shape(tmp_path, monkeypatch):
    """Before session 58 such a scene (no [indenter]: a rigid 5 mm cylinder) built its own shape, 35 s, the same
    numbers as the shipped one of the paper's 60 MPa tip."""
    scene = tmp_path / "mine.toml"
    scene.write_text('name = "mine"\n[tissue]\nwidth_m = 0.070\nheight_m = 0.050\nyoungs_pa = 4000\npoisson = 0.4\n')
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path / "cache"))        # an empty cache: only planner/data
    monkeypatch.setattr(fsr, "_MEM", {})
    monkeypatch.setattr(fsr, "build_shape", lambda prior: pytest.fail("the shape was built, not found"))
    mine = load(str(scene)).prior()
    assert mine.indenter.youngs_pa is None
    shape = fsr.prior_finite_strain(mine)
    shipped = list(fsr.SHIPPED.glob(f"{fsr.KIND}-*.npz"))
    assert len(shipped) == 1
    assert shape is not None and np.array_equal(shape.g, np.load(shipped[0])["g"])
