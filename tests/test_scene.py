"""Scene description: built-ins, TOML round trip, and validation errors that name the offending field."""
from __future__ import annotations

import dataclasses

import pytest

from fem import scene as S
from fem.scene import Scene, SceneError, Stone, Tissue

# ------------------------------------------------------------------------------------------------ built-ins

def test_builtin_scenes_match_the_study():
    p = S.load("paper")
    assert p.tissue == Tissue(width_m=0.070, height_m=0.050, youngs_pa=2500.0, poisson=0.4)
    assert [(s.x_m, s.depth_m, s.diameter_m) for s in p.stones] == [(0.035, 0.025, 0.015)]
    assert S.load("paper-left").stones[0].x_m == 0.020
    assert S.load("paper-right").stones[0].x_m == 0.050
    deep = S.load("paper-deep").stones[0]
    assert (deep.x_m, deep.depth_m, deep.diameter_m) == (0.035, 0.040, 0.010)
    assert S.load("healthy").stones == ()
    assert p.analysis.order == 2 and p.analysis.mesh_size_m == 0.002 and p.analysis.plane == "strain"


def test_prior_has_no_stones_and_keeps_tissue():
    p = S.load("paper")
    prior = p.prior()
    assert prior.stones == () and prior.tissue == p.tissue and prior.key() != p.key()
    assert prior.key() == S.load("healthy").key()          # the key ignores the name


def test_unknown_scene_name_is_an_error():
    with pytest.raises(SceneError, match="unknown scene 'nope'"):
        S.load("nope")
    with pytest.raises(SceneError, match="does not exist"):
        S.load("missing.toml")


# ------------------------------------------------------------------------------------------------ TOML

@pytest.mark.parametrize("name", sorted(S.BUILTIN))
def test_toml_round_trip_builtin(name, tmp_path):
    sc = S.load(name)
    path = tmp_path / f"{name}.toml"
    path.write_text(S.dump_toml(sc))
    back = S.load(str(path))
    assert back == sc
    assert back.key() == sc.key()
    assert S.dump_toml(back) == S.dump_toml(sc)


def test_toml_round_trip_awkward_values(tmp_path):
    sc = Scene(name="odd \"name\"", tissue=Tissue(width_m=1e-2, height_m=7e-3, youngs_pa=1.5e16, poisson=-0.25),
               stones=(Stone(x_m=3e-3, depth_m=2e-3, diameter_m=1e-3, youngs_pa=1e-5, poisson=0.49),
                       Stone(x_m=7e-3, depth_m=4e-3, diameter_m=2e-3)),
               analysis=S.Analysis(plane="stress", order=1, mesh_size_m=1e-3, surface_refine=2.5,
                                   top_displacement_m=0.0))
    path = tmp_path / "odd.toml"
    path.write_text(S.dump_toml(sc))
    assert S.load_toml(path) == sc


def test_toml_minimal_file_uses_defaults_and_file_stem(tmp_path):
    path = tmp_path / "tiny.toml"
    # [tissue] and its four fields are required (issue 13: no default tissue); an integer is accepted as a number
    path.write_text("[tissue]\nwidth_m = 0.07\nheight_m = 0.05\nyoungs_pa = 3000\npoisson = 0.4\n")
    sc = S.load_toml(path)
    assert sc.name == "tiny" and sc.tissue.youngs_pa == 3000.0 and isinstance(sc.tissue.youngs_pa, float)
    assert sc.stones == () and sc.analysis == S.Analysis()


