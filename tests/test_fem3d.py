"""Verification of fem in 3D (issue 15) on small meshes: exact block compression, patch tests (P1 and P2),
convergence rates on a manufactured solution, the condensed contact path against a plain full solve, Hertz on a
coarse mesh (loose tolerance, measured; the 1 % target is benched in bench/bench_3d.py), mirror symmetry, rigid
stones, the disk cache and scene validation. Together well under a minute."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sps

from fem import condense
from fem import scene as S
from fem.assembly import Material
from fem.assembly3d import body_force3d, elasticity_matrix3d, element_dofs3d, gradients3d, strain_matrices3d
from fem.contact3d import STRESS_RESOLVED, SurfaceModel3D, check_waypoint3d, patch_nodes, surface_model3d, tip_profile3d
from fem.elements3d import EDGES, quadrature, shape
from fem.mesh3d import Mesh3D, _orient, mesh_block, mesh_scene3d
from fem.model3d import Model3D, build_model3d, fixed_bottom
from fem.scene_mesh3d import mesh_for3d
from fem.stress3d import point_operator3d, recover3d, recovery_operator3d
from fem.uniform3d import solve_uniform3d


def _scene(order=2, size=0.006, refine=2.0, stones=(), W=0.03, L=0.024, H=0.015, patch=None, radius=0.004,
           top_displacement_m=0.001, **kw):
    return S.Scene(name="t3d", tissue=S.Tissue(width_m=W, length_m=L, height_m=H, youngs_pa=2500.0, poisson=0.4),
                   stones=stones, indenter=S.Indenter(shape="sphere", radius_m=radius),
                   analysis=S.Analysis(order=order, mesh_size_m=size, surface_refine=refine, patch_m=patch,
                                       top_displacement_m=top_displacement_m, **kw))


def _model(mesh, E=1.0, nu=0.3) -> Model3D:
    n = int(mesh.region.max()) + 1
    return Model3D(mesh=mesh, materials=[Material(E, nu)] * n, centres=[(0.0, 0.0, 0.0)] * (n - 1),
                   rigid=[False] * (n - 1))


def _boundary(mesh) -> np.ndarray:
    X = mesh.nodes
    size = np.array([mesh.width_m, mesh.length_m, mesh.height_m])
    tol = 1e-9 * size.max()
    return np.flatnonzero(np.any((X < tol) | (X > size - tol), axis=1))


def _dirichlet(model, nodes, values, load=None) -> np.ndarray:
    fixed = np.ravel(np.column_stack([3 * nodes, 3 * nodes + 1, 3 * nodes + 2]))
    order = np.argsort(fixed)
    fac = model.partition(fixed[order])
    return fac.full(fac.solve(np.ravel(values)[order], load))


# ------------------------------------------------------------------------------------------------ mesh

def test_gmsh_node_order_and_shared_stone_surface():
    """Every P2 mid-edge node of a straight tetrahedron sits at its edge's midpoint in the order fem.elements3d
    states; the stone's surface nodes are shared by tissue and stone elements (glued); all Jacobians positive."""
    mesh = mesh_block(0.03, 0.024, 0.015, [(0.015, 0.012, 0.007, 0.004)], 0.006, 3.0, 2)
    X = mesh.nodes
    mids = np.stack([X[mesh.tets[:, 4 + k]] - 0.5 * (X[mesh.tets[:, a]] + X[mesh.tets[:, b]])
                     for k, (a, b) in enumerate(EDGES)], axis=1)
    straight = np.abs(mids).max(axis=(1, 2)) < 1e-12
    assert straight.mean() > 0.9      # curved ones lie on the sphere only
    _, det = gradients3d(mesh, quadrature(2)[0])
    assert det.min() > 0
    assert np.isclose(det.sum() / 24 * 4 / 4, 0.03 * 0.024 * 0.015, rtol=1e-3)
    vert = mesh.tets[:, :4]     # (mid-edge nodes of a folded element may have been straightened off the sphere)
    shared = np.intersect1d(np.unique(vert[mesh.region == 0]), np.unique(vert[mesh.region == 1]))
    r = np.linalg.norm(X[shared] - [0.015, 0.012, 0.007], axis=1)
    assert len(shared) > 12 and np.allclose(r, 0.004, rtol=1e-6)


# ------------------------------------------------------------------------------------------------ exact block

