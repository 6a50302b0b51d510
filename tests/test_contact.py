"""Contact (load B): exactness of the LCP, fast path vs plain full solve, Hertz, and the study's findings."""
import dataclasses

import numpy as np
import pytest
from scipy.optimize import nnls

from fem import scene as S
from fem.contact import SurfaceModel, indent_full, surface_model, tip_profile
from fem.lcp import solve_lcp
from fem.mesh import mesh_section
from fem.model import build_model
from fem.scene import Analysis, Indenter, Scene, Tissue


def test_lcp_matches_independent_nnls_and_is_complementary():
    rng = np.random.default_rng(1)
    for _ in range(200):
        n = int(rng.integers(1, 30))
        A = rng.normal(size=(n, n))
        M = A @ A.T + 1e-2 * np.eye(n)
        q = rng.normal(size=n)
        r = solve_lcp(M, q, start=q < 0)
        # independent: min 1/2 z'Mz + q'z, z >= 0  <=>  NNLS  min |L'z + L^-1 q|, M = L L'
        L = np.linalg.cholesky(M)
        z_ref, _ = nnls(L.T, -np.linalg.solve(L, q), maxiter=50 * n)
        scale = np.abs(q).max()
        assert np.all(r.z >= 0)
        assert r.w.min() > -1e-10 * scale
        assert abs(r.z @ r.w) < 1e-10 * scale * max(1.0, np.abs(r.z).max())
        np.testing.assert_allclose(r.z, z_ref, atol=1e-8 * max(1.0, np.abs(z_ref).max()))


@pytest.fixture(scope="module")
def paper():
    return surface_model(S.load("paper"))


@pytest.fixture(scope="module")
def healthy():
    return surface_model(S.load("healthy"))


@pytest.fixture(scope="module")
def coarse_paper():
    sc = S.load("paper").with_analysis(mesh_size_m=0.004)
    return sc, SurfaceModel(sc)


@pytest.mark.parametrize("x0, depth", [(0.035, 0.004), (0.012, 0.002), (0.0, 0.003), (0.070, 0.001), (0.028, 0.0048)])
def test_fast_path_agrees_with_full_solve_to_roundoff(coarse_paper, x0, depth):
    sc, m = coarse_paper
    full = indent_full(sc, x0, depth, model=m.model)
    idx, f, gap = m.contact_forces(x0, depth)
    F = np.zeros(len(m.top))
    F[idx] = f
    assert abs(f.sum() / full["force_n_per_m"] - 1) < 1e-10
    assert np.abs(F - full["nodal_force_n_per_m"]).max() < 1e-10 * F.max()
    u = m.full_field(x0, depth)
    assert np.abs(u - full["u"]).max() < 1e-10 * np.abs(u).max()
    assert np.array_equal(f > 0, full["active"][idx])


@pytest.mark.parametrize("x0", [0.005, 0.020, 0.035, 0.0512])
def test_complementarity_no_penetration_no_tension(paper, x0):
    depth = 0.004
    idx, f, gap = paper.contact_forces(x0, depth)
    q = tip_profile(paper.scene.indenter, x0, depth, paper.x[idx])
    assert np.all(f >= 0)                                        # no tension
    assert gap.min() > -1e-12 * np.abs(q).max()                  # no penetration
    assert np.abs(gap[f > 0]).max() < 1e-12 * np.abs(q).max()    # in contact: zero gap
    assert np.abs(f * gap).max() < 1e-12 * f.max() * np.abs(q).max()
    # the gap really is tip profile minus the deformed surface
    u = paper.full_field(x0, depth)
    uy = u[2 * paper.top[idx] + 1]
    np.testing.assert_allclose(gap, q - uy, atol=1e-12 * np.abs(q).max())


def test_hertz_line_contact():
    """Rigid cylinder on a block 40 R wide and 10 R deep; compare with Hertz for the computed load."""
    E, nu, R = 2500.0, 0.4, 0.010
    sc = Scene(name="hertz", tissue=Tissue(width_m=0.2, height_m=0.1, youngs_pa=E, poisson=nu),
               indenter=Indenter(radius_m=R), analysis=Analysis(mesh_size_m=0.01, surface_refine=1.0))
    mesh = mesh_section(0.2, 0.1, [], 0.01, 1.0, 2, focus=(0.1, 2e-5, 0.0006))
    m = SurfaceModel(sc, model=build_model(sc, mesh=mesh))
    r = m.indent(0.1, 5e-5)
    P = r.force_n_per_m
    Es = E / (1 - nu ** 2)
    a = np.sqrt(4 * P * R / (np.pi * Es))
    p0 = 2 * P / (np.pi * a)
    assert a < 0.05 * R and a < 0.01 * 0.1                     # a << R and << block
    f, s = r.nodal_force_n_per_m, r.contact_x_m - 0.1
    a_moment = 2 * np.sqrt((f * s ** 2).sum() / f.sum())       # exact for p ~ sqrt(1 - x^2/a^2)
    assert abs(a_moment / a - 1) < 0.01
    assert abs(r.half_width_m / a - 1) < 0.01                  # extent of the contact zone
    assert abs(r.pressure_pa.max() / p0 - 1) < 0.01
    # the pressure profile follows the ellipse inside the contact
    inside = np.abs(s) < 0.8 * a
    np.testing.assert_allclose(r.pressure_pa[inside], p0 * np.sqrt(1 - (s[inside] / a) ** 2), rtol=0.02)


