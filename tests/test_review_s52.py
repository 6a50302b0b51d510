"""Session 52: a NO STONE answer reports the no-stone fit's tissue (2D, as 3D did); a section wider than 70 mm keeps
the table's positions within 35 mm of its side and spaces the rest at most FAR_SPACING_M apart."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fem.contact import surface_model
from fem.scene import load
from planner.localize import Measurements, localize
from planner.surrogate import FAR_SPACING_M, REF_WIDTH_M, Grid, _grid_xs

DEPTH_M = 0.004
SIGMA_N = 2e-4


class _Louder:
    """A surrogate whose stones press ``gain`` times as hard: another stone fit, the same no-stone fit."""

    def __init__(self, sur, gain):
        self._sur, self._gain = sur, gain

    def __getattr__(self, name):
        return getattr(self._sur, name)

    def contrast(self, *a, **k):
        return self._gain * self._sur.contrast(*a, **k)

    def contrast_many(self, *a, **k):
        return self._gain * self._sur.contrast_many(*a, **k)

    def contrast_slopes(self, *a, **k):
        return self._gain * self._sur.contrast_slopes(*a, **k)


def test_a_no_stone_answer_reports_the_no_stone_fits_tissue(paper_prior, paper_surrogate):
    """Session 51's review: a 2D NO STONE answer's tissue estimates, bounds and contrast came from the stone fit it
    had rejected. Now they are the no-stone fit's: they do not change when the stone model does."""
    W = paper_prior.tissue.width_m
    x = np.linspace(0.005, W - 0.005, 19)
    lin = surface_model(paper_prior)
    F = 1.3 * np.array([lin.force_n(float(v), DEPTH_M) for v in x])
    rng = np.random.default_rng(3)
    n = len(x)
    m = Measurements(x, np.full(n, DEPTH_M), F + rng.normal(0, SIGMA_N, n), np.full(n, SIGMA_N), np.full(n, 5.0),
                     np.arange(n))
    a = localize(paper_prior, m, paper_surrogate)
    b = localize(paper_prior, m, _Louder(paper_surrogate, 3.0))
    assert not a.detected and not b.detected
    assert a.nuisance["fit"] == b.nuisance["fit"] == "no stone"
    assert (a.x_m, a.depth_m) != (b.x_m, b.depth_m)                # the stone fits differ ...
    for k in ("stiffness_scale", "thickness_scale", "surface_offset_m", "surface_tilt_rad", "sensor_drift_n_per_s",
              "finite_strain_amplitude"):
        assert a.nuisance[k] == pytest.approx(b.nuisance[k], rel=1e-9, abs=1e-12), k    # ... the answer does not
    assert np.allclose(a.contrast_n, b.contrast_n, rtol=0, atol=1e-12)
    assert a.nuisance["stiffness_scale"][0] == pytest.approx(1.3, rel=0.02)
    assert not [s for s in a.at_bound if s in ("x", "clearance", "diameter")]
    assert a.nuisance["finite_strain_gain_chi2"] is None


def _prior(width_m: float):
    p = load("paper").prior()
    return dataclasses.replace(p, tissue=dataclasses.replace(p.tissue, width_m=width_m))


@pytest.mark.parametrize("width_m", [0.0701, 0.079, 0.09, 0.12, 0.2, 0.3])
def test_a_wider_section_keeps_the_positions_near_its_side_and_bounds_the_rest(width_m):
    """Session 51's review: on a 200 mm section the positions 15 and 36.25 mm (session 50's rule) left a gap where
    the interpolated contrast was 1.1-1.6 % off fem and stones came out 5.5-7.9 sigma off. The side changes the
    contrast within some 35 mm of it: Grid.xs_m's positions stay there; beyond, at most FAR_SPACING_M apart."""
    g = np.asarray(Grid().xs_m)
    xs = _grid_xs(_prior(width_m), Grid())
    assert xs[-1] == pytest.approx(width_m / 2) and np.all(np.diff(xs) > 0)
    assert np.array_equal(xs[:len(g) - 1], g[:-1])
    far = xs[xs > g[-1] + 1e-9]
    assert np.all(np.diff(np.r_[g[-1], far]) <= FAR_SPACING_M + 1e-12)
    if width_m / 2 - g[-1] >= g[-1] - g[-2]:
        assert xs[len(g) - 1] == g[-1]
    if width_m == 0.0701:               # just wider than 70 mm: next to the grid itself (continuous there)
        assert np.allclose(xs, g, atol=1e-4)


def test_up_to_70_mm_the_positions_still_scale():
    assert np.array_equal(_grid_xs(_prior(0.05), Grid()), np.asarray(Grid().xs_m) * 0.05 / REF_WIDTH_M)


