"""Issue 13, fem side: bad scene values refused with one message naming the field, its value and the allowed range;
mesh size estimated and capped before gmsh; waypoints that crush the tissue and solutions that invert elements
refused; nothing non-finite leaves fem. Small meshes only."""
from __future__ import annotations

import math
import subprocess
import sys
import tomllib
import warnings
from importlib import metadata

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fem import scene as S
from fem.contact import SurfaceModel, check_waypoint
from fem.guards import InvertedElementsError, NonFiniteResultError, check_finite
from fem.mesh import estimate_dofs_bound, estimate_nodes, mesh_scene
from fem.results import Profile
from fem.scene import SceneError
from fem.scene_mesh import check_mesh_budget, estimate_size, gmsh_version, mesh_for

BASE = """name = "t"
[tissue]
width_m = 0.07
height_m = 0.05
youngs_pa = 2500.0
poisson = 0.4
[indenter]
youngs_pa = 60.0e6
[analysis]
mesh_size_m = 0.008
surface_refine = 2.0
top_displacement_m = 0.005
[[stone]]
x_m = 0.035
depth_m = 0.025
diameter_m = 0.015
"""


def _with(section: str, key: str, value: str) -> dict:
    d = tomllib.loads(BASE)
    table = d["stone"][0] if section == "stone" else d[section]
    table[key] = tomllib.loads(f"v = {value}")["v"]
    return d


def test_base_is_valid():
    S.from_dict(tomllib.loads(BASE))


@pytest.mark.parametrize("text,expect", [
    ("", "no [tissue] table"),
    ("# only a comment\n", "no [tissue] table"),
    ('[analysis]\nmesh_size_m = 0.008\n', "no [tissue] table"),
    ("[tissue]\nyoungs_pa = 3000.0\n", "[tissue] lacks width_m, height_m, poisson"),
    ("[tissue]\nwidth_m = 0.07\nheight_m = 0.05\nyoungs_pa = 2500.0\n", "[tissue] lacks poisson"),
])
def test_scene_file_without_tissue_is_refused(tmp_path, text, expect):
    p = tmp_path / "s.toml"
    p.write_text(text)
    with pytest.raises(SceneError) as e:
        S.load(p)
    assert expect in str(e.value)


@pytest.mark.parametrize("section,key,value,expect", [
    ("tissue", "youngs_pa", "1e-300", "tissue.youngs_pa = 1e-300 is outside the allowed range [1e-06, 1e+18] Pa"),
    ("tissue", "youngs_pa", "1e300", "tissue.youngs_pa = 1e+300 is outside the allowed range"),
    ("stone", "youngs_pa", "1e300", "stone[0].youngs_pa = 1e+300 is outside"),
    ("stone", "youngs_pa", "1e-300", "stone[0].youngs_pa = 1e-300 is outside"),
    ("indenter", "youngs_pa", "1e300", "indenter.youngs_pa = 1e+300 is outside"),
    ("indenter", "youngs_pa", "1e-300", "indenter.youngs_pa = 1e-300 is outside"),
    ("indenter", "radius_m", "1e300", "indenter.radius_m = 1e+300 is outside the allowed range [1e-05, 10] m"),
    ("indenter", "radius_m", "0.1", "indenter.radius_m = 0.1 must be at most half the tissue width"),
    ("indenter", "thickness_m", "1e300", "indenter.thickness_m = 1e+300 is outside the allowed range [1e-05, 10]"),
    ("tissue", "width_m", "1000.0", "tissue.width_m = 1000.0 is outside the allowed range [1e-05, 10] m"),
    ("tissue", "width_m", "1e300", "tissue.width_m = 1e+300 is outside"),
    ("analysis", "surface_refine", "1e-300", "analysis.surface_refine = 1e-300 is outside the allowed range [1, 64]"),
    ("analysis", "surface_refine", "1e6", "analysis.surface_refine = 1000000.0 is outside the allowed range [1, 64]"),
    ("analysis", "mesh_size_m", "1e-7", "analysis.mesh_size_m / surface_refine"),
    ("analysis", "top_displacement_m", "-0.001", "analysis.top_displacement_m must be a finite number >= 0"),
    ("analysis", "top_displacement_m", "inf", "analysis.top_displacement_m must be a finite number >= 0"),
])
def test_out_of_range_values_name_field_value_and_range(section, key, value, expect):
    with pytest.raises(SceneError) as e:
        S.from_dict(_with(section, key, value))
    assert expect in str(e.value)


@pytest.mark.parametrize("value, expect", [
    ("0.049", "analysis.top_displacement_m = 0.049 (load A; default 0.005 when not given) is 98% of the tissue height"),
    ("0.016", "the linear model allows at most 30%"),
    ("0.05", "must lie in (0, height_m = 0.05) m"),
    ("0", "0 moves the top by nothing"),
])
def test_load_a_refuses_a_top_displacement_beyond_its_limit_where_it_is_solved(value, expect):
    """Load A's limit is checked where load A is solved (fem.uniform, fem.uniform3d), not when the scene loads: the
    other loads never use it, and the study's 5 mm default refused every command on a tissue under 16.7 mm."""
    from fem.uniform import solve_uniform
    sc = S.from_dict(_with("analysis", "top_displacement_m", value))     # loads: load B does not use it
    with pytest.raises(SceneError) as e:
        solve_uniform(sc)
    assert expect in str(e.value)


