"""The 3D surrogate (planner.surrogate3d) on a small coarse block and a tiny grid (seconds of fem): on-node values
equal direct fem to round-off, between nodes and off-centre within a measured bound, the modulus scaling, smoothness
in every argument, and the fingerprint catching a changed fem."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fem import contact3d
from fem.scene import Analysis, Indenter, Scene, Tissue
from planner import fingerprint
from planner import surrogate3d as s3
from planner.tasks import Runner

BLOCK = Scene(name="small-block", tissue=Tissue(width_m=0.030, length_m=0.030, height_m=0.020),
              indenter=Indenter(shape="sphere", radius_m=0.004, youngs_pa=60.0e6),
              analysis=Analysis(order=2, mesh_size_m=0.008, surface_refine=4.0, patch_m=0.024, grade=0.5))
GRID = s3.Grid3D(s_m=(2e-3, 3e-3, 4.5e-3), diam_m=(5e-3, 7e-3), levels_m=(1e-3, 1.5e-3, 2e-3, 2.5e-3),
                 dr_m=1e-3, r_max_m=0.030, n_angles=8, mesh_size_m=0.008, grade=0.5, cal_nodes=())
CENTRE = s3.patch_centre(BLOCK)       # where the table's candidates sit (to the last bit: gmsh's mesh follows it)


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    """The tiny table, built serially into a private cache directory (also returned as the directory)."""
    cache = tmp_path_factory.mktemp("cache3d")
    mp = pytest.MonkeyPatch()
    mp.setenv("PALPATE_CACHE_DIR", str(cache))
    mp.delenv("PALPATE_CACHE", raising=False)
    s3._MEM.clear()
    sur = s3.load_surrogate3d(BLOCK.prior(), runner=Runner(workers=1, progress=False), grid=GRID)
    yield sur, cache, mp
    mp.undo()
    s3._MEM.clear()


def _direct_same_mesh(xs, ys, depth, diam, x, y, d):
    """Direct fem on the table's mesh: the stone model minus the prior on the same mesh."""
    scene = s3.table_scene(BLOCK.prior(), GRID, BLOCK.tissue.youngs_pa)
    st = s3.stone_scene(scene, xs, ys, depth, diam)
    m = s3.stone_model3d(st)
    return s3.forces_at(m, x, y, d) - s3.forces_at(s3.same_mesh_prior(st, m), x, y, d)


def test_on_node_centred_equals_direct_fem_to_round_off(table):
    """A grid candidate under the patch centre, probes on table offsets and levels: the table equals direct fem's
    contrast averaged over the 8 directions (how the table defines its axisymmetric profile) to round-off."""
    sur = table[0]
    s, D = GRID.s_m[1], GRID.diam_m[1]
    r = np.array([0.0, 2e-3, 4e-3, 6e-3])
    th = np.arange(8) * np.pi / 4
    d = 2e-3
    X = (CENTRE[0] + r[:, None] * np.cos(th)).ravel()
    Y = (CENTRE[1] + r[:, None] * np.sin(th)).ravel()
    direct = _direct_same_mesh(*CENTRE, s + D / 2, D, X, Y, np.full(len(X), d)).reshape(len(r), 8).mean(axis=1)
    est = sur.contrast(CENTRE[0] + r, CENTRE[1], d, *CENTRE, s + D / 2, D)
    assert direct[0] > 0
    np.testing.assert_allclose(est, direct, rtol=1e-9, atol=1e-12)


def test_between_nodes_and_off_centre_within_the_measured_error(table):
    """A stone between the grid nodes, 2 mm off the centre in x and -1.5 mm in y, against direct fem's contrast on
    the table's mesh (the stone model minus the prior on the same mesh): RMS error under 10 % of the peak contrast
    over a probe grid (measured: 6.6 %; a tiny grid, its D step is 2 mm). On this coarse mesh the contrast against
    the prior's own mesh differs from it by 39 % of the peak (RMS; mesh ripple, docs/surrogate3d.md)."""
    sur = table[0]
    xs, ys, s, D = 0.017, 0.0135, 2.6e-3, 6.1e-3
    X, Y = s3.probe_grid(BLOCK, 7)
    d = np.full(len(X), 2e-3)
    true = _direct_same_mesh(xs, ys, s + D / 2, D, X, Y, d)
    est = sur.contrast(X, Y, d, xs, ys, s + D / 2, D)
    ok = np.isfinite(true)
    peak = np.abs(true[ok]).max()
    rms = np.sqrt(np.mean((est[ok] - true[ok]) ** 2))
    assert ok.sum() > 20 and rms < 0.10 * peak, (rms / peak, ok.sum())


