"""Table keys name only what changes the answer (planner.surrogate.table_scene, fem.tip.contact_scene).

The surrogate's table is keyed at a unit tissue modulus and scaled by E: checked here against direct fem at another
modulus (not assumed). A tip fem treats as rigid shares the rigid tip's table. A user's TOML scene with the paper's
tissue (any modulus) and a rigid tip reuses the shipped table: no table is built."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from app.cli import main
from fem.contact import surface_key
from fem.scene import Indenter, Stone, load
from fem.tip import TIP_TOLERANCE, rigid_tip_bound
from planner import surrogate as sg

STONE = Stone(x_m=0.031, depth_m=0.019, diameter_m=0.011)
X0 = np.array([0.020, 0.027, 0.031, 0.036, 0.045])


def _with_tissue(scene, **changes):
    return dataclasses.replace(scene, tissue=dataclasses.replace(scene.tissue, **changes))


def _forces(scene, depth_m=0.004):
    m = sg.stone_model(scene)
    return np.array([m.force_n(float(x), depth_m) for x in X0])


def test_force_is_proportional_to_the_tissue_modulus_at_fixed_poisson_ratio():
    """Direct fem, rigid stone and tip: 7000 Pa gives 2.8 x the force of 2500 Pa to round-off; another Poisson
    ratio does not (so the key must hold nu)."""
    paper = load("paper").prior().with_stones([STONE])
    f_ref = _forces(paper)
    f_stiff = _forces(_with_tissue(paper, youngs_pa=7000.0))
    np.testing.assert_allclose(f_stiff, 2.8 * f_ref, rtol=1e-9)
    f_nu = _forces(_with_tissue(paper, poisson=0.45))
    assert np.max(np.abs(f_nu / f_ref - 1)) > 0.05


def test_the_scaled_table_matches_direct_fem_at_another_modulus(monkeypatch):
    """The shipped table (built at 2500 Pa) scaled to 6000 Pa against direct fem at 6000 Pa: its error is the
    interpolation error at 2500 Pa, scaled by the same factor (to 1e-6 of the contrast), and small."""
    monkeypatch.setattr(sg, "build_table", _no_build)
    paper = load("paper").prior()
    stiff = _with_tissue(paper, youngs_pa=6000.0)
    errs = {}
    for prior in (paper, stiff):
        sur = sg.load_surrogate(prior, build=False)
        base = sg.surface_model(prior)
        true = _forces(prior.with_stones([STONE])) - np.array([base.force_n(float(x), 0.004) for x in X0])
        est = sur.contrast(X0, 0.004, STONE.x_m, STONE.depth_m, STONE.diameter_m)
        errs[prior.tissue.youngs_pa] = (est - true, np.max(np.abs(true)))
    (e_ref, peak_ref), (e_stiff, peak_stiff) = errs[2500.0], errs[6000.0]
    assert peak_stiff == pytest.approx(2.4 * peak_ref, rel=1e-9)
    np.testing.assert_allclose(e_stiff, 2.4 * e_ref, atol=1e-6 * peak_stiff)
    assert np.max(np.abs(e_stiff)) < 0.03 * peak_stiff


def _no_build(*args, **kwargs):
    raise AssertionError("a surrogate table was built")


def test_what_selects_a_table():
    """Same key: another tissue modulus, the 60 MPa tip (rho = 4.5e-5 < 1e-3), a rigid tip, another name, other
    stones, load A's displacement. Other key: Poisson ratio, size, tip radius, an elastic (soft) tip, mesh."""
    paper = load("paper").prior()
    assert 0 < rigid_tip_bound(paper) < 5e-5 < TIP_TOLERANCE
    key = sg.cache_path(paper, sg.Grid()).name
    rigid_tip = dataclasses.replace(paper, indenter=Indenter())
    same = [rigid_tip, _with_tissue(paper, youngs_pa=900.0), dataclasses.replace(paper, name="mine"),
            paper.with_analysis(top_displacement_m=0.002)]
    for s in same:
        assert sg.cache_path(s, sg.Grid()).name == key, s
    soft_tip = dataclasses.replace(paper, indenter=Indenter(youngs_pa=1.0e6))       # rho = 2.7e-3: elastic
    assert rigid_tip_bound(soft_tip) > TIP_TOLERANCE
    other = [_with_tissue(paper, poisson=0.45), _with_tissue(paper, width_m=0.060), soft_tip,
             dataclasses.replace(paper, indenter=Indenter(radius_m=0.004)), paper.with_analysis(mesh_size_m=0.0015)]
    for s in other:
        assert sg.cache_path(s, sg.Grid()).name != key, s
    # an elastic tip keys by E_tip / E: the same soft tip on a stiffer tissue in proportion shares its table
    soft_stiff = dataclasses.replace(_with_tissue(soft_tip, youngs_pa=5000.0), indenter=Indenter(youngs_pa=2.0e6))
    assert sg.cache_path(soft_stiff, sg.Grid()).name == sg.cache_path(soft_tip, sg.Grid()).name
    # fem's own disk cache: the rigid-treated tip shares the rigid tip's operators; a soft tip does not
    assert surface_key(paper, {}) == surface_key(rigid_tip, {})
    assert surface_key(paper, {"rigid_tip": False}) != surface_key(rigid_tip, {"rigid_tip": False})
    assert surface_key(soft_tip, {}) != surface_key(rigid_tip, {})


TOML = """name = "my-kidney"
[tissue]
width_m = 0.070
height_m = 0.050
youngs_pa = {youngs_pa}
poisson = 0.4
[[stone]]
x_m = 0.030
depth_m = 0.020
diameter_m = 0.012
"""


@pytest.mark.parametrize("youngs_pa", [2500.0, 5000.0])
def test_run_on_a_user_scene_reuses_the_shipped_table(tmp_path, monkeypatch, youngs_pa):
    """`palpate run my.toml --sim`: the paper's tissue (and a stiffer one) with a rigid tip (no tip modulus)
    reuses the shipped table, scaled; no table is built (the builder raises) and the stone is found."""
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path / "cache"))      # only the shipped table can be found
    monkeypatch.setattr(sg, "build_table", _no_build)
    sg._MEM.clear()
    scene = tmp_path / "my.toml"
    scene.write_text(TOML.format(youngs_pa=youngs_pa))
    out = tmp_path / "run"
    assert main(["run", str(scene), "--sim", "--budget-probes", "15", "--no-figure", "--out", str(out)]) == 0
    r = json.loads((out / "result.json").read_text())
    assert r["detected"]
    assert abs(r["estimate"]["x_m"]["value"] - 0.030) < 1e-3
    assert not list((tmp_path / "cache").glob("surrogate-*"))