@pytest.mark.parametrize("order", [1, 2])
def test_block_compression_exact_3d(order):
    """Top face moved down by d, frictionless top, bottom u_z = 0: the homogeneous uniaxial state
    u = (nu e x, nu e y, -e z), sigma_zz = -E e, reproduced to round-off by P1 and P2 on a graded mesh."""
    sc = _scene(order=order)
    r = solve_uniform3d(sc)
    E, nu, H, d = 2500.0, 0.4, 0.015, 0.001
    e = d / H
    X = r.model.mesh.nodes
    exact = np.column_stack([nu * e * X[:, 0], nu * e * X[:, 1], -e * X[:, 2]])
    assert np.abs(r.u.reshape(-1, 3) - exact).max() < 1e-10 * d
    for k, v in (("szz_pa", -E * e), ("sxx_pa", 0.0), ("syy_pa", 0.0), ("sxy_pa", 0.0), ("syz_pa", 0.0)):
        assert np.abs(r.nodal[k] - v).max() < 1e-9 * E * e
    assert np.abs(r.surface.fields["von_mises_pa"] - E * e).max() < 1e-9 * E * e
    assert r.reaction_n == pytest.approx(E * e * 0.03 * 0.024, rel=1e-10)


# ------------------------------------------------------------------------------------------------ patch tests

@pytest.mark.parametrize("order", [1, 2])
def test_patch_linear_field_3d(order):
    """A linear displacement prescribed on the boundary of a graded mesh with a spherical inner interface (curved
    isoparametric P2 elements there) is reproduced inside to round-off, with constant stress everywhere."""
    mesh = mesh_block(0.03, 0.024, 0.015, [(0.015, 0.012, 0.007, 0.004)], 0.006, 3.0, order)
    model = _model(mesh, E=2500.0, nu=0.4)
    a = np.array([1e-4, -2e-4, 3e-4])
    G = np.array([[0.011, -0.023, 0.005], [0.017, -0.031, 0.002], [-0.004, 0.013, 0.021]])
    exact = a + mesh.nodes @ G.T
    bnd = _boundary(mesh)
    u = _dirichlet(model, bnd, exact[bnd])
    assert np.abs(u.reshape(-1, 3) - exact).max() < 1e-12
    eps = np.array([G[0, 0], G[1, 1], G[2, 2], G[1, 2] + G[2, 1], G[0, 2] + G[2, 0], G[0, 1] + G[1, 0]])
    sig = elasticity_matrix3d(2500.0, 0.4) @ eps
    s = (recovery_operator3d(model) @ u).reshape(-1, 6)
    assert np.abs(s - sig).max() < 1e-9 * np.abs(sig).max()


def test_patch_quadratic_field_p2():
    """P2 reproduces a quadratic displacement field exactly: with the body force it implies (constant here) and the
    field prescribed on the boundary, the interior is exact to round-off on a straight-sided graded mesh."""
    E, nu = 2500.0, 0.3
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    mesh = mesh_block(0.03, 0.024, 0.015, [], 0.006, 2.0, 2)
    model = _model(mesh, E=E, nu=nu)

    def exact(X):
        x, y, z = X.T
        return np.column_stack([x * x + 0.5 * y * z, -x * y + z * z, 0.3 * y * y - x * z])

    # f = -(mu lap u + (lam + mu) grad div u); div u = 2x - x - x = 0, lap u = (2, 2 - ... ) by hand:
    lap = np.array([2.0, 2.0, 0.6 - 0.0])
    grad_div = np.zeros(3)
    f = -(mu * lap + (lam + mu) * grad_div)
    load = body_force3d(mesh, lambda x, y, z: (f[0] + 0 * x, f[1] + 0 * x, f[2] + 0 * x))
    bnd = _boundary(mesh)
    ex = exact(mesh.nodes)
    u = _dirichlet(model, bnd, ex[bnd], load=load)
    assert np.abs(u.reshape(-1, 3) - ex).max() < 1e-9 * np.abs(ex).max()
    # the stress points (fem.stress3d.point_operator3d): inside their elements, with the exact field's stress there
    els = np.arange(0, len(mesh.tets), 7)
    R, X = point_operator3d(model, els)
    corners = mesh.nodes[mesh.tets[els, :4]]
    assert np.all((X.reshape(len(els), 4, 3) > corners.min(1)[:, None]) & (X.reshape(len(els), 4, 3)
                                                                          < corners.max(1)[:, None]))
    x, y, z = X.T
    G = np.stack([np.column_stack([2 * x, 0.5 * z, 0.5 * y]), np.column_stack([-y, -x, 2 * z]),
                  np.column_stack([-z, 0.6 * y, -x])], axis=1)                  # du_i/dx_j at the points
    eps = np.column_stack([G[:, 0, 0], G[:, 1, 1], G[:, 2, 2], G[:, 1, 2] + G[:, 2, 1], G[:, 0, 2] + G[:, 2, 0],
                           G[:, 0, 1] + G[:, 1, 0]])
    sig = eps @ elasticity_matrix3d(E, nu).T
    assert np.abs((R @ u).reshape(-1, 6) - sig).max() < 1e-8 * np.abs(sig).max()


# ------------------------------------------------------------------------------------------------ convergence

PI = np.pi


