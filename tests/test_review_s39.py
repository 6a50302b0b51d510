"""Session 39's review findings, each as a test: an elastic flat punch too soft to be taken as rigid is refused
when the scene is read (one line naming the field, exit 2; it used to end in a traceback from fem.tip in 2D), with
fem's own bound; a 3D probed patch narrower than the tip is refused when read (every waypoint was refused later,
with an interval whose ends were the wrong way round); the examples the help teaches run."""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from app.cli import main
from fem import scene as S
from fem import tip as T

ROOT = Path(__file__).resolve().parents[1]
FLAT_2D = """name = "flat-el"
[tissue]
width_m = 0.070
height_m = 0.050
youngs_pa = 2500.0
poisson = 0.4
[indenter]
shape = "flat"
radius_m = 0.005
youngs_pa = {e}
"""


@pytest.mark.parametrize("plane", ["strain", "stress"])
@pytest.mark.parametrize("tip_e", [5e3, 2.5e6, 60e6])
def test_the_scene_refusal_uses_fems_own_rigid_tip_bound(plane, tip_e):
    base = S.load("healthy")
    sc = dataclasses.replace(base, indenter=dataclasses.replace(base.indenter, youngs_pa=tip_e),
                             analysis=dataclasses.replace(base.analysis, plane=plane))
    assert S.ELASTIC_TIP_NEGLIGIBLE == T.TIP_TOLERANCE
    assert S._tip_relative_compliance(sc) == T.rigid_tip_bound(sc)
    flat = dict(indenter=dataclasses.replace(sc.indenter, shape="flat"))
    if T.treated_as_rigid(sc):
        dataclasses.replace(sc, **flat)         # a punch fem takes as rigid: accepted
    else:
        with pytest.raises(S.SceneError, match=r"indenter\.youngs_pa = .* with indenter\.shape = 'flat'"):
            dataclasses.replace(sc, **flat)