def test_toml_syntax_error_is_a_scene_error(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[tissue\nwidth_m = 1\n")
    with pytest.raises(SceneError, match="not valid TOML"):
        S.load_toml(path)


# ------------------------------------------------------------------------------------------------ validation

BASE = S.dump_toml(S.load("paper"))


def _toml_error(tmp_path, text: str) -> str:
    path = tmp_path / "s.toml"
    path.write_text(text)
    with pytest.raises(SceneError) as e:
        S.load_toml(path)
    return str(e.value)


def _replace_line(text: str, section: str, key: str, value: str) -> str:
    out, sec = [], None
    for line in text.splitlines():
        if line.startswith("["):
            sec = line.strip("[]")
        if sec == section and line.startswith(f"{key} ="):
            line = f"{key} = {value}"
        out.append(line)
    assert out != text.splitlines(), f"{section}.{key} not found"
    return "\n".join(out) + "\n"


@pytest.mark.parametrize("section,key,value,field", [
    ("tissue", "width_m", "0.0", "tissue.width_m"),
    ("tissue", "height_m", "-0.05", "tissue.height_m"),
    ("tissue", "youngs_pa", "0.0", "tissue.youngs_pa"),
    ("tissue", "youngs_pa", "nan", "tissue.youngs_pa"),
    ("tissue", "youngs_pa", "inf", "tissue.youngs_pa"),
    ("tissue", "poisson", "0.5", "tissue.poisson"),
    ("tissue", "poisson", "-1.0", "tissue.poisson"),
    ("stone", "diameter_m", "0.0", "stone[0].diameter_m"),
    ("stone", "youngs_pa", "-5.0", "stone[0].youngs_pa"),
    ("stone", "poisson", "0.7", "stone[0].poisson"),
    ("indenter", "radius_m", "0.0", "indenter.radius_m"),
    ("indenter", "youngs_pa", "0.0", "indenter.youngs_pa"),
    ("indenter", "thickness_m", "-1.0", "indenter.thickness_m"),
    ("indenter", "shape", '"sphere"', "indenter.shape"),
    ("analysis", "plane", '"axisymmetric"', "analysis.plane"),
    ("analysis", "order", "3", "analysis.order"),
    ("analysis", "mesh_size_m", "0.0", "analysis.mesh_size_m"),
    ("analysis", "mesh_size_m", "0.03", "analysis.mesh_size_m"),
    ("analysis", "surface_refine", "-2.0", "analysis.surface_refine"),
    ("analysis", "top_displacement_m", "-0.06", "analysis.top_displacement_m"),
])
def test_bad_values_name_the_field(tmp_path, section, key, value, field):
    msg = _toml_error(tmp_path, _replace_line(BASE, section, key, value))
    assert field in msg


@pytest.mark.parametrize("section,key,value,field", [
    ("tissue", "youngs_pa", '"soft"', "tissue.youngs_pa"),
    ("tissue", "poisson", "true", "tissue.poisson"),
    ("stone", "x_m", "[0.035]", "stone[0].x_m"),
    ("analysis", "order", "2.0", "analysis.order"),
    ("analysis", "plane", "1", "analysis.plane"),
    ("indenter", "shape", "3", "indenter.shape"),
])
def test_wrong_types_name_the_field(tmp_path, section, key, value, field):
    msg = _toml_error(tmp_path, _replace_line(BASE, section, key, value))
    assert field in msg


@pytest.mark.parametrize("where,value,expect", [
    ("x_m", "0.005", "leaves the tissue sideways"),       # 7.5 mm radius, 5 mm from the left edge
    ("x_m", "0.065", "leaves the tissue sideways"),
    ("depth_m", "0.005", "through the top or bottom"),
    ("depth_m", "0.045", "through the top or bottom"),
    ("depth_m", "0.0075", "through the top or bottom"),   # tangent to the top surface counts as leaving
])
def test_stone_leaving_the_tissue(tmp_path, where, value, expect):
    msg = _toml_error(tmp_path, _replace_line(BASE, "stone", where, value))
    assert "stone[0]" in msg and where in msg and expect in msg


def _two_stones(dx: float) -> Scene:
    a = Stone(x_m=0.020, depth_m=0.025, diameter_m=0.010)
    return Scene(stones=(a, dataclasses.replace(a, x_m=0.020 + dx)))


def test_stones_touching_or_overlapping_are_rejected():
    _two_stones(0.0101)                                 # 0.1 mm apart: accepted
    for dx in (0.010, 0.008):                           # touching, overlapping
        with pytest.raises(SceneError, match=r"stone\[1\] touches or overlaps stone\[0\]"):
            _two_stones(dx)


@pytest.mark.parametrize("text,expect", [
    ("colour = 1\n", "unknown top-level key(s): colour"),
    ("[tissue]\nstiffness = 1.0\n", "unknown key(s) in [tissue]: stiffness"),
    ("[[stone]]\nx_m = 0.03\ndepth_m = 0.02\ndiameter_m = 0.01\nradius_m = 0.005\n",
     "unknown key(s) in [stone[0]]: radius_m"),
    ("[analysis]\nsolver = \"lu\"\n", "unknown key(s) in [analysis]: solver"),
    ("[indenter]\nangle = 1.0\n", "unknown key(s) in [indenter]: angle"),
])
def test_unknown_keys_are_named(tmp_path, text, expect):
    assert expect in _toml_error(tmp_path, text)


@pytest.mark.parametrize("text,expect", [
    ("name = 3\n", "name must be a string"),
    ("tissue = 5\n", "[tissue] must be a table"),
    ("stone = 5\n", "stone must be an array of tables"),
    ("[[stone]]\nx_m = 0.03\ndepth_m = 0.02\n", "[stone[0]]"),          # diameter_m missing
])
def test_structural_errors(tmp_path, text, expect):
    assert expect in _toml_error(tmp_path, text)


def test_python_construction_is_validated_too():
    with pytest.raises(SceneError, match="tissue.poisson"):
        Scene(tissue=Tissue(poisson=0.5))
    with pytest.raises(SceneError, match="analysis.order"):
        S.load("paper").with_analysis(order=3)
    with pytest.raises(SceneError, match=r"stone\[0\]"):
        S.load("paper").with_stones([Stone(x_m=0.035, depth_m=0.049, diameter_m=0.004)])