def _mms(E=1.0, nu=0.3):
    """u = (sin(pi x) sin(pi y) sin(pi z), x y z, exp(x) cos(y)) and f = -div sigma(u), by hand."""
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))

    def u(x, y, z):
        return np.sin(PI * x) * np.sin(PI * y) * np.sin(PI * z), x * y * z, np.exp(x) * np.cos(y)

    def f(x, y, z):
        s, c = np.sin, np.cos
        lap = (-3 * PI ** 2 * s(PI * x) * s(PI * y) * s(PI * z), 0 * x, 0 * x)
        # div u = pi cos(pi x) s(pi y) s(pi z) + x z + 0
        gd = (-PI ** 2 * s(PI * x) * s(PI * y) * s(PI * z) + z,
              PI ** 2 * c(PI * x) * c(PI * y) * s(PI * z),
              PI ** 2 * c(PI * x) * s(PI * y) * c(PI * z) + x)
        return tuple(-(mu * lap[i] + (lam + mu) * gd[i]) for i in range(3))
    return u, f


def _l2_error(order: int, size: float) -> tuple[float, float]:
    mesh = mesh_block(1.0, 1.0, 1.0, [], size, 1.0, order)
    model = _model(mesh)
    u_ex, f = _mms()
    ex = np.column_stack(u_ex(*mesh.nodes.T))
    bnd = _boundary(mesh)
    u = _dirichlet(model, bnd, ex[bnd], load=body_force3d(mesh, f)).reshape(-1, 3)
    pts, w = quadrature(4)
    N = shape(order, pts)
    _, det = gradients3d(mesh, pts)
    Xq = np.einsum("qa,mai->mqi", N, mesh.nodes[mesh.tets])
    uq = np.einsum("qa,mai->mqi", N, u[mesh.tets])
    eq = np.stack(u_ex(Xq[..., 0], Xq[..., 1], Xq[..., 2]), axis=-1)
    err = np.sqrt(np.einsum("mq,q,mqi->", det, w, (uq - eq) ** 2))
    return err, len(mesh.tets) ** (-1 / 3)


@pytest.mark.parametrize("order, sizes, lo", [(1, (0.5, 0.25), 1.6), (2, (0.5, 0.25), 2.5)])
def test_l2_convergence_rate_3d(order, sizes, lo):
    """The L2 error of a manufactured solution falls as h^(p+1): rate measured from two uniform meshes (h from
    the element count). Measured here: P1 2.9, P2 3.0 (P1 pre-asymptotic on these coarse meshes); the lower bounds
    leave room for unstructured meshes."""
    (e1, h1), (e2, h2) = (_l2_error(order, s) for s in sizes)
    rate = np.log(e1 / e2) / np.log(h1 / h2)
    assert lo < rate < order + 2.5, rate


def test_manufactured_body_force_is_div_sigma():
    """The hand-derived f of _mms satisfies div sigma(u) + f = 0 (central differences at random points)."""
    u, f = _mms()
    D = elasticity_matrix3d(1.0, 0.3)
    h = 1e-4
    rng = np.random.default_rng(1)

    def sigma(p):
        g = np.zeros((3, 3))
        for j in range(3):
            e = np.zeros(3)
            e[j] = h
            g[:, j] = (np.array(u(*(p + e))) - np.array(u(*(p - e)))) / (2 * h)
        eps = np.array([g[0, 0], g[1, 1], g[2, 2], g[1, 2] + g[2, 1], g[0, 2] + g[2, 0], g[0, 1] + g[1, 0]])
        s = D @ eps
        return np.array([[s[0], s[5], s[4]], [s[5], s[1], s[3]], [s[4], s[3], s[2]]])

    for p in rng.uniform(0.2, 0.8, (5, 3)):
        div = np.zeros(3)
        for j in range(3):
            e = np.zeros(3)
            e[j] = 1e-3
            div += (sigma(p + e)[:, j] - sigma(p - e)[:, j]) / 2e-3
        assert np.allclose(div + np.array(f(*p)), 0.0, atol=1e-4 * np.abs(f(*p)).max())


# ------------------------------------------------------------------------------------------------ contact

@pytest.fixture(scope="module")
def small_contact():
    sc = _scene(order=2, size=0.006, refine=4.0, W=0.03, L=0.03, H=0.015, patch=0.02, radius=0.004)
    return SurfaceModel3D(sc, solver="auto")