def test_a_thin_blocks_thinner_copy_takes_a_mesh_fem_accepts(tmp_path):
    """Session 51's review: a 40 x 40 x 20 mm block with the default 3D analysis (mesh 9.6 mm, fem's limit is half
    the height) had its 3D table built for 9.7 min, then its 0.9-height copy for the thickness term refused."""
    from fem.scene import validate
    from planner.tissue_response import THICKNESS_STEP, scene_with_height, thickness_reference
    f = tmp_path / "small40.toml"
    f.write_text('name = "small40"\n[tissue]\nwidth_m = 0.040\nlength_m = 0.040\nheight_m = 0.020\n'
                 'youngs_pa = 5000.0\npoisson = 0.45\n[indenter]\nshape = "sphere"\nradius_m = 0.002\n')
    sc = load(str(f))
    validate(sc)
    assert sc.is_3d and sc.analysis.mesh_size_m > 0.9 * sc.tissue.height_m / 2   # the copy's limit it would break
    ref = thickness_reference(sc)
    for node, h in zip((scene_with_height(sc, 1.0 - THICKNESS_STEP), ref, scene_with_height(sc, 1.0 + THICKNESS_STEP)),
                       (0.018, 0.020, 0.022)):
        validate(node)
        assert node.tissue.height_m == pytest.approx(h)
        assert node.analysis.mesh_size_m == pytest.approx(0.9 * 0.02 / 2)      # one mesh for the three
    assert thickness_reference(load("block3d").prior()) is None                 # uncapped: the prior's nodes


def test_a_capped_mesh_leaves_the_priors_force_and_takes_the_slope_on_one_mesh():
    """The session-52 review: capping the thinner node's mesh alone moved its force as much as the 10 % height
    change (slope 2.4 times too small); all three nodes on the capped mesh put the mesh change into the prior's own
    force (a 3D run's stone then came out 2.4-3.2 sigma off). Now the outer nodes are taken relative to the prior's
    height on their mesh: the prior's force is fem's on its own mesh, the slope the capped mesh's, and near a finer
    mesh's (a 2D section 20 mm tall, mesh 9.8 mm where the 18 mm node allows 9 mm)."""
    from fem import recall
    from planner.tissue_response import prior_and_thickness_slope, thickness_reference
    base = load("paper")

    def section(mesh_m):
        return dataclasses.replace(base, stones=(), tissue=dataclasses.replace(base.tissue, height_m=0.02),
                                   analysis=dataclasses.replace(base.analysis, mesh_size_m=mesh_m))
    x, d = np.array([0.01, 0.03]), 0.003
    capped, one_mesh, fine = section(0.0098), section(0.009), section(0.003)
    assert thickness_reference(capped) is not None and thickness_reference(one_mesh) is None
    F, slope = prior_and_thickness_slope(capped, x, d)
    assert np.allclose(F, [recall.force_n(capped, float(v), d) for v in x], rtol=1e-12)
    F9, slope9 = prior_and_thickness_slope(one_mesh, x, d)
    assert not np.allclose(F, F9, rtol=1e-3)                   # (the mesh moves the force: -2.0 and +0.5 % here)
    assert np.allclose(slope / F, slope9 / F9, rtol=1e-9)
    Ff, slopef = prior_and_thickness_slope(fine, x, d)
    assert np.all(slope < 0) and np.allclose(slope / F, slopef / Ff, rtol=0.05)  # measured 0.1 and 0.5 % off


SMALL_TIP = """name = "{name}"
[tissue]
width_m = 0.060
height_m = 0.040
youngs_pa = 4000.0
poisson = 0.45
[indenter]
shape = "cylinder"
radius_m = {radius}
"""


def _small_tip(tmp_path, radius):
    f = tmp_path / f"tip{radius}.toml"
    f.write_text(SMALL_TIP.format(name=f"tip{radius}", radius=radius))
    return str(f)


def test_the_default_depth_limit_follows_a_small_tip():
    """Session 51's review: a tip of radius 4 mm or less refused a run's default depth limit (4 mm) and needed
    --depth-limit-m; now the default is 0.8 of a radius up to 5 mm (the built-in 5 mm tips keep 4 mm)."""
    import argparse

    from app.runexec import run_limits
    from core.contracts import Limits, default_depth_limit_m
    none = argparse.Namespace(depth_limit_m=None)
    assert run_limits(none, 0.002).depth_limit_m == pytest.approx(0.0016)
    assert run_limits(none, 0.005).depth_limit_m == Limits().depth_limit_m == default_depth_limit_m(0.005)
    assert run_limits(none, 0.010).depth_limit_m == Limits().depth_limit_m
    assert run_limits(argparse.Namespace(depth_limit_m=0.003), 0.002).depth_limit_m == 0.003   # given: as given


