"""Session 58: the finite-strain sweeps' tangent factor and the finite-strain shape's key.

fem.hyperindent keeps CHOLMOD's symbolic analysis of the material tangent between Newton steps (its sparsity pattern
is the mesh's) and solves a step's right-hand sides in one sweep through the factor (fem.condense.Cholesky.refactor,
solve_columns). Checked against the plain path it replaced (a new factorization every step, solved column by column):
the same Newton iterations and forces to round-off. And a tip fem treats as rigid is keyed without its modulus, so a
scene with the paper's tissue and the default rigid tip finds the shipped shape of the paper's 60 MPa tip."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp

import fem.hyperindent as hyperindent
import planner.finite_strain_response as fsr
from fem.condense import Cholesky, available
from fem.hypertruth import HyperelasticForce, sweep_depths
from fem.scene import load
from fem.tip import TIP_TOLERANCE

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
    chol = Cholesky(K1, order)
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
    with pytest.raises(ArithmeticError):
        chol.refactor(sp.csc_matrix(K2 - 10.0 * sp.identity(400, format="csc").multiply(K2 != 0)))


def _plain_factorize(self, Kt):
    """The path before session 58: a new CHOLMOD factorization every Newton step, cvxopt's solve (column by
    column)."""
    return Cholesky(Kt, self._order_for(Kt)).solve


def test_a_sweep_with_the_kept_factor_is_the_plain_sweep(monkeypatch):
    """The paper section on a coarse mesh (tip 10 mm from the side and in the middle): the same Newton iteration
    counts at every depth and the same forces to 1e-12."""
    sc = load("paper").prior().with_analysis(mesh_size_m=0.005, surface_refine=2.5)
    depths = sweep_depths(sc)[:6]
    fast = [hyperindent.HyperIndenter(sc).sweep(x, depths) for x in (0.010, 0.035)]
    monkeypatch.setattr(hyperindent.HyperIndenter, "_factorize", _plain_factorize)
    plain = [hyperindent.HyperIndenter(sc).sweep(x, depths) for x in (0.010, 0.035)]
    for a, b in zip(fast, plain):
        assert not a.stopped and not b.stopped
        assert np.array_equal(a.newton_iterations, b.newton_iterations)
        assert np.array_equal(a.depth_m, b.depth_m)
        assert np.abs(a.force_n / b.force_n - 1).max() < 1e-12, (a.force_n, b.force_n)


def test_a_rigid_treated_tip_shares_the_shape_key_and_an_elastic_one_does_not():
    paper = load("paper").prior()
    assert paper.indenter.youngs_pa == 60e6
    rigid = dataclasses.replace(paper, indenter=dataclasses.replace(paper.indenter, youngs_pa=None))
    assert fsr.at_shape_modulus(paper).key() == fsr.at_shape_modulus(rigid).key()
    assert HyperelasticForce(paper).corr.key() == HyperelasticForce(rigid).corr.key()
    # a tip just stiff enough for the finite-strain model (1000 x the tissue) but not treated as rigid by fem's
    # linear model (its Hertz bound above TIP_TOLERANCE): the linear force differs, so the key must too
    soft = dataclasses.replace(paper, indenter=dataclasses.replace(paper.indenter, youngs_pa=1.05e3 * 2500.0))
    assert not fsr.unsupported(soft)
    from fem.tip import rigid_tip_bound
    assert rigid_tip_bound(soft) > TIP_TOLERANCE
    assert fsr.at_shape_modulus(soft).key() != fsr.at_shape_modulus(rigid).key()


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
    assert shape is not None and shape.g.shape == (11, 11)
    paper = fsr.prior_finite_strain(load("paper").prior())
    assert np.array_equal(shape.g, paper.g)
