"""fem's force grid (SurfaceModel.force_grid_n: each position's depths swept, each LCP warm-started from the depth
before) gives one force_n per waypoint bit for bit, with NaN exactly where fem refuses the waypoint."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fem import scene as S
from fem.contact import SurfaceModel

MESH = dict(mesh_size_m=0.004, surface_refine=4.0)
LEVELS = (1e-3, 1.5e-3, 2e-3, 3e-3, 4e-3, 6e-3)


def _one_by_one(m: SurfaceModel, xs, levels) -> np.ndarray:
    out = np.full((len(levels), len(xs)), np.nan)
    for a, d in enumerate(levels):
        for b, x in enumerate(xs):
            try:
                out[a, b] = m.force_n(float(x), float(d))
            except ValueError:
                pass
    return out


def _scenes():
    paper = S.load("paper").with_analysis(**MESH)
    shallow = paper.with_stones([S.Stone(x_m=0.03, depth_m=0.0075, diameter_m=0.008)])    # refused past 3.75 mm
    soft_tip = dataclasses.replace(paper.prior(), indenter=S.Indenter(radius_m=0.004, youngs_pa=20 * 2500.0))
    flat = dataclasses.replace(paper, indenter=S.Indenter(shape="flat", radius_m=0.003))
    return {"prior": paper.prior(), "stone": paper, "shallow stone": shallow, "elastic tip": soft_tip,
            "flat punch": flat}


@pytest.mark.parametrize("name", list(_scenes()))
def test_force_grid_is_force_n_bit_for_bit(name):
    m = SurfaceModel(_scenes()[name])
    xs = np.linspace(0.0, m.scene.tissue.width_m, 29)
    grid = m.force_grid_n(xs, LEVELS)
    ref = _one_by_one(m, xs, LEVELS)
    assert grid.shape == (len(LEVELS), len(xs))
    np.testing.assert_array_equal(np.isnan(grid), np.isnan(ref))
    assert np.array_equal(grid, ref, equal_nan=True)
    assert np.all(grid[~np.isnan(grid)] > 0)
    if name == "shallow stone":
        assert np.isnan(grid).any() and not np.isnan(grid[0]).any()     # refusals past the crush limit only
    if name == "elastic tip":
        assert not m.rigid_tip


def test_force_grid_refusal_then_resume_depths():
    """A refused depth between allowed ones (out-of-order levels) leaves NaN there and the others exact."""
    m = SurfaceModel(_scenes()["shallow stone"])
    xs = np.array([0.01, 0.03])
    levels = (1e-3, 4.5e-3, 2e-3)                 # 4.5 mm is past the crush limit over the stone at x = 30 mm
    grid = m.force_grid_n(xs, levels)
    assert np.isnan(grid[1, 1]) and not np.isnan(grid[1, 0])
    assert np.array_equal(grid, _one_by_one(m, xs, levels), equal_nan=True)


@pytest.mark.parametrize("name", ["stone", "elastic tip"])
def test_2d_compliance_cholmod_and_superlu_agree(name, monkeypatch):
    """The 2D compliance from CHOLMOD's factor (fem.condense.CholmodSchur, the default with cvxopt) against SuperLU's
    (fem.schur_lu.SchurFactor, without it): two independent factorizations and orderings of the same K_ff."""
    from fem import condense
    sc = _scenes()[name]
    fast = SurfaceModel(sc)
    assert type(fast.fac).__name__ == "CholmodSchur"
    monkeypatch.setattr(condense, "available", lambda: False)
    plain = SurfaceModel(sc)
    assert type(plain.fac).__name__ == "SchurFactor"
    np.testing.assert_allclose(fast.C, plain.C, rtol=0, atol=1e-12 * np.abs(plain.C).max())
    xs = np.linspace(0.005, 0.065, 7)
    np.testing.assert_allclose(fast.force_grid_n(xs, LEVELS), plain.force_grid_n(xs, LEVELS), rtol=1e-11)
