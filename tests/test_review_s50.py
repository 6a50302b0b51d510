"""Session 50: a plan file's errors name the option and the file; a section wider than 70 mm keeps the localizer's
table positions near its sides; the 2D stone fit also starts with H0's tissue taken as linear."""
from __future__ import annotations

import dataclasses
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from app import cell
from app.cli import main
from core.contracts import Plan, PlanError
from fem.scene import load
from planner.localize import Measurements, localize
from planner.surrogate import REF_WIDTH_M, Grid, _grid_xs
from robot.records import read_records


@pytest.mark.parametrize("text, said", [("{}", "plan version None is not supported"),
                                         ("not json", "cannot read it: not valid JSON"),
                                         ('{"version": 2, "extra": 1}', "unknown")])
@pytest.mark.parametrize("command", ["run", "cell"])
def test_a_bad_plan_file_is_one_line_naming_the_option_and_the_file(tmp_path, capsys, text, said, command):
    """`--plan p.json` with no version said only "plan version None is not supported": neither the option nor the
    file."""
    plan = tmp_path / "p.json"
    plan.write_text(text)
    if command == "run":
        rc = main(["run", "paper", "--sim", "--plan", str(plan), "--out", str(tmp_path / "o")])
    else:
        rc = cell.main(["--plan", str(plan), "--sim", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1
    assert f": --plan {plan}: " in err and said in err and err.count(str(plan)) == 1, err


def test_plan_load_names_the_file_of_a_malformed_plan(tmp_path):
    """A run's own saved plans are read by Plan.load too: its message says which file."""
    plan = tmp_path / "plan_round0.json"
    plan.write_text('{"version": 7}')
    with pytest.raises(PlanError, match="^" + re.escape(f"plan {plan}: plan version 7 is not supported")):
        Plan.load(plan)


def _prior(width_m: float):
    p = load("paper").prior()
    return dataclasses.replace(p, tissue=dataclasses.replace(p.tissue, width_m=width_m))


@pytest.mark.parametrize("width_m", [0.05, 0.07])
def test_table_positions_up_to_70_mm_scale_with_the_width(width_m):
    assert np.array_equal(_grid_xs(_prior(width_m), Grid()), np.asarray(Grid().xs_m) * width_m / REF_WIDTH_M)


# (a wider section's positions: session 52 changed the rule; tests/test_review_s52.py checks it)


def test_a_big_side_stone_in_neo_hookean_tissue_is_not_placed_in_the_middle(paper_prior, paper_surrogate):
    """The mismatch study v6's trial 43 (tests/data/mismatch-hyper-trial-0043: its 25 records and the truth;
    ``palpate study mismatch --hyperelastic --workers 2``, seed 1): a 9.5 mm stone 8.2 mm deep, 6.9 mm from the side
    of neo-Hookean tissue 1.5 times as stiff. The no-stone fit took the stone's bump as finite-strain stiffening
    (amplitude 4.1), every start held that amplitude, and all ended at a 17 mm stone 42 mm deep at x 47.6 +- 3.6 mm
    (chi2 409 on 44 dof; LR 1630): a confident answer 41 mm away. A start with H0's tissue taken as linear finds the
    family's better minimum at the stone (chi2 19; measured x 5.66 mm, depth 7.43 mm, amplitude 1.1)."""
    data = Path(__file__).parent / "data" / "mismatch-hyper-trial-0043"
    stone = tomllib.loads((data / "truth.toml").read_text())["stone"][0]
    meas = Measurements.from_records(read_records(data), statuses=("ok", "force_limit", "depth_limit"))
    assert len(meas) == 25
    loc = localize(paper_prior, meas, paper_surrogate)
    assert loc.detected and loc.chi2_1 < 2 * loc.dof_1, (loc.chi2_1, loc.dof_1)      # measured 19.3 (409 before)
    assert abs(loc.x_m - stone["x_m"]) < 3e-3, loc.x_m                                 # measured 5.66 mm
    assert abs(loc.depth_m - stone["depth_m"]) < 3e-3, loc.depth_m                     # measured 7.43 mm
    assert 0.5 < loc.nuisance["finite_strain_amplitude"][0] < 2.0                      # neo-Hookean: near 1


def test_the_depth_interval_holds_the_estimate_at_the_tables_shallowest_smallest_stone():
    """An estimate with the smallest diameter at the smallest clearance (a 4 mm stone, its top 1.5 mm deep): at its
    own depth the held fit had no room for the diameter and counted as infinite, so the intervals were built around
    the next depth and excluded the estimate (the review's 100 x 30 mm section: depth 3.50 mm, 68 % interval
    3.58-3.59 mm). A synthetic chi2 with its minimum there: the intervals now start at the estimate."""
    from planner.localize import _depth_profile
    lo = np.array([5.0, np.log(1.5), 4.0])
    hi = np.array([65.0, np.log(36.0), 17.0])

    def resid(q):         # q = (x mm, log s, D mm, one nuisance): the depth pulled to 3.5 mm, D to 4 mm
        dep = np.exp(q[1]) + q[2] / 2
        return np.array([(q[0] - 35.0) / 0.3, (dep - 3.5) / 0.4, (q[2] - 4.0) / 2.0, q[3]])

    def jac(q):
        s = np.exp(q[1])
        return np.array([[1 / 0.3, 0, 0, 0], [0, s / 0.4, 0.5 / 0.4, 0], [0, 0, 0.5, 0], [0, 0, 0, 1.0]])
    q = np.array([35.0, np.log(1.5), 4.0, 0.0])
    out = _depth_profile(resid, jac, q, lo, hi, 3.5e-3, 0.5e-3, 0.0, 1.0, 50.0, np.array([-1.0]), np.array([1.0]))
    for key in ("68", "95"):
        a, b = out[key]
        assert a <= 3.5e-3 + 1e-9 < b, (key, out[key])
    assert out["68"][1] == pytest.approx(3.9e-3, abs=0.05e-3)     # chi2 = ((d - 3.5) / 0.4)^2 = 1 at 3.9 mm


def test_readings_past_the_linear_range_warn_of_bias_and_suggest_a_depth_limit_that_avoids_them():
    """The review's shallow stones on a 100 x 30 mm section: diameters 0.8-1.9 mm small (3-6 sigma) with only a
    warning that the error was in the sigmas; with --depth-limit-m 0.002 (the tissue over them within the linear
    model) within 1 sigma. The warning now says the bias may exceed the sigmas and gives that depth limit."""
    from types import SimpleNamespace

    from fem.contact import STONE_LAYER_MAX
    from planner.refine import caveats
    loc = SimpleNamespace(at_bound=[], n_beyond_linear_range=12, depth_m=0.00694, diameter_m=0.0080, dof_1=84,
                          chi2_fit=80.0, chi2_1=80.0)
    said = caveats(loc)
    top = 0.00694 - 0.004
    assert "biased beyond them" in said and "--depth-limit-m 0.0019" in said, said
    assert float(said.split("--depth-limit-m ")[1].split()[0]) <= STONE_LAYER_MAX * top
    loc.depth_m, loc.diameter_m = 0.0043, 0.008        # its top 0.3 mm deep: only the shallowest probe comes near
    assert "--depth-limit-m 0.001 comes nearest" in caveats(loc) and "biased beyond them" in caveats(loc)


def test_waiting_for_a_building_table_says_one_status_line_at_a_time(monkeypatch):
    """While the run waited for the table, the build's progress line and a "waiting for the table" line with the same
    numbers were both said every 15 s. Now the waiting line comes only when the build has said nothing for as long."""
    import threading
    import time as _time

    import planner.pending as pending
    release = threading.Event()

    def slow_build(prior, grid, progress, runner):
        for k in range(1, 9):
            _time.sleep(0.05)
            progress(k, 8, 0.05 * k)            # a stone every 50 ms: the build speaks every 0.1 s
        release.wait(0.6)                       # then silent for a while: the waiting line speaks
        return "table"
    monkeypatch.setattr(pending, "load_surrogate", slow_build)
    said: list[tuple[float, str]] = []
    p = pending.PendingSurrogate(None, lambda m: said.append((_time.perf_counter(), m)), runner=object(),
                                 every_s=0.1)
    assert p.result() == "table"
    span = said[-1][0] - said[0][0]
    assert len(said) <= span / 0.1 + 2, said        # one line per 0.1 s (both spoke: about two)
    assert any(m.startswith("waiting for the table") for _, m in said)
    assert any(m.startswith("surrogate table: ") for _, m in said)


def test_a_waiting_line_counts_its_time_to_now():
    """Between two finished stones the waiting line said the build's last count word for word (a review's log held
    one line nine times): it now counts the time, and the time left, to now (session 59)."""
    import time as _time

    import planner.pending as pending
    p = object.__new__(pending.PendingSurrogate)
    p._state = {"done": 40, "total": 485, "elapsed_s": 134.0}
    p.t_start = _time.perf_counter() - 160.0
    assert p.status() == "surrogate table: 40/485 stones (134 s, about 1491 s to go)"
    assert p.status(live=True) == "surrogate table: 40/485 stones (160 s, about 1465 s to go)"


def test_a_table_key_changes_only_where_the_positions_did():
    """Up to 70 mm the tables keep their keys (the shipped paper table's name included); a wider section's key holds
    its positions, so a table built with the old scaled ones is never read for it."""
    from planner.surrogate import SHIPPED, _key, cache_path, table_scene
    assert cache_path(load("paper").prior(), Grid(), SHIPPED).exists()
    assert "xs_m" not in _key(table_scene(_prior(0.07)), Grid())
    wide = _key(table_scene(_prior(0.12)), Grid())
    assert wide["xs_m"] == [repr(float(x)) for x in _grid_xs(_prior(0.12), Grid())]