def test_fast_contact_agrees_with_a_plain_full_solve(small_contact):
    """The condensed LCP answer against the full model solved directly with the contact nodes held at the tip's
    profile (u_z = q) and everything else free: the same displacements at the contact nodes, and its reactions
    there equal the LCP's forces to round-off; no penetration and no tension anywhere on the window."""
    m = small_contact
    x, y, d = 0.0152, 0.0147, 0.0008
    idx, f, gap = m.contact_forces(x, y, d)
    active = f > 0
    assert active.sum() >= 5
    q = tip_profile3d(m.scene.indenter, x, y, d, m.xy[idx, 0], m.xy[idx, 1])
    assert gap.min() > -1e-12 * d and np.all(gap[active] < 1e-12 * d)
    model = m.model
    base = np.unique(fixed_bottom(model))
    cdofs = model.reduced_index(3 * m.patch[idx[active]] + 2)
    fixed = np.concatenate([base, cdofs])
    order = np.argsort(fixed)
    fac = model.partition(fixed[order])
    u = fac.solve(np.concatenate([np.zeros(len(base)), q[active]])[order])
    reaction = -(model.K @ u)[cdofs]
    assert np.allclose(reaction, f[active], rtol=1e-8, atol=1e-10 * f.max())
    u_fast = m.full_field(x, y, d)
    assert np.abs(u_fast - model.P @ u).max() < 1e-9 * d


def test_hertz_sphere_coarse():
    """A rigid sphere on a block 10 R wide and 5 R deep, P2, coarse (fine size R / 8 under the tip): the force within
    8 % of Hertz F = 4/3 E* R^1/2 d^3/2 and the contact radius within 15 % of sqrt(R d). Measured here: +3.9 % and
    +1.8 %; the excess is the finite block (stiffer than a half-space) and the coarse mesh. `bench/bench_3d.py hertz`
    measures the 1 % target: +0.33 % on a block 40 R wide and 20 R deep with grade 0.25. The maximum von Mises
    (over the elements' stress points) against Hertz's on-axis maximum for the force found (Johnson eq. 3.45): within
    6 % and at 0.35-0.65 a deep (measured +1.5 % at 0.50 a; Hertz: 0.51 a). The nodes' averaged stresses gave +15 %
    at 0.42 a here, which is why fem.contact3d searches stress points."""
    R, d, E, nu, W, H = 0.005, 0.0005, 2500.0, 0.4, 0.05, 0.025
    sc = S.Scene(name="hertz", tissue=S.Tissue(width_m=W, length_m=W, height_m=H, youngs_pa=E, poisson=nu),
                 indenter=S.Indenter(shape="sphere", radius_m=R),
                 analysis=S.Analysis(order=2, mesh_size_m=0.01, surface_refine=20.0, patch_m=2.2 * R))
    a = np.sqrt(R * d)
    mesh = mesh_block(W, W, H, [], 0.01, 20.0, 2, patch_m=2.2 * R, focus=(W / 2, W / 2, R / 8, 1.3 * a))
    m = SurfaceModel3D(sc, mesh=mesh)
    r = m.indent(W / 2, W / 2, d)
    F_hertz = 4 / 3 * E / (1 - nu ** 2) * np.sqrt(R) * d ** 1.5
    assert r.force_n == pytest.approx(F_hertz, rel=0.08)
    assert r.force_n > F_hertz        # a finite block is stiffer than the half-space
    assert r.contact_radius_m == pytest.approx(a, rel=0.15)
    a_f = (3 * r.force_n * R * (1 - nu ** 2) / (4 * E)) ** (1 / 3)     # Hertz's contact radius and centre pressure
    p0 = 3 * r.force_n / (2 * np.pi * a_f ** 2)                        # for the force found
    zr = np.linspace(1e-4, 3.0, 30000)
    vm_axis = np.abs(p0 / (1 + zr ** 2) - p0 * ((1 + nu) * (1 - zr * np.arctan(1 / zr)) - 0.5 / (1 + zr ** 2)))
    assert r.max_von_mises_pa == pytest.approx(vm_axis.max(), rel=0.06)
    assert 0.35 * a_f < r.max_von_mises_at_m[2] < 0.65 * a_f
    assert np.hypot(r.max_von_mises_at_m[0] - W / 2, r.max_von_mises_at_m[1] - W / 2) < 0.5 * a_f
    assert r.contact_radius_over_element == pytest.approx(r.contact_radius_m / (0.01 / 20.0))
    assert r.contact_radius_over_element > STRESS_RESOLVED        # resolved, by the measure the commands warn with
    # the surface pressure at every node within 0.8 a, corner nodes that carry no force included (session 45's review
    # read 0 at a fifth of them): Hertz's p0 sqrt(1 - r^2/a^2) to the documented upper-estimate bias (measured: 96
    # nodes, 0.96-1.24 of Hertz; the 11 without force 1.08-1.17)
    rr = np.hypot(r.contact_x_m - W / 2, r.contact_y_m - W / 2)
    inside = rr < 0.8 * a_f
    p_hertz = p0 * np.sqrt(1 - (rr[inside] / a_f) ** 2)
    assert inside.sum() >= 10 and (r.nodal_force_n[inside] == 0).any()     # (the case the review found is here)
    assert np.all(r.pressure_pa[inside] > 0.8 * p_hertz) and np.all(r.pressure_pa[inside] < 1.4 * p_hertz)
    assert np.all(r.pressure_pa[rr > 1.3 * r.contact_radius_m] == 0)