def test_a_soft_elastic_flat_punch_is_refused_in_one_line(tmp_path):
    path = tmp_path / "flat.toml"
    path.write_text(FLAT_2D.format(e=5000.0))
    p = subprocess.run([sys.executable, "-m", "app.cli", "simulate", str(path), "--load", "indent", "--x-m", "0.035",
                        "--depth-m", "0.002"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "indenter.youngs_pa = 5000.0 with indenter.shape = 'flat'" in p.stderr and "cylinder" in p.stderr


def test_a_soft_elastic_flat_punch_is_refused_in_3d_with_its_round_alternative():
    sc = S.load("block3d")
    with pytest.raises(S.SceneError, match="or shape = 'sphere'"):
        dataclasses.replace(sc, indenter=dataclasses.replace(sc.indenter, shape="flat", youngs_pa=5000.0))


def _examples(text: str, command: str) -> list[str]:
    """The example command lines of a --help epilog that start with ``palpate COMMAND paper`` (the 2D built-ins
    paper, paper-left, ...)."""
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line.startswith(f"palpate {command} paper"):
            out.append(line.split("   ")[0].strip())       # (a comment may follow after 3 spaces)
    return out


def test_every_2d_example_in_the_help_runs(tmp_path, monkeypatch, capsys):
    """The examples `palpate --help` and `palpate plan --help` teach, on the 2D scenes, each run as written
    (outputs into a scratch directory): one of them asked for a depth limit beyond the tip and was refused. Each
    through the command line's own entry point in this process (until session 58 each in a fresh interpreter: 2 s
    of imports apiece; commands in a fresh interpreter are run by tests/test_review_s42.py and others)."""
    import shlex

    from app.cli import EPILOG as MAIN
    from app.commands.plan import EPILOG as PLAN
    from app.commands.predict import EPILOG as PREDICT
    from app.commands.simulate import EXAMPLES as SIMULATE
    cases = [c for text, cmd in ((MAIN, "simulate"), (MAIN, "predict"), (MAIN, "plan"), (PLAN, "plan"),
                                 (SIMULATE, "simulate"), (PREDICT, "predict")) for c in _examples(text, cmd)]
    assert len(cases) >= 12, cases
    for k, line in enumerate(dict.fromkeys(cases)):
        argv = shlex.split(line)[1:]
        cwd = tmp_path / f"ex{k}"
        cwd.mkdir()
        monkeypatch.chdir(cwd)
        rc = main(argv)
        assert rc == 0, (line, capsys.readouterr().err[-500:])


def test_a_probed_patch_narrower_than_the_tip_is_refused_when_the_scene_is_read():
    sc = S.load("block3d")
    R = sc.indenter.radius_m
    with pytest.raises(S.SceneError, match=r"analysis\.patch_m = .* is narrower than the tip"):
        sc.with_analysis(patch_m=2 * R - 1e-4)
    assert sc.with_analysis(patch_m=2 * R).analysis.patch_m == 2 * R      # one waypoint's footprint: accepted


def test_a_resumed_run_says_which_probes_it_presses_again(tmp_path):
    """Probes stopped at a limit hold a measurement (counted by measured_on_disk, which an interrupted run's last line
    reports: it said 0 probes after 5). Since session 59 a resumed run presses a depth_limit probe no more than an ok
    one (a force_limit stop, which may have been a spike, it does): the resume note counts them with the ok ones."""
    sys.path.insert(0, str(Path(__file__).parent))
    from robot_fixtures import make_plan, make_sim

    from app.runexec import measured_on_disk, resuming_note
    from core.contracts import Limits
    from robot.driver import run_plan
    plan = make_plan((0.02, 0.035, 0.05), depth_m=0.004, limits=Limits(depth_limit_m=0.004))
    arm, c, r = make_sim(surface_height_m=lambda x: 0.003 if x > 0.03 else 0.0)    # the last two: depth_limit
    assert run_plan(plan, c, r, tmp_path).status == "ok"
    assert measured_on_disk(tmp_path) == 3
    assert resuming_note(tmp_path).endswith("3 probes measured before are not pressed again")


def test_probes_that_felt_no_contact_are_named_and_all_of_them_make_the_run_not_detectable(tmp_path):
    """A truth narrower than the prior left probes in the air: flagged implausible with a sensor fault as the reason,
    and the run said nothing; a tissue 5000 times softer than the prior answered NO STONE though no probe felt it.
    Now the probes that felt no contact are named (and the reason says so), and none felt means NOT DETECTABLE."""
    sys.path.insert(0, str(Path(__file__).parent))
    from robot_fixtures import make_plan, make_sim

    from app.runexec import no_contact, no_contact_warning, verdict
    from planner.localize import Localization
    from robot.driver import run_plan
    from robot.records import read_records
    plan = make_plan((0.02, 0.035, 0.05), depth_m=0.003)
    arm, c, r = make_sim(surface_height_m=lambda x: -0.006 if x > 0.03 else 0.0)     # the last two: in the air
    assert run_plan(plan, c, r, tmp_path / "a").status == "ok"
    nc = no_contact(tmp_path / "a")
    assert nc["n"] == 2 and nc["of"] == 3 and nc["index"] == [1, 2], nc
    assert "2 of 3 probes felt no contact" in no_contact_warning(nc) and "x = 35.0, 50.0 mm" in no_contact_warning(nc)
    recs = read_records(tmp_path / "a")
    assert recs[0].implausible is None and all("no contact was felt" in x.implausible for x in recs[1:])
    loc = Localization(detected=False, lr=0.1, lr_threshold=20.0)
    assert verdict(loc, object(), "no stone (LR 0.1)", "ok", None, nc).startswith("NO STONE")
    arm, c, r = make_sim(surface_height_m=lambda x: -0.006)
    assert run_plan(plan, c, r, tmp_path / "b").status == "ok"
    line = verdict(loc, object(), "no stone (LR 0.1)", "ok", None, no_contact(tmp_path / "b"))
    assert line.startswith("NOT DETECTABLE: no probe felt contact")
    arm, c, r = make_sim()
    assert run_plan(plan, c, r, tmp_path / "c").status == "ok" and no_contact(tmp_path / "c") is None


def test_a_table_for_a_narrow_section_extrapolates_the_stones_that_would_leave_its_side():
    """The table's grid positions scale with the width, its diameters do not: below 60 mm its widest stones at the
    first position left the section and fem refused the whole build (after the run had started: a dask traceback,
    then an error about an internal stone). Now those entries are extrapolated in x, never computed, and a section
    too small for the table's reference stone is refused before anything starts."""
    import numpy as np

    from planner import surrogate as su
    base = S.load("healthy")
    sc = dataclasses.replace(base, tissue=dataclasses.replace(base.tissue, width_m=0.040),
                             analysis=dataclasses.replace(base.analysis, mesh_size_m=0.004))
    grid = su.Grid(s_m=(3e-3, 6e-3), diam_m=(4e-3, 17e-3), xs_m=(10e-3, 20e-3, 35e-3), levels_m=(3e-3,), dx0_m=5e-3)
    xs = su._grid_xs(sc, grid)
    assert not su.fits_sideways(sc, xs[0], 0.003 + 0.0085, 0.017) and su.fits_sideways(sc, xs[1], 0.003 + 0.0085, 0.017)
    computed = []
    real = su._one_stone

    def spy(shared, stone):
        computed.append(stone)
        return real(shared, stone)
    su._one_stone = spy
    try:
        d = su.build_table(sc, grid, workers=1)
    finally:
        su._one_stone = real
    assert len(computed) == 2 * 2 * 3 - 2 and all(not (x < 0.006 and D > 0.01) for x, _, D in computed)
    t = d["table"]
    assert np.isfinite(t).all() and np.abs(t[:, 1, 1:]).max() > 0
    frac = (xs[0] - xs[1]) / (xs[2] - xs[1])
    assert np.allclose(t[:, 1, 0], t[:, 1, 1] + frac * (t[:, 1, 2] - t[:, 1, 1]), rtol=0, atol=1e-15)
    narrow = dataclasses.replace(sc, tissue=dataclasses.replace(sc.tissue, width_m=0.012))
    su.check_table_fits(narrow)                 # the fingerprint stone falls back to one that fits
    assert su.fingerprint_stone(narrow, su.Grid()) != su.FP_STONE
    thin = dataclasses.replace(sc, tissue=dataclasses.replace(sc.tissue, height_m=0.005),
                               analysis=dataclasses.replace(sc.analysis, mesh_size_m=0.002))
    with pytest.raises(ValueError, match=r"height_m = 0\.005 m\) is too small for the localizer's table"):
        su.check_table_fits(thin)


def test_the_localizers_prior_response_covers_a_thin_tissue():
    """On a 15 mm thick section the localizer's prior response asked fem for indentations up to 0.96 R on the
    thickness node 10 % thinner, beyond the 30 % of its height fem allows: the run ended in a traceback once the
    table was built. Its depth grid now stops at fem's deepest there (extrapolated beyond, as at the tip radius); on
    the paper's 50 mm section it is what it was."""
    import numpy as np

    from planner import tissue_response as tr
    paper = S.load("paper").prior()
    R = paper.indenter.radius_m
    assert np.array_equal(tr.PriorResponse(paper, [0.035]).logd,
                          np.linspace(np.log(tr.MIN_FRAC * R), np.log(tr.MAX_FRAC * R), tr.N_NODES))
    thin = dataclasses.replace(paper, tissue=dataclasses.replace(paper.tissue, height_m=0.015),
                               analysis=dataclasses.replace(paper.analysis, mesh_size_m=0.003))
    resp = tr.PriorResponse(thin, [0.02, 0.035])
    assert np.exp(resp.logd[-1]) <= S.STRAIN_MAX * 0.9 * 0.015
    f = resp.force_n(np.array([0.004, 0.004]), eta=-0.05)
    assert np.all(np.isfinite(f)) and np.all(f > 0)


def test_the_reported_peak_ratio_is_never_below_a_sample():
    """Two stones made the ratio's hump lopsided: the window's parabola peaked at 1.13235 while a sample read 1.13293.
    The peak's value is now at least the largest sample's; on a symmetric hump it is the parabola's, as before."""
    import numpy as np

    from app.commands.predict import _peak
    from core.peak import parabola_peak, upper_window
    xs = np.linspace(0.0, 0.04, 41)
    lop = 1 + 0.13 * np.exp(-((xs - 0.021) / 0.003) ** 2) + 0.05 * np.exp(-((xs - 0.028) / 0.01) ** 2)
    lo, hi = upper_window(lop, int(np.argmax(lop)))
    assert parabola_peak(xs, lop, lo, hi)[1] < lop.max()          # the case: the fit alone is below a sample
    assert _peak(xs, lop)["ratio"] == lop.max()
    sym = 1 + 0.15 * np.exp(-((xs - 0.0203) / 0.006) ** 2)
    lo, hi = upper_window(sym, int(np.argmax(sym)))
    assert _peak(xs, sym)["ratio"] == parabola_peak(xs, sym, lo, hi)[1] >= sym.max()


def test_a_thin_tissue_plans_a_fixed_depth_and_the_suggested_depth_limit_is_accepted(tmp_path):
    """The refusal of a depth limit beyond fem's 30 % of the height applies to the depth search only (a fixed
    --depth-m plans as before), and the limit it suggests is one it accepts (it was rounded up past the limit)."""
    import re

    from core.contracts import Limits, PlanError
    from planner.plan import plan_raster
    base = S.load("healthy")
    thin = dataclasses.replace(base, tissue=dataclasses.replace(base.tissue, height_m=0.01234567),
                               analysis=dataclasses.replace(base.analysis, mesh_size_m=0.003))
    plan = plan_raster(thin, n_waypoints=5, depth_m=0.002)
    assert len(plan.probes) == 5
    with pytest.raises(PlanError, match="give --depth-limit-m <=") as e:
        plan_raster(thin, n_waypoints=5)
    suggested = float(re.search(r"<= ([0-9.e-]+) m", str(e.value)).group(1))
    assert suggested <= S.STRAIN_MAX * 0.01234567
    assert len(plan_raster(thin, n_waypoints=5, limits=Limits(depth_limit_m=suggested)).probes) == 5


def test_result_json_names_the_verdict():
    from app.runexec import verdict_kind
    assert [verdict_kind(x) for x in ("STONE stone at x", "NO STONE no stone (LR 0.1", "NOT LOCALIZED: too few",
                                      "NOT DETECTABLE: no probe", "NO RESULT: the arm")] == \
        ["stone", "no_stone", "not_localized", "not_detectable", "no_result"]