def test_the_table_scales_with_the_tissue_modulus(table):
    """The same table serves a stiffer prior, scaled by E / youngs_ref_pa, and fem's force scales the same way."""
    sur, _, _ = table
    stiff = dataclasses.replace(BLOCK, tissue=dataclasses.replace(BLOCK.tissue, youngs_pa=6000.0)).prior()
    sur2 = s3.load_surrogate3d(stiff, build=False, grid=GRID)
    args = (np.array([0.012, 0.016, 0.019]), 0.014, 2e-3, 0.016, 0.015, 5.5e-3, 6e-3)
    np.testing.assert_allclose(sur2.contrast(*args), 2.4 * sur.contrast(*args), rtol=1e-12)
    assert sur2.abs_err_n == pytest.approx(2.4 * sur.abs_err_n)
    fp = s3.fingerprint(s3.table_scene(BLOCK.prior(), GRID, 2500.0))
    np.testing.assert_allclose(s3.fingerprint(s3.table_scene(stiff, GRID, 6000.0)), 2.4 * fp, rtol=1e-9)


@pytest.mark.parametrize("arg", range(7))
def test_smooth_in_every_argument(table, arg):
    """A sweep of each argument across several grid cells: finite values, and no jump (the steps change slowly:
    Catmull-Rom is C1)."""
    sur = table[0]
    base = [0.014, 0.016, 1.7e-3, 0.015, 0.015, 6e-3, 6e-3]
    span = [(0.009, 0.021), (0.009, 0.021), (1.0e-3, 2.5e-3), (0.010, 0.020), (0.010, 0.020),
            (2.1e-3 + 3e-3, 4.4e-3 + 3e-3), (5e-3, 7e-3)][arg]
    v = np.linspace(*span, 401)
    f = []
    for val in v:
        a = list(base)
        a[arg] = val
        f.append(float(sur.contrast(np.array([a[0]]), np.array([a[1]]), np.array([a[2]]), *a[3:])[0]))
    f = np.array(f)
    assert np.all(np.isfinite(f))
    df = np.diff(f)
    assert np.abs(df).max() > 0
    assert np.abs(np.diff(df)).max() < 0.1 * np.abs(df).max()


def test_the_fingerprint_catches_a_changed_fem(table, monkeypatch, capsys):
    """fem's contact answering 0.1 % differently (changed code: a new planner.fingerprint.numbers_version): the
    cached table is not used (and not rebuilt with build=False)."""
    s3._MEM.clear()
    assert s3.load_surrogate3d(BLOCK.prior(), build=False, grid=GRID) is not None
    s3._MEM.clear()
    orig = contact3d.SurfaceModel3D.force_n
    monkeypatch.setattr(contact3d.SurfaceModel3D, "force_n", lambda self, *a: 1.001 * orig(self, *a))
    monkeypatch.setattr(fingerprint, "numbers_version", lambda: "fem changed")
    with pytest.raises(FileNotFoundError):
        s3.load_surrogate3d(BLOCK.prior(), build=False, grid=GRID)
    assert "fingerprint differs" in capsys.readouterr().err