def _mirrored(mesh, axis: int):
    nodes = mesh.nodes.copy()
    nodes[:, axis] = (mesh.width_m, mesh.length_m)[axis] - nodes[:, axis]
    m = Mesh3D(nodes=nodes, tets=mesh.tets.copy(), region=mesh.region, order=mesh.order, width_m=mesh.width_m,
               length_m=mesh.length_m, height_m=mesh.height_m)
    _orient(m)
    return m


@pytest.fixture(scope="module")
def stone_scene():
    st = (S.Stone(x_m=0.015, y_m=0.015, depth_m=0.006, diameter_m=0.005),)
    return _scene(order=2, size=0.006, refine=4.0, W=0.03, L=0.03, H=0.015, patch=0.02, radius=0.003, stones=st)


def test_mirror_symmetry_in_x_and_y(stone_scene):
    """A stone centred in x and y: the model on the mesh mirrored in x (in y) answers at the mirrored waypoint what
    the original answers, to round-off (assembly, rigid stone, supports and contact carry no handedness); on one
    (unsymmetric) mesh the mirrored forces differ by the discretisation only (measured below 5 %)."""
    sc, d = stone_scene, 0.0008
    mesh = mesh_for3d(sc, use=False)
    m = SurfaceModel3D(sc, mesh=mesh)
    for axis in (0, 1):
        mm = SurfaceModel3D(sc, mesh=_mirrored(mesh, axis))
        for x, y in ((0.011, 0.013), (0.0125, 0.0155)):
            xm, ym = (0.03 - x, y) if axis == 0 else (x, 0.03 - y)
            assert mm.force_n(xm, ym, d) == pytest.approx(m.force_n(x, y, d), rel=1e-9)
            assert m.force_n(xm, ym, d) == pytest.approx(m.force_n(x, y, d), rel=0.05)


def test_stone_raises_force_and_load_a_peak_above_it(stone_scene):
    """The force peaks over the stone, and the load A surface peak lies over it within one surface element."""
    sc, d = stone_scene, 0.0008
    m = SurfaceModel3D(sc)
    assert m.force_n(0.015, 0.015, d) > 1.05 * m.force_n(0.008, 0.015, d)
    res = solve_uniform3d(sc, full_field=False)
    xp, yp, _ = res.surface.peak()
    assert np.hypot(xp - 0.015, yp - 0.015) < 0.006 / 4


class _FullSolveOnly:
    """A condensing factorization seen without ``solve_contact``: displacements by the full solve."""

    def __init__(self, fac):
        self.free, self.c, self.compliance, self.solve = fac.free, fac.c, fac.compliance, fac.solve


@pytest.mark.skipif(not condense.available(), reason="cvxopt (CHOLMOD) is not installed")
def test_stresses_by_the_backward_sweep_equal_the_full_solve(stone_scene, monkeypatch):
    """Stresses under the tip from the backward sweep alone through the factor's interior columns (the patch's
    displacements from the compliance: fem.interior_factor) equal those of the full back-substitution to round-off:
    displacements, the maximum von Mises and where it is, the contact pressures; a rigid stone in the model (its
    prolongation) included. So does the condensing factorization's own sweep (CholmodSchur.solve_contact, the
    fallback when the factor cannot be read in place: two waypoints at once take CHOLMOD's multi-column sweep,
    fem.condense._CholmodDirect, one waypoint cvxopt's)."""
    m = SurfaceModel3D(stone_scene)
    pts = [(0.015, 0.015, 0.0008), (0.0112, 0.0171, 0.0006)]
    fast = m.indent_many(pts)
    u_fast = m.full_field(*pts[1])
    one, u_one = m.indent_with_field(*pts[1])         # the stresses and the field from one sweep: the same
    assert one.max_von_mises_pa == m.indent(*pts[1]).max_von_mises_pa and np.array_equal(u_one, u_fast)
    assert m.interior() is not None or condense._CholmodDirect.get() is None
    monkeypatch.setattr(m, "interior", lambda: None)
    schur = m.indent_many(pts)
    u_schur = m.full_field(*pts[1])
    monkeypatch.setattr(m, "_fac", _FullSolveOnly(m.fac))
    full = m.indent_many(pts)
    u_full = m.full_field(*pts[1])
    assert np.abs(u_fast - u_full).max() < 1e-10 * np.abs(u_full).max()
    assert np.abs(u_schur - u_full).max() < 1e-10 * np.abs(u_full).max()
    for a, b in [*zip(fast, full), *zip(schur, full)]:
        assert a.max_von_mises_pa > 0 and a.max_von_mises_at_m == b.max_von_mises_at_m
        assert a.max_von_mises_pa == pytest.approx(b.max_von_mises_pa, rel=1e-10)
        assert np.allclose(a.pressure_pa, b.pressure_pa, rtol=1e-9, atol=1e-10 * b.pressure_pa.max())


