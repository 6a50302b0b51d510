"""The whole 3D loop on the simulated arm: `palpate run BLOCK --sim` plans a grid over the probed area (CasADi),
probes (robot.driver on the in-memory arm pressing the TRUE block, nano17 noise), localizes in (x, y, depth) from the
prior block and the records only, refines and reports.

The truths are block3d's own (its default mesh, 35-45 s per fem model here): the scenes the issue names. The
surrogate table's coarse mesh is no truth to test against: its mesh ripple (0.2-0.6 mN between a stone's mesh and
the prior's) is half the paper stone's whole contrast (1.4 mN at 3 mm) and put that stone 6.7 mm off; on block3d's
mesh the ripple is 0.05-0.1 mN (docs/loop3d.md). The surrogate is the table shipped in planner/data for block3d,
checked against today's fem by its fingerprint."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

import app.commands.run3d as run3d
from app.cli import main
from robot.records import read_records

CHI2_2DOF_95 = 5.991          # the 95 % uncertainty ellipse of (x, y)


@pytest.fixture(scope="module")
def surrogate():
    """The shipped table (planner/data). Rebuilding it takes ~25 min: rather than do that inside a test, fail and
    say how."""
    from fem.scene import load
    from planner.surrogate3d import load_surrogate3d
    try:
        return load_surrogate3d(load("block3d").prior(), build=False)
    except FileNotFoundError as e:
        pytest.fail(f"{e}: fem's numbers changed or the table is missing; rebuild it with "
                    f"`python -m planner.surrogate3d block3d --ship` and commit planner/data/")


def _found(r: dict, x_m: float, y_m: float, depth_m: float) -> tuple[float, float]:
    """(lateral error, squared Mahalanobis distance of (x, y) in the reported ellipse); asserts the depth lies within
    3 stated sigmas."""
    assert r["status"] == "ok" and r["detected"] is True and r["dimension"] == 3, r.get("evidence")
    est = r["estimate"]
    dx, dy = est["x_m"]["value"] - x_m, est["y_m"]["value"] - y_m
    sx, sy, c = est["x_m"]["sigma"], est["y_m"]["sigma"], est["corr_xy"]
    cov = np.array([[sx * sx, c * sx * sy], [c * sx * sy, sy * sy]])
    d2 = float(np.array([dx, dy]) @ np.linalg.solve(cov, [dx, dy]))
    assert abs(est["depth_m"]["value"] - depth_m) < 3 * est["depth_m"]["sigma"], est
    return math.hypot(dx, dy), d2


def test_block3d_stone_is_found_within_1_mm(tmp_path, surrogate):
    """`palpate run block3d --sim` (the paper's stone under the middle, 25 mm deep), the issue's test. With the
    Nano17's noise (seed 0) the stone lies inside the reported 95 % ellipse and its depth within 3 sigmas; result.json
    carries y_m; the grid covers the area; the figure is written; x and y sigmas below 1 mm. Within 1 mm in the plane
    is asserted, as within 0.5 mm, on a second run with a noise-free sensor (measured 0.25 mm: the method's own
    error), because with noise it is a draw: the estimate's sigma is about 0.7 mm per axis after 84 probes, so one seed lands within 1 mm with odds of about 2 to
    1 (on block3d's mesh since 2026-11-26, seeds 0, 1, 2: 1.41, 0.47, 0.76 mm, all inside their 95 % ellipses; on
    the previous mesh seed 0 gave 0.90 mm). The 3D accuracy study measures the error's distribution."""
    assert main(["run", "block3d", "--sim", "--out", str(tmp_path / "noisy")]) == 0
    r = json.loads((tmp_path / "noisy" / "result.json").read_text())
    lateral, d2 = _found(r, 0.035, 0.035, 0.025)
    est = r["estimate"]
    assert d2 < CHI2_2DOF_95 and max(est["x_m"]["sigma"], est["y_m"]["sigma"]) < 1e-3, est   # measured 0.66, 0.74 mm
    assert r["sim"]["error"]["lateral_m"] == pytest.approx(lateral)
    assert r["probes_used"] <= 84 and len(r["rounds"]) >= 2
    recs = read_records(tmp_path / "noisy")
    assert len(recs) == r["probes_used"] and all(rec.status == "ok" for rec in recs)
    assert any(abs(rec.y_m - 0.035) > 0.01 for rec in recs)          # the grid covers the area, not a line
    assert all(rec.contact_y_m is not None and abs(rec.contact_y_m - rec.y_m) < 1e-4 for rec in recs)
    assert (tmp_path / "noisy" / "fig_run.png").stat().st_size > 10_000
    assert main(["run", "block3d", "--sim", "--sensor", "ideal", "--no-figure", "--out", str(tmp_path / "ideal")]) == 0
    r = json.loads((tmp_path / "ideal" / "result.json").read_text())
    lateral, d2 = _found(r, 0.035, 0.035, 0.025)
    assert lateral < 0.5e-3 and d2 < CHI2_2DOF_95, r["estimate"]


def test_stone_off_the_centre_in_y_is_found_there(tmp_path, surrogate):
    """block3d-front (the stone at y = 20 mm, 5 mm inside the probed area's edge, x = 35 mm), its block's thickness
    measured to 1 mm (``--thickness-sigma-m 0.001``: this test is about the position in y): found there, within
    1 mm in the plane (measured 0.46 mm) and inside its 95 % ellipse; not at the centre. (With the default 6 % on
    the thickness the same run gives y 21.52 +- 0.56 mm, 1.5 mm and 2.7 sigma off: docs/localize.md.) Its stone lies 20 mm from
    a side: ``--no-fem-correction`` keeps the run to the table (fem's correction on block3d's mesh takes about two
    minutes a pass; it has its own tests in tests/test_loop3d.py)."""
    assert main(["run", "block3d-front", "--sim", "--no-figure", "--thickness-sigma-m", "0.001", "--no-fem-correction",
                 "--out", str(tmp_path)]) == 0
    r = json.loads((tmp_path / "result.json").read_text())
    assert r["nuisance"]["thickness_prior_sigma"] == pytest.approx(0.001 / 0.05)     # block3d is 50 mm thick
    assert r["detectability"]["thickness_prior_sigma"] == pytest.approx(0.001 / 0.05)
    lateral, d2 = _found(r, 0.035, 0.020, 0.025)
    assert lateral < 1e-3 and d2 < CHI2_2DOF_95, r["estimate"]


def test_healthy_block_gives_no_stone_and_the_localizer_never_sees_the_truth(tmp_path, surrogate, monkeypatch):
    """A healthy block whose true surface lies 0.8 mm above the registered one: no stone, the offset and the
    stiffness scale recovered. Every localization call gets the stone-free prior (a spy on the loop's localizer)."""
    import planner.refine3d as refine3d
    seen = []
    real = refine3d.localize3d

    def spy(prior, meas, *a, **k):
        seen.append(prior)
        return real(prior, meas, *a, **k)
    monkeypatch.setattr(refine3d, "localize3d", spy)
    assert main(["run", "block3d-healthy", "--sim", "--grid", "5x5", "--no-figure", "--truth-surface-offset-m",
                 "0.0008", "--out", str(tmp_path)]) == 0
    r = json.loads((tmp_path / "result.json").read_text())
    assert r["status"] == "ok" and r["detected"] is False, r["evidence"]
    assert r["nuisance"]["fit"] == "no stone"
    assert abs(r["nuisance"]["stiffness_scale"]["value"] - 1.0) < 0.02         # measured 1.004 +- 0.004
    assert abs(r["nuisance"]["surface_offset_m"]["value"] - 0.0008) < 5e-5    # measured 0.800 +- 0.013 mm
    assert seen and all(p.stones == () for p in seen)


def _corner_round():
    """Session 39's review round (tests/data/k3d_corner_seed0_round0.npz: a 10 mm stone at (26, 45) mm, 18 mm deep,
    in a 4000 Pa block), its forces scaled to block3d's prior (2500 Pa): (prior, measurements, table)."""
    from pathlib import Path

    from fem.scene import load
    from planner.localize import Measurements
    from planner.surrogate3d import load_surrogate3d
    z = np.load(Path(__file__).parent / "data" / "k3d_corner_seed0_round0.npz")
    f = {n: z[n] for n in z.files}
    for n in ("force_n", "sigma_n", "onset_threshold_n", "dwell_start_n", "dwell_end_n"):
        f[n] = f[n] * (2500.0 / 4000.0)
    prior = load("block3d").prior()
    return prior, Measurements(**f), load_surrogate3d(prior, build=False)


def test_an_off_centre_3d_stone_is_found_when_the_no_stone_fits_tilt_takes_its_slope(monkeypatch):
    """(Here, beside the runs that build block3d's prior.) Session 39's review: a 10 mm stone at (26, 45) mm, 18 mm deep, in a 4000 Pa block; with the nano17's noise of
    seed 0 the no-stone fit tilted the surface 3 sigma, the contrast's peak moved to the far corner, and every start
    of the stone fit there ended at the bounds: NO STONE (LR 1.2); seeds 0 and 2 of 3 missed it. The stone fit now
    also starts from the best candidates over the whole probed area with the surface untilted. The round's
    measurements are kept in tests/data (the run's own records); the block's forces scale with its modulus, so they
    are localized on block3d's prior (2500 Pa) scaled by 2500/4000."""
    import planner.localize3d as L
    prior, meas, sur = _corner_round()
    loc = L.localize3d(prior, meas, sur)
    assert loc.detected and loc.lr > 50, loc.lr
    assert math.hypot(loc.x_m - 0.026, loc.y_m - 0.045) < 1.5e-3
    monkeypatch.setattr(L, "N_FLAT_STARTS", 0)              # the starts around the peak only: the miss
    assert not L.localize3d(prior, meas, sur).detected


def test_a_3d_stone_near_a_side_is_flagged_and_its_warning_says_why(monkeypatch):
    """Session 53's review: on a 50 x 50 x 30 mm block a stone 13 mm from a side came out 2 mm too shallow, 12-14
    sigma, with no warning, and the run stopped as "target uncertainty reached" (the 3D table takes every stone as
    one away from the sides). A fitted stone within SIDE_REACH3D_M of a side is now in at_bound ("near side"): a
    warning, and the run does not call its sigmas converged. Here on session 39's records (a stone at (26, 45) mm
    on block3d's 70 mm square: 25 mm from the nearest side), with the reach moved either side of that. (Here, beside
    the runs that build block3d's prior.)"""
    import planner.localize3d as L
    from planner.localize import NEAR_SIDE, SIDE_REACH3D_M
    from planner.refine import caveats
    from planner.refine3d import converged3d
    prior, meas, sur = _corner_round()
    assert SIDE_REACH3D_M == 0.022
    loc = L.localize3d(prior, meas, sur)
    side = min(loc.x_m, 0.07 - loc.x_m, loc.y_m, 0.07 - loc.y_m)
    assert loc.detected and 0.023 < side < 0.027 and NEAR_SIDE not in loc.at_bound
    monkeypatch.setattr(L, "SIDE_REACH3D_M", side + 1e-3)
    monkeypatch.setattr(L, "_LAST_FIT", {}, raising=False)
    near = L.localize3d(prior, meas, sur)
    assert NEAR_SIDE in near.at_bound
    assert (near.x_m, near.y_m, near.depth_m, near.sigma_depth_m) == (loc.x_m, loc.y_m, loc.depth_m, loc.sigma_depth_m)
    text = caveats(near)
    assert "within 22 mm of the block's side" in text and "its sigmas do not say how far off" in text
    assert "tissue's" not in text                     # not taken for a tissue parameter at its bound
    assert not converged3d(near, 1.0) and converged3d(loc, 1.0)


class _Stop(Exception):
    """Raised where the 3D run would load its surrogate table: after the plan's checks, before any probing."""


def test_a_3d_run_whose_plan_never_reaches_the_contact_threshold_is_refused(tmp_path, monkeypatch, capsys):
    """Said for 2D runs and `palpate plan` only until session 46 (the 3D run took such a plan without a word); warned
    from session 46 on, the run then going on to the driver's contact_unfelt fault at its first probe (exit 1); since
    session 56 refused before anything starts (exit 2: robot.driver.unfelt_probes), the table never built. In this
    module: block3d's prior model is built once for its runs."""
    plan = tmp_path / "plan.json"
    assert main(["plan", "block3d", "--grid", "3x3", "--out", str(plan)]) == 0
    d = json.loads(plan.read_text())
    top = max(p["predicted_force_n"] for p in d["probes"])
    d["motion"]["contact_threshold_n"] = 1.5 * top          # a hand-edited plan: no probe reaches it
    plan.write_text(json.dumps(d))
    seen = []

    def stop(prior, where):
        seen.append(capsys.readouterr().err)
        raise _Stop
    monkeypatch.setattr(run3d, "_table", stop)
    capsys.readouterr()
    assert main(["run", "block3d", "--sim", "--plan", str(plan), "--no-figure", "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert not seen, "the run reached its table"
    assert f"--plan {plan}: refused before any motion: probe 0" in err and "motion.contact_threshold_n" in err, err
    assert not (tmp_path / "run" / "probes.jsonl").exists()