def test_force_contrast_peaks_over_the_stone(paper, healthy):
    xs = np.linspace(0.005, 0.065, 25)
    spacing = xs[1] - xs[0]
    fp = np.array([paper.force_n(x, 0.004) for x in xs])
    fh = np.array([healthy.force_n(x, 0.004) for x in xs])
    ratio = fp / fh
    assert ratio.max() > 1.05
    assert abs(xs[np.argmax(ratio)] - 0.035) <= spacing
    assert np.all(fp >= fh * (1 - 1e-9))         # a stiff inclusion never softens the response
    # at 100 waypoints (0.6 mm apart) the ratio's top is flat to ~1e-6: the sub-waypoint fit still finds the stone
    from app.commands.predict import _peak
    xs = np.linspace(0.005, 0.065, 100)
    ratio = np.array([paper.force_n(x, 0.004) / healthy.force_n(x, 0.004) for x in xs])
    assert abs(_peak(xs, ratio)["x_m"] - 0.035) <= xs[1] - xs[0]
    # healthy tissue is mirror-symmetric about the centre (the mesh is not exactly: allow its asymmetry)
    np.testing.assert_allclose(fh, fh[::-1], rtol=2e-3)


@pytest.mark.parametrize("name, xs_stone", [("paper-left", 0.020), ("paper-right", 0.050)])
def test_contrast_follows_the_stone(healthy, name, xs_stone):
    m = surface_model(S.load(name))
    xs = np.linspace(0.005, 0.065, 25)
    ratio = np.array([m.force_n(x, 0.004) / healthy.force_n(x, 0.004) for x in xs])
    assert abs(xs[np.argmax(ratio)] - xs_stone) <= xs[1] - xs[0]


def test_max_stress_under_tip_and_falls_away_from_stone(paper):
    xs = np.array([0.035, 0.030, 0.025, 0.020, 0.015])
    res = paper.indent_many(xs, 0.004)
    R = paper.scene.indenter.radius_m
    for r in res:
        assert abs(r.max_von_mises_at_m[0] - r.x_m) <= R          # the maximum sits under the tip
        assert r.max_von_mises_at_m[1] <= R
    vm = [r.max_von_mises_pa for r in res]
    assert all(a > b for a, b in zip(vm, vm[1:]))                  # falls as the tip leaves the stone


def test_elastic_tip_within_stated_bound_and_soft_tip_softer():
    sc = S.load("paper")
    rigid = surface_model(sc)
    assert rigid.rigid_tip and "rigid" in rigid.tip_note
    elastic = SurfaceModel(sc, model=rigid.model, rigid_tip=False)
    assert not elastic.rigid_tip
    for x in (0.020, 0.035):
        change = 1 - elastic.force_n(x, 0.004) / rigid.force_n(x, 0.004)
        assert 0 < change < rigid.tip_bound
    soft = dataclasses.replace(sc, indenter=dataclasses.replace(sc.indenter, youngs_pa=1.0e4))
    ms = SurfaceModel(soft, model=rigid.model)
    assert not ms.rigid_tip
    assert ms.force_n(0.035, 0.004) < 0.97 * rigid.force_n(0.035, 0.004)


def test_flat_punch_and_monotone_force():
    sc = dataclasses.replace(S.load("healthy"), indenter=Indenter(shape="flat", radius_m=0.003))
    m = surface_model(sc)
    r = m.indent(0.035, 0.002)
    face = np.abs(r.contact_x_m - 0.035) <= 0.003 - 1e-12
    assert np.all(r.nodal_force_n_per_m[face] > 0)                 # the whole face is in contact
    assert np.abs(r.gap_m[face]).max() < 1e-12 * 0.002
    cyl = surface_model(S.load("healthy"))
    depths = np.linspace(0.0, 0.0048, 13)
    F = [cyl.force_n(0.035, d) for d in depths]
    assert F[0] == 0 and all(b > a for a, b in zip(F, F[1:]))
    d = cyl.depth_for_force(0.035, 0.05, 0.0045)
    assert abs(cyl.force_n(0.035, d) - 0.05) < 1e-6


def test_bad_waypoints_are_refused(paper):
    for x0, d in [(-0.001, 0.002), (0.071, 0.002), (0.035, -1e-3), (0.035, float("nan")), (0.035, 0.06),
                  (0.035, 0.005)]:                     # at the tip radius: tissue would wrap the tip
        with pytest.raises(ValueError, match="x_m|depth_m"):
            paper.force_n(x0, d)