@pytest.mark.skipif(not condense.available(), reason="cvxopt (CHOLMOD) is not installed")
def test_metis_and_amd_orderings_condense_alike(stone_scene, monkeypatch):
    """The interior's ordering (METIS nested dissection, or AMD when pymetis is absent) changes the compliance by
    round-off only; without pymetis "auto" falls back to AMD."""
    model = build_model3d(stone_scene)
    free = np.setdiff1d(np.arange(model.n_dofs), np.unique(fixed_bottom(model)))
    contact = model.reduced_index(3 * patch_nodes(model.mesh, stone_scene.analysis.patch_m) + 2)
    amd = condense.schur(model.K, free, contact, ordering="amd")
    assert amd.ordering == "amd"
    if condense.metis_available():
        nd = condense.schur(model.K, free, contact, ordering="metis")
        assert nd.ordering == "metis"
        assert np.abs(nd.compliance - amd.compliance).max() < 1e-10 * np.abs(amd.compliance).max()
    monkeypatch.setattr(condense, "metis_available", lambda: False)
    assert condense.schur(model.K, free, contact).ordering == "amd"



@pytest.mark.skipif(not condense.available(), reason="cvxopt (CHOLMOD) is not installed")
def test_schur_block_read_in_place_equals_the_converted_factor(stone_scene, monkeypatch):
    """The trailing block read in place from CHOLMOD's supernodal factor (no copy of the factor) is the one cvxopt's
    getfactor conversion gives, bitwise; a factor whose layout the reader does not accept falls back to it."""
    model = build_model3d(stone_scene)
    free = np.setdiff1d(np.arange(model.n_dofs), np.unique(fixed_bottom(model)))
    contact = model.reduced_index(3 * patch_nodes(model.mesh, stone_scene.analysis.patch_m) + 2)
    direct = condense.schur(model.K, free, contact)
    monkeypatch.setattr(condense._CholmodDirect, "trailing_block", lambda self, F, p, nc: None)
    converted = condense.schur(model.K, free, contact)
    if condense._CholmodDirect.get() is not None:
        assert direct.extract == "in place"
    assert converted.extract == "getfactor"
    assert np.array_equal(direct.compliance, converted.compliance)
    assert np.array_equal(direct._Linv, converted._Linv)

def test_rigid_stone_matches_elastic_stone():
    """The 6-DOF rigid-body reduction against a meshed elastic stone 2e6 times stiffer: load A agrees to O(E_t/E_s)
    plus round-off (measured 1e-7 relative)."""
    st = (S.Stone(x_m=0.015, y_m=0.012, depth_m=0.007, diameter_m=0.006),)
    sc = _scene(order=1, stones=st)
    rr = solve_uniform3d(sc, full_field=False, rigid_stones=True)
    re = solve_uniform3d(sc, full_field=False, rigid_stones=False)
    assert rr.model.n_dofs < re.model.n_dofs
    assert rr.reaction_n == pytest.approx(re.reaction_n, rel=1e-5)
    vm_r, vm_e = rr.surface.fields["von_mises_pa"], re.surface.fields["von_mises_pa"]
    assert np.abs(vm_r - vm_e).max() < 1e-5 * vm_e.max()


def test_cache_restores_the_compliance_bitwise(tmp_path, monkeypatch):
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path))
    sc = _scene(order=1, size=0.006, refine=2.0, patch=0.02, radius=0.004)
    from fem import contact3d
    contact3d._CACHE.clear()
    a = surface_model3d(sc, cache=True)
    contact3d._CACHE.clear()
    b = surface_model3d(sc, cache=True)
    assert b is not a and b._model is None          # restored: nothing assembled
    assert np.array_equal(a.C, b.C)
    assert b.force_n(0.015, 0.012, 0.0005) == a.force_n(0.015, 0.012, 0.0005)
    assert b.indent(0.015, 0.012, 0.0005).max_von_mises_pa == pytest.approx(
        a.indent(0.015, 0.012, 0.0005).max_von_mises_pa, rel=1e-9)
    if condense._CholmodDirect.get() is not None:  # fields after a restore: the interior factor, no compliance
        assert b._fac is None and b.interior() is not None
    if condense.available():
        assert b.fac.compliance is None             # the condensing factorization after a restore: no compliance


def test_bad_waypoints_refused():
    sc = _scene(patch=0.02, radius=0.004)
    with pytest.raises(ValueError, match="y_m=0.002 must lie in"):
        check_waypoint3d(sc, 0.015, 0.002, 0.001)
    with pytest.raises(ValueError, match="below the tip radius"):
        check_waypoint3d(sc, 0.015, 0.012, 0.004)
    with pytest.raises(ValueError, match="x_m=nan"):
        check_waypoint3d(sc, float("nan"), 0.012, 0.001)


