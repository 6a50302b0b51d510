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
    the interpolated contrast was 1.1-1.6 % off fem and stones came out 5.5-8.7 sigma off. The side changes the
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
    from planner.tissue_response import THICKNESS_STEP, scene_with_height
    f = tmp_path / "small40.toml"
    f.write_text('name = "small40"\n[tissue]\nwidth_m = 0.040\nlength_m = 0.040\nheight_m = 0.020\n'
                 'youngs_pa = 5000.0\npoisson = 0.45\n[indenter]\nshape = "sphere"\nradius_m = 0.002\n')
    sc = load(str(f))
    validate(sc)
    assert sc.is_3d and sc.analysis.mesh_size_m > 0.9 * sc.tissue.height_m / 2   # the copy's limit it would break
    thin = scene_with_height(sc, 1.0 - THICKNESS_STEP)
    validate(thin)
    assert thin.analysis.mesh_size_m == pytest.approx(0.9 * 0.02 / 2)
    thick = scene_with_height(sc, 1.0 + THICKNESS_STEP)
    assert thick.analysis == sc.analysis and thick.tissue.height_m == pytest.approx(0.022)


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
    assert "depth limit 1.6 mm (0.8 of the tip's 2 mm radius" in err, err
    plan = json.loads(out.read_text())
    assert plan["limits"]["depth_limit_m"] == pytest.approx(0.0016)
    assert max(p["depth_m"] for p in plan["probes"]) <= 0.0016 + 1e-12


def test_run_on_a_tip_too_small_to_probe_says_why(tmp_path, capsys):
    from app.cli import main
    assert main(["run", _small_tip(tmp_path, 0.001), "--sim", "--no-figure", "--out", str(tmp_path / "r")]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("palpate:")]
    assert len(lines) == 1 and "indenter.radius_m = 0.001 m is too small to probe" in lines[0], lines
    assert "0.00125 m" in lines[0] and not (tmp_path / "r").exists()


def test_probes_the_prior_predicts_below_the_contact_threshold_are_a_note_not_a_fault(tmp_path):
    """Session 52's review (a 40 x 40 x 20 mm block, a 2 mm tip at its 1.6 mm default limit): 24 of 84 probes felt
    no contact, each where the prior itself predicts less than the 0.02 N threshold, and the run warned that the
    tissue there was absent, lower or softer than the prior says. Now those make a note; a probe where the prior
    predicts contact still makes the warning, named."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).parent))
    from robot_fixtures import make_plan, make_sim

    from app.runexec import no_contact, no_contact_warning
    from robot.driver import run_plan
    air = {"surface_height_m": lambda x: -0.006 if x > 0.03 else 0.0}       # the last two probes: in the air
    plan = make_plan((0.02, 0.035, 0.05), depth_m=0.003, predicted=0.005)   # the prior: below the 0.02 N threshold
    arm, c, r = make_sim(**air)
    assert run_plan(plan, c, r, tmp_path / "a").status == "ok"
    nc = no_contact(tmp_path / "a")
    assert nc["n"] == 2 and nc["prior_below_threshold"] == [True, True], nc
    assert no_contact_warning(nc).startswith("note: 2 of 3 probes felt no contact down to their planned depth, as "
                                             "the prior predicts there")
    plan = make_plan((0.02, 0.035, 0.05), depth_m=0.003, predicted=0.005)
    plan.probes[2].predicted_force_n = 0.1                                   # here the prior predicts contact
    arm, c, r = make_sim(**air)
    assert run_plan(plan, c, r, tmp_path / "b").status == "ok"
    w = no_contact_warning(no_contact(tmp_path / "b"))
    assert w.startswith("warning: 1 of 3 probes felt no contact") and "x = 50.0 mm" in w, w
    assert "1 more felt none where the prior itself predicts less than the contact threshold" in w


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
    assert "depth 1.6 mm (0.8 of the tip's 2 mm radius" in capsys.readouterr().err
    assert json.loads(out.read_text())["depth_m"] == pytest.approx(0.0016)