def test_a_thin_tissue_loads_and_indents_with_the_default_top_displacement():
    sc = S.from_dict({"tissue": {"width_m": 0.07, "height_m": 0.012, "youngs_pa": 2500.0, "poisson": 0.4},
                      "analysis": {"mesh_size_m": 0.003, "surface_refine": 3.0}})
    assert sc.analysis.top_displacement_m > 0.3 * sc.tissue.height_m     # the default, beyond load A's limit here
    from fem.contact import surface_model
    assert surface_model(sc, cache=False).force_n(0.035, 0.001) > 0
    with pytest.raises(SceneError, match="load A"):
        S.check_load_a(sc)


def test_builtin_scenes_stay_valid():
    for name in S.BUILTIN:
        sc = S.load(name)
        assert S.from_dict(sc.to_dict()) == sc


@pytest.mark.parametrize("changes,field", [
    (dict(mesh_size_m=1e-5), "analysis.mesh_size_m"),
    (dict(mesh_size_m=2e-4, surface_refine=64.0), "analysis.mesh_size_m"),
])
def test_huge_meshes_are_refused_before_gmsh(changes, field, monkeypatch):
    sc = S.load("paper").with_analysis(**changes)
    with pytest.raises(SceneError) as e:
        mesh_for(sc, use=False)                      # would hang in gmsh without the cap
    msg = str(e.value)
    assert "DOFs" in msg and "above the cap of 2e+06" in msg and field in msg
    est = estimate_size(sc)["dofs"]
    assert f"{est:.3g}" in msg
    monkeypatch.setenv("PALPATE_MAX_DOFS", "1000")
    with pytest.raises(SceneError, match="above the cap of 1e"):
        check_mesh_budget(S.load("paper").with_analysis(mesh_size_m=0.004))


@settings(max_examples=60, deadline=None)
@given(w=st.floats(0.01, 0.2), h=st.floats(0.01, 0.2), size=st.floats(5e-4, 0.02), refine=st.floats(0.5, 16.0),
       order=st.sampled_from([1, 2]), stones=st.lists(st.tuples(st.floats(0.1, 0.9), st.floats(0.2, 0.8),
                                                                 st.floats(0.02, 0.2)), max_size=3))
def test_dof_bound_is_above_the_estimate(w, h, size, refine, order, stones):
    """check_mesh_budget skips the estimate when its closed-form bound is within the cap: the bound must hold."""
    placed = [(fx * w, fy * h, fr * min(w, h)) for fx, fy, fr in stones]
    est = estimate_nodes(w, h, placed, size, refine, order)["dofs"]
    assert estimate_dofs_bound(w, h, [r for _, _, r in placed], size, refine, order) >= est


def test_budget_refuses_exactly_what_the_estimate_exceeds(monkeypatch):
    """Around the cap the bound defers to the estimate: refused iff the estimate exceeds the cap."""
    sc = S.load("paper").with_analysis(mesh_size_m=0.003)
    est = estimate_size(sc)["dofs"]
    for cap, refused in ((int(est * 1.01), False), (int(est * 0.99), True)):
        monkeypatch.setenv("PALPATE_MAX_DOFS", str(cap))
        if refused:
            with pytest.raises(SceneError, match="above the cap"):
                check_mesh_budget(sc)
        else:
            check_mesh_budget(sc)