# ------------------------------------------------------------------------------------------------ scenes

@pytest.mark.parametrize("change, match", [
    (lambda d: d["stone"][0].pop("y_m"), r"stone\[0\]\.y_m is missing"),
    (lambda d: d["tissue"].pop("length_m"), r"stone\[0\]\.y_m = 0\.035 places a sphere"),
    (lambda d: d["indenter"].update(shape="cylinder"), r"indenter\.shape must be 'sphere' or 'flat' in a 3D"),
    (lambda d: d["stone"][0].update(y_m=0.065), r"stone\[0\] \(y_m=0\.065, diameter_m=0\.015\) touches or leaves"),
    (lambda d: d["analysis"].update(patch_m=0.08), r"analysis\.patch_m = 0\.08 is wider"),
    (lambda d: d["analysis"].update(formulation="mixed"), r"formulation = 'mixed' is 2D only"),
    (lambda d: d["tissue"].update(length_m=-1.0), r"tissue\.length_m must be a positive"),
])
def test_3d_scene_validation_names_the_field(change, match):
    d = S.load("block3d").to_dict()
    change(d)
    with pytest.raises(S.SceneError, match=match):
        S.from_dict(d)


def test_3d_builtins_and_2d_keys_unchanged():
    for name in ("block3d", "block3d-healthy", "block3d-left", "block3d-front", "block3d-deep"):
        sc = S.load(name)
        assert sc.is_3d and S.from_dict(sc.to_dict()) == sc
        assert S.from_dict(__import__("tomllib").loads(S.dump_toml(sc)), name) == sc
    assert S.load("block3d-healthy").stones == () and S.load("block3d").stones[0].y_m == 0.035
    assert S.load("paper").key() == "991c9db8de30c8f3"      # the 2D key before issue 15
    assert "length_m" not in S.load("paper").to_dict()["tissue"]
    with pytest.raises(S.SceneError, match="patch_m = 0.01 applies to a 3D block"):
        S.load("paper").with_analysis(patch_m=0.01)
    with pytest.raises(S.SceneError, match=r"indenter\.shape must be 'cylinder' or 'flat' in a 2D scene"):
        S.from_dict({**S.load("paper").to_dict(), "indenter": {"shape": "sphere"}})


def test_element_dofs_and_strain_matrix_shapes():
    mesh = mesh_block(0.03, 0.024, 0.015, [], 0.012, 1.0, 2)
    d = element_dofs3d(mesh)
    assert d.shape == (len(mesh.tets), 30) and d.max() == mesh.n_dofs - 1
    G, _ = gradients3d(mesh, quadrature(2)[0])
    B = strain_matrices3d(G)
    assert B.shape == (len(mesh.tets), 4, 6, 30)
    # a rigid rotation has zero strain
    w = np.array([0.1, -0.2, 0.3])
    u = np.cross(w, mesh.nodes).ravel()
    assert np.abs(np.einsum("mqkn,mn->mqk", B, u[d])).max() < 1e-12


def test_block3d_model_builds_its_rigid_stone(monkeypatch):
    """block3d's stone is 2e6 times stiffer than tissue: a rigid body of 6 DOFs."""
    sc = S.load("block3d").with_analysis(mesh_size_m=0.02, surface_refine=2.0, order=1, patch_m=None, grade=None)
    m = build_model3d(sc, use_cache=False)
    assert m.rigid == [True]
    stone_nodes = np.unique(m.mesh.tets[m.mesh.region == 1])
    assert m.n_dofs == 3 * (m.mesh.n_nodes - len(stone_nodes)) + 6


def test_a_stone_smaller_than_the_bulk_size_meshes():
    """A 5 mm stone in a block meshed at 16 mm (a surrogate-table candidate): the stone's surface is meshed at most
    at its radius. At the bulk's refined size (8 mm) gmsh's surface mesher crashed the process (segfault)."""
    mesh = mesh_block(0.04, 0.04, 0.035, [(0.02, 0.02, 0.035 - 0.00683, 0.0025)], size_m=0.016, surface_refine=4.0,
                      order=2, patch_m=0.03, grade=0.5)
    on = mesh.region > 0
    assert on.any() and (~on).any()
    stone_nodes = np.unique(mesh.tets[on])
    r = np.linalg.norm(mesh.nodes[stone_nodes] - np.array([0.02, 0.02, 0.035 - 0.00683]), axis=1)
    assert r.max() <= 0.0025 * (1 + 1e-9)                   # the stone's elements lie inside its sphere
    assert r.max() >= 0.0025 * (1 - 1e-6)                   # and reach its surface