def test_plan_on_a_2_mm_tip_plans_within_its_default_and_says_so(tmp_path, capsys):
    import json

    from app.cli import main
    out = tmp_path / "plan.json"
    assert main(["plan", _small_tip(tmp_path, 0.002), "--waypoints", "9", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "depth limit 1.6 mm (by default 0.8 of the tip's radius, 2 mm, where that is below 4 mm)" in err, err
    plan = json.loads(out.read_text())
    assert plan["limits"]["depth_limit_m"] == pytest.approx(0.0016)
    assert max(p["depth_m"] for p in plan["probes"]) <= 0.0016 + 1e-12


def test_run_on_a_tip_too_small_to_probe_says_why(tmp_path, capsys):
    from app.cli import main
    assert main(["run", _small_tip(tmp_path, 0.001), "--sim", "--no-figure", "--out", str(tmp_path / "r")]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("palpate:")]
    assert len(lines) == 1 and "indenter.radius_m = 0.001 m: a run's default depth limit" in lines[0], lines
    assert "no depth below the tip's radius reaches it" in lines[0] and not (tmp_path / "r").exists()
    # (a 1.2 mm tip: its default, 0.96 mm, is too shallow, but a limit from 1 mm up to its radius probes)
    assert main(["run", _small_tip(tmp_path, 0.0012), "--sim", "--no-figure", "--out", str(tmp_path / "r2")]) == 2
    assert "give --depth-limit-m D with 0.001 <= D < 0.0012" in capsys.readouterr().err


def test_probes_the_prior_predicts_below_the_contact_threshold_are_a_note_not_a_fault(tmp_path):
    """Session 52's review (a 40 x 40 x 20 mm block, a 2 mm tip at its 1.6 mm default limit): 24 of 84 probes felt
    no contact, each where the prior itself predicts less than the 0.02 N threshold, and the run warned that the
    tissue there was absent, lower or softer than the prior says. Now those make a note; a probe where the prior
    predicts contact still makes the warning, named. (The simulated tissue pushes back some 12-17 mN at 0.4 mm.)"""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).parent))
    from robot_fixtures import make_plan, make_sim

    from app.runexec import no_contact, no_contact_warning
    from robot.driver import run_plan
    from robot.records import read_records
    plan = make_plan((0.02, 0.035, 0.05), depth_m=0.0004, predicted=0.01)    # the prior: below the 0.02 N threshold
    arm, c, r = make_sim()
    assert run_plan(plan, c, r, tmp_path / "a").status == "ok"
    assert all(x.implausible is None for x in read_records(tmp_path / "a"))
    nc = no_contact(tmp_path / "a")
    assert nc["n"] == 3 and nc["expected_by_prior"] == [True] * 3, nc
    assert no_contact_warning(nc).startswith("warning: no probe felt contact down to its planned depth, as the "
                                             "prior predicts")
    plan = make_plan((0.02, 0.035, 0.05), depth_m=0.0004, predicted=0.01)
    plan.probes[2].predicted_force_n = 0.03                                  # here the prior predicts contact
    arm, c, r = make_sim()
    assert run_plan(plan, c, r, tmp_path / "b").status == "ok"
    nc = no_contact(tmp_path / "b")
    assert nc["expected_by_prior"] == [True, True, False], nc
    w = no_contact_warning(nc)
    assert w.startswith("warning: 1 of 3 probes felt no contact") and "x = 50.0 mm" in w, w
    assert "2 more felt none where the prior itself predicts less than the contact threshold" in w
    nc = {**nc, "of": 10, "expected_by_prior": [True] * 3}                  # seven more felt contact: a note
    assert no_contact_warning(nc).startswith("note: 3 of 10 probes felt no contact down to their planned depth, as "
                                             "the prior predicts there")


def test_a_no_contact_probe_left_out_of_the_fit_is_never_a_note():
    """The session-52 review's case: a probe the prior predicts below the threshold, but flagged implausible (left
    out of the fit): it is warned about, not noted as expected."""
    from types import SimpleNamespace

    from app.runexec import _expected_by_prior, no_contact_warning
    rec = SimpleNamespace(force_predicted_prior_n=0.01, contact_threshold_n=0.02, implausible=None)
    assert _expected_by_prior(rec)
    assert not _expected_by_prior(SimpleNamespace(**{**rec.__dict__, "implausible": "no contact was felt"}))
    assert not _expected_by_prior(SimpleNamespace(**{**rec.__dict__, "force_predicted_prior_n": 0.03}))
    nc = {"n": 2, "of": 5, "x_m": [0.01, 0.02], "y_m": [0.0, 0.0], "index": [0, 1], "expected_by_prior": [True, False]}
    assert no_contact_warning(nc).startswith("warning: 1 of 5 probes felt no contact")