def test_gmsh_version_read_without_importing_it():
    """gmsh's version (part of the cache keys) as its distribution states it, read in a fresh process that then has
    loaded neither gmsh nor importlib.metadata (a cached command's start-up)."""
    assert gmsh_version() == metadata.version("gmsh")
    code = ("import sys; from fem.scene_mesh import gmsh_version; v = gmsh_version(); "
            "print(v, 'gmsh' in sys.modules, 'importlib.metadata' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == [metadata.version("gmsh"), "False", "False"]


@pytest.mark.parametrize("name,order,h,refine", [
    ("paper", 1, 0.008, 2.0), ("paper", 2, 0.004, 4.0), ("healthy", 2, 0.004, 16.0), ("paper-deep", 1, 0.004, 4.0),
    ("paper-left", 2, 0.008, 2.0),
])
def test_dof_estimate_within_a_factor_two(name, order, h, refine):
    sc = S.load(name).with_analysis(order=order, mesh_size_m=h, surface_refine=refine)
    est = estimate_size(sc)
    mesh = mesh_scene(sc)
    assert 0.5 < est["dofs"] / mesh.n_dofs < 2.0
    assert 0.5 < est["top_nodes"] / len(mesh.top) < 2.0


# ------------------------------------------------------------------------------------------------ waypoints

COARSE = dict(mesh_size_m=0.008, surface_refine=2.0)


def _thin() -> S.Scene:
    return S.Scene(name="thin", tissue=S.Tissue(width_m=0.07, height_m=0.005),
                   analysis=S.Analysis(mesh_size_m=0.002, surface_refine=2.0, top_displacement_m=0.0005))


def test_thin_tissue_deep_indentation_is_refused():
    sc = _thin()
    with pytest.raises(ValueError, match="80% of the tissue height"):
        check_waypoint(sc, 0.035, 0.004)
    check_waypoint(sc, 0.035, 0.0015)


def test_paper_scene_at_4mm_is_fine():
    sm = SurfaceModel(S.load("paper").with_analysis(**COARSE))
    r = sm.indent(0.035, 0.004)
    assert r.force_n > 0 and np.isfinite(r.to_dict()["max_von_mises_pa"])
    strain = sm.check_deformation(sm.full_field(0.035, 0.004)[:, None], [0.035], [0.004])
    assert 0 < strain[0] < 1


def _shallow_stone() -> S.Scene:
    stone = S.Stone(x_m=0.035, depth_m=0.0052, diameter_m=0.010)       # top 0.2 mm under the surface
    return S.load("paper").with_stones([stone]).with_analysis(mesh_size_m=0.003, surface_refine=8.0)


def test_stone_just_under_the_surface():
    sc = _shallow_stone()
    with pytest.raises(ValueError, match=r"stone\[0\] under the tip lies 0.2 mm below the surface"):
        check_waypoint(sc, 0.035, 0.004)
    check_waypoint(sc, 0.055, 0.004)                                      # 20 mm away: fine
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        sm = SurfaceModel(sc)
    assert sm.indent(0.055, 0.004).force_n > 0
    # the post-solve check catches the inversion itself (the waypoint check bypassed)
    F = np.zeros((len(sm.top), 1))
    idx, f, _ = sm.contact_forces(0.035, 0.00014)
    F[idx, 0] = f * (0.004 / 0.00014)                                    # the 4 mm load, linearly scaled
    with pytest.raises(InvertedElementsError, match="turn inside out"):
        sm.check_deformation(sm.displacements(F), [0.035], [0.004])


def test_load_a_strain_warning():
    sc = S.load("healthy").with_analysis(top_displacement_m=0.01, **COARSE)
    from fem.uniform import solve_uniform
    with pytest.warns(UserWarning, match="20% exceeds the 10%"):
        solve_uniform(sc, full_field=False)


# ------------------------------------------------------------------------------------------------ non-finite

def test_nonfinite_results_are_named():
    with pytest.raises(NonFiniteResultError, match=r"surface.von_mises_pa\[1\] = inf"):
        Profile(np.array([0.0, 1.0, 2.0]), {"von_mises_pa": np.array([1.0, np.inf, 0.5])}).to_dict()
    with pytest.raises(NonFiniteResultError, match=r"a.b\[0\] = nan"):
        check_finite({"a": {"b": [math.nan]}}, "x")
    assert check_finite({"a": [1.0, np.ones(2)]}, "x")["a"][0] == 1.0


# ------------------------------------------------------------------------------------------------ property

BAD = st.one_of(st.just(math.nan), st.just(math.inf), st.just(-math.inf), st.just(0.0), st.just(-1.0),
                st.just(1e300), st.just(1e-300), st.just(0), st.just(10 ** 400), st.text(max_size=3),
                st.lists(st.floats(), max_size=2), st.booleans(), st.dictionaries(st.text(max_size=2), st.integers(),
                                                                                   max_size=1),
                st.floats(allow_nan=True, allow_infinity=True))
FIELDS = [("tissue", k) for k in ("width_m", "height_m", "youngs_pa", "poisson")] + \
         [("stone", k) for k in ("x_m", "depth_m", "diameter_m", "youngs_pa", "poisson")] + \
         [("indenter", k) for k in ("shape", "radius_m", "youngs_pa", "poisson", "thickness_m")] + \
         [("analysis", k) for k in ("plane", "order", "mesh_size_m", "surface_refine", "top_displacement_m",
                                    "formulation")] + [("top", "name"), ("top", "tissue"), ("top", "stone")]


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(FIELDS), BAD), min_size=1, max_size=3))
def test_from_dict_returns_a_scene_or_raises_scene_error(changes):
    d = tomllib.loads(BASE)
    for (section, key), value in sorted(changes, key=lambda c: c[0][0] == "top"):   # whole tables replaced last
        if section == "top":
            d[key] = value
        elif section == "stone":
            d["stone"][0][key] = value
        else:
            d[section][key] = value
    try:
        sc = S.from_dict(d)
    except SceneError:
        return
    S.validate(sc)
    for v in (sc.tissue.width_m, sc.tissue.youngs_pa, sc.analysis.mesh_size_m):
        assert math.isfinite(v)