def test_straightening_folded_p2_elements_leaves_none_folded():
    """A 7 mm stone on the 3D study's coarse mesh (a random stone of `palpate study accuracy3d`): straightening one
    folded P2 element folded a neighbour sharing its edge, and the study stopped on 'inverted element(s)'. The
    straightening repeats until every element is valid."""
    from fem.scene_mesh3d import jacobians3d
    mesh = mesh_block(0.07, 0.07, 0.05, [(0.031412728, 0.041758818, 0.05 - 0.025095319, 0.0070592124 / 2)],
                      size_m=0.016, surface_refine=8.0, order=2, patch_m=0.05, grade=0.5)
    assert mesh.straightened >= 2
    assert np.all(jacobians3d(mesh) > 0)


@pytest.mark.skipif(not condense.available(), reason="cvxopt (CHOLMOD) is not installed")
def test_schur_block_read_in_place_for_every_split():
    """The in-place read against a dense reference for every size of the trailing set on a small SPD matrix (a 2D
    grid Laplacian plus its diagonal): supernodes that straddle the split included. The condensed compliance is the
    inverse of the Schur complement S = K_cc - K_ci K_ii^-1 K_ic."""
    m = 9
    T = sps.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(m, m))
    K = (sps.kron(T, sps.eye(m)) + sps.kron(sps.eye(m), T) + sps.eye(m * m)).tocsr()
    n = K.shape[0]
    Kd = K.toarray()
    free = np.arange(n)
    rng = np.random.default_rng(3)
    for nc in range(1, n, 4):
        c = np.sort(rng.choice(n, nc, replace=False))
        i = np.setdiff1d(free, c)
        S = Kd[np.ix_(c, c)] - Kd[np.ix_(c, i)] @ np.linalg.solve(Kd[np.ix_(i, i)], Kd[np.ix_(i, c)])
        fac = condense.schur(K, free, c)
        if condense._CholmodDirect.get() is not None:
            assert fac.extract == "in place"
        assert np.abs(fac.compliance - np.linalg.inv(S)).max() < 1e-10 * np.abs(np.linalg.inv(S)).max()


@pytest.mark.parametrize("order", [1, 2])
def test_matrix_free_recovery_equals_the_operator(order):
    """recover3d (one displacement vector, no operator built) gives the operator's product to round-off: all nodes,
    a subset (the top, which meets the stone-free tissue only, and nodes on a stone's surface, where the tissue side
    counts), stresses and strains; a random field so that no element's contribution can hide."""
    mesh = mesh_block(0.03, 0.024, 0.015, [(0.015, 0.012, 0.007, 0.004)], 0.006, 3.0, order)
    model = _model(mesh, E=2500.0, nu=0.4)
    u = np.random.default_rng(3).standard_normal(mesh.n_dofs) * 1e-4
    stone = np.unique(mesh.tets[mesh.region == 1])
    for nodes in (None, mesh.top, stone[::3]):
        for strain in (False, True):
            ref = (recovery_operator3d(model, nodes, strain=strain) @ u).reshape(-1, 6)
            got = recover3d(model, u, nodes, strain=strain)
            assert got.shape == ref.shape
            assert np.abs(got - ref).max() <= 1e-12 * np.abs(ref).max()
    with pytest.raises(ValueError, match="displacement vector"):
        recover3d(model, u[:-1])


def test_the_mesh_does_not_depend_on_the_order_stones_are_listed_in():
    """Two stones listed both ways: the same nodes and elements, each stone's region labelled in its list's order
    (session 56's review: gmsh meshed each order differently, the force over a stone moved by 1.4 % and the load A
    peak by 4 %, to the other stone)."""
    s1 = S.Stone(x_m=0.015, y_m=0.022, depth_m=0.008, diameter_m=0.006)
    s2 = S.Stone(x_m=0.026, y_m=0.018, depth_m=0.007, diameter_m=0.005)

    def scene(stones):
        return S.Scene(name="two", tissue=S.Tissue(width_m=0.040, length_m=0.040, height_m=0.020, youngs_pa=800.0,
                                                   poisson=0.45), stones=stones,
                       indenter=S.Indenter(shape="sphere", radius_m=0.005),
                       analysis=S.Analysis(mesh_size_m=0.01, surface_refine=3.0, patch_m=0.030))
    a, b = mesh_scene3d(scene((s1, s2))), mesh_scene3d(scene((s2, s1)))
    assert np.array_equal(a.nodes, b.nodes) and np.array_equal(a.tets, b.tets)
    assert set(np.unique(a.region)) == {0, 1, 2}
    assert np.array_equal(b.region, np.array([0, 2, 1])[a.region])       # stone 1 of one list is stone 2 of the other
    centre = a.nodes[a.tets[a.region == 1][:, :4]].mean(axis=(0, 1))      # region 1 is the first listed: s1
    assert np.hypot(centre[0] - s1.x_m, centre[1] - s1.y_m) < 1e-3