def test_plan_on_a_tip_too_small_for_its_default_says_so_in_one_line(tmp_path, capsys):
    """The session-52 review: `palpate plan` on a 1 mm tip said its default in one line, then blamed
    --min-depth-m, which was not given; a --depth-m past the default limit blamed --depth-limit-m, not given."""
    from app.cli import main
    assert main(["plan", _small_tip(tmp_path, 0.001), "--out", str(tmp_path / "p.json")]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "indenter.radius_m = 0.001 m: the default depth limit" in err[0], err
    assert main(["plan", _small_tip(tmp_path, 0.003), "--depth-m", "0.0028", "--out", str(tmp_path / "p.json")]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "must be at most the default depth limit 0.0024 m" in err[0], err


def test_a_resume_compares_the_depth_limit_the_run_planned_to():
    """The session-52 review: a 3 mm tip's run (planned to 2.4 mm by default) was refused on resume with
    --depth-limit-m 0.0024 ("not given (default 0.004)"). run_options now holds the limit it planned to."""
    import argparse

    from app.runexec import _depth_limit_option, _same_option
    paper = load("paper")
    tip3 = dataclasses.replace(paper, indenter=dataclasses.replace(paper.indenter, radius_m=0.003))
    none = argparse.Namespace(depth_limit_m=None, plan=None)
    assert _depth_limit_option(none, tip3, None) == {"depth_limit_m": pytest.approx(0.0024)}
    given = _depth_limit_option(argparse.Namespace(depth_limit_m=0.0024, plan=None), tip3, None)
    assert _same_option("depth_limit_m", _depth_limit_option(none, tip3, None), given)
    assert _depth_limit_option(none, paper, None) == {"depth_limit_m": 0.004}
    assert _same_option("depth_limit_m", {}, _depth_limit_option(none, paper, None))   # a run before session 52
    assert _depth_limit_option(argparse.Namespace(depth_limit_m=None, plan="p.json"), paper, None) == {}


def test_the_predict_figure_marks_the_peak_the_json_reports(tmp_path, monkeypatch):
    """Session 51's review: the figure marked the largest sample of the force ratio, the JSON a sub-waypoint fit
    (another x and ratio). Now the figure is handed the JSON's peak."""
    import json

    from app.cli import main
    from fem import plots
    seen = {}
    real = plots.predict_graph

    def spy(*a, **k):
        seen.update(k)
        return real(*a, **k)
    monkeypatch.setattr(plots, "predict_graph", spy)
    out = tmp_path / "p.json"
    assert main(["predict", "paper", "--waypoints", "15", "--depth-m", "0.003", "--plots", str(tmp_path),
                 "--json", str(out)]) == 0
    pr = json.loads(out.read_text())["peak_ratio"]
    assert seen["peak"] == (pr["x_m"], pr["ratio"])
    assert pr["x_m"] != pr["x_max_sample_m"]          # the case: the fit lies between waypoints
    assert (tmp_path / "fig11_predict.png").stat().st_size > 10_000


def test_predict_on_a_2_mm_tip_presses_to_its_default_and_says_so(tmp_path, capsys):
    """`palpate predict` on a 2 mm tip refused its own default depth (4 mm) as if the user had given it ("--depth-m
    0.004 ... must be below the tip radius"); it now takes the run's rule and says so."""
    import json

    from app.cli import main
    out = tmp_path / "p.json"
    assert main(["predict", _small_tip(tmp_path, 0.002), "--waypoints", "5", "--quiet", "--json", str(out)]) == 0
    assert "depth 1.6 mm (by default 0.8 of the tip's radius, 2 mm" in capsys.readouterr().err
    assert json.loads(out.read_text())["depth_m"] == pytest.approx(0.0016)


def test_messages_name_the_default_they_used(tmp_path, capsys):
    """The second session-52 review: on a 10 mm tip `plan` called the 4 mm default "0.8 of the tip's radius"; a
    `predict` whose default depth the section refuses named a --depth-m that was not given."""
    from app.cli import main
    assert main(["plan", _small_tip(tmp_path, 0.010), "--depth-m", "0.006", "--out", str(tmp_path / "p.json")]) == 2
    err = capsys.readouterr().err
    assert "at most the default depth limit 0.004 m (the 4 mm default" in err and "0.8 of" not in err, err
    f = tmp_path / "thin.toml"
    f.write_text(SMALL_TIP.format(name="thin", radius=0.0045).replace("height_m = 0.040", "height_m = 0.008")
                 + "[analysis]\nmesh_size_m = 0.002\n")
    assert main(["predict", str(f), "--force-only", "--waypoints", "3"]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("palpate: the default depth 0.0036 m (0.004 m, or 0.8 of the tip's "
                                                   "radius where that is less; --depth-m to choose)"), lines