def test_the_fingerprint_is_computed_once_per_fem_version(table, monkeypatch):
    """A second process (memory cleared) reads today's fingerprint from the disk cache: the same numbers as
    computing it, without fem; a changed fem (numbers_version) or the cache switched off computes it again."""
    s3._MEM.clear()
    s3.load_surrogate3d(BLOCK.prior(), build=False, grid=GRID)          # computed or read: now on disk
    own = s3.table_scene(BLOCK.prior(), GRID, BLOCK.tissue.youngs_pa)
    fresh = s3.fingerprint(own)
    calls = []
    real = s3.fingerprint
    monkeypatch.setattr(s3, "fingerprint", lambda sc: calls.append(1) or real(sc))
    s3._MEM.clear()
    s3.load_surrogate3d(BLOCK.prior(), build=False, grid=GRID)
    assert not calls
    np.testing.assert_array_equal(s3._fingerprint_now(own), fresh)
    monkeypatch.setattr(fingerprint, "numbers_version", lambda: "another fem")
    np.testing.assert_array_equal(s3._fingerprint_now(own), fresh)
    assert len(calls) == 1
    monkeypatch.setenv("PALPATE_CACHE", "0")
    s3._fingerprint_now(own)
    assert len(calls) == 2


def test_a_calibration_is_applied_only_on_the_mesh_it_was_made_for(table, monkeypatch):
    """The table's mesh needs none; another mesh gets its own (solved once, then cached), never another mesh's: the
    shipped block3d table was calibrated on block3d's default mesh and applied, before this, to scenes on the table's
    own mesh too (the tests' coarse block and the 3D study), scaling their contrast by 0.82-0.95 for nothing."""
    sur, _, _ = table
    assert np.all(sur.mesh_factor == 1.0)                                   # BLOCK is on GRID's mesh
    grid = dataclasses.replace(GRID, cal_nodes=((1, 1),))
    finer = dataclasses.replace(BLOCK, analysis=dataclasses.replace(BLOCK.analysis, mesh_size_m=0.006)).prior()
    with pytest.raises(FileNotFoundError, match="calibration"):
        s3.calibration_for(finer, grid, sur.data, build=False)
    cal_s, fac = s3.calibration_for(finer, grid, sur.data, runner=Runner(workers=1, progress=False))
    assert cal_s.tolist() == [grid.s_m[1]] and fac.shape == (1, len(grid.levels_m))
    assert np.all(np.isfinite(fac)) and np.all(np.abs(fac - 1) < 0.3) and np.any(fac != 1.0)
    monkeypatch.setattr(s3, "calibrate3d", lambda *a, **k: pytest.fail("solved again instead of read from the cache"))
    again = s3.calibration_for(finer, grid, sur.data, build=False)
    assert np.array_equal(again[1], fac)
    stored = dict(sur.data, cal_mesh=s3.own_mesh(finer), cal_s_m=cal_s, cal_factor=2 * fac)
    assert np.array_equal(s3.calibration_for(finer, grid, stored)[1], 2 * fac)   # built for this mesh: its own


def test_remembered_stencils_give_the_contrast_computed_afresh(table):
    """The radial and depth stencils are remembered under their exact inputs (a Jacobian's steps repeat them): the
    same contrast, bit for bit, as a table that remembers nothing, over repeated, broadcast and changed inputs."""
    sur = table[0]
    fresh = s3.Surrogate3D(sur.data, calibration=sur.calibration)
    fresh.scale, fresh.T, fresh.abs_err_n = sur.scale, sur.T, sur.abs_err_n
    rng = np.random.default_rng(4)
    x0, x1, y0, y1 = sur.region
    x, y = rng.uniform(x0, x1, 25), rng.uniform(y0, y1, 25)
    d = rng.choice(sur.levels, 25)
    s0, D0 = float(sur.s[1]), float(sur.diam[1])
    for trial in range(40):
        xs, ys = (float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1))) if trial % 3 else (0.5 * (x0 + x1), y0)
        dd = d if trial % 2 else d + 1e-4 * (trial % 5)
        got = sur.contrast(x, y, dd, xs, ys, s0 + D0 / 2, D0)
        fresh._stencils.clear()
        assert np.array_equal(got, fresh.contrast(x, y, dd, xs, ys, s0 + D0 / 2, D0))
    assert np.array_equal(sur.contrast(x[:3], y[0], d[0], xs, ys, s0 + D0 / 2, D0),          # broadcast inputs
                          fresh.contrast(x[:3], np.full(3, y[0]), np.full(3, d[0]), xs, ys, s0 + D0 / 2, D0))
    assert sur._stencils and not any(a.flags.writeable for v in sur._stencils.values() for a in v)
