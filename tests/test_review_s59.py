"""Session 59's independent review of 2D fem on scenes of its own: predict's ratio peak on a peak sharper than the
waypoints' spacing (it reported the largest sample, 0.5 mm from a stone the three samples around it place within
0.1 mm); near-incompressible tissue, whose nodal contact pressure oscillates without a word (+10 % at nu 0.49, +54 %
at 0.499) and whose locking warning advised, for the contact model too, a mixed formulation only load A has."""
from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import pytest

from app.commands.predict import _peak
from app.resolution import NU_PRESSURE_WARN, warn_pressure_near_incompressible2d
from fem.model import warn_if_locking
from fem.scene import load


def test_a_peak_sharper_than_the_spacing_takes_the_parabola_through_its_top_three():
    """The review's profile (a stone 6.5 mm deep at x = 42 mm, `predict --waypoints 21 --depth-m 0.001`): 1.3063,
    1.3674, 1.2448 at 40, 42.5, 45 mm; only two samples lie in the upper quarter. The vertex of the parabola through
    the top three samples (42.08 mm), not the largest sample (42.5 mm), is the peak."""
    xs = np.arange(0.030, 0.0551, 0.0025)
    ratio = np.array([1.0, 1.01, 1.03, 1.08, 1.3063, 1.3674, 1.2448, 1.06, 1.02, 1.005, 1.0])
    i = int(np.argmax(ratio))
    assert xs[i] == pytest.approx(0.0425)
    y0, y1, y2 = ratio[i - 1:i + 2]
    h = xs[1] - xs[0]
    vertex = xs[i] + h * (y0 - y2) / (2 * (y0 - 2 * y1 + y2))
    p = _peak(xs, ratio)
    assert p["x_m"] == pytest.approx(vertex, abs=1e-12)
    assert abs(p["x_m"] - 0.042) < 0.1e-3 < 0.4e-3 < abs(xs[i] - 0.042)      # 0.08 mm off the stone, the sample 0.5
    assert p["x_max_sample_m"] == xs[i] and p["ratio"] >= ratio[i]


def test_a_broad_peak_keeps_its_window():
    """The fallback is for a window of fewer than three samples only: a broad bump keeps its upper-quarter window
    (the same vertex as the least-squares parabola through it)."""
    xs = np.linspace(0.0, 0.06, 25)
    ratio = 1.0 + 0.4 * np.exp(-((xs - 0.031) / 0.012) ** 2)
    p = _peak(xs, ratio)
    assert abs(p["x_m"] - 0.031) < 0.3e-3


def _with_poisson(nu: float, name: str = "paper"):
    sc = load(name).prior()
    return dataclasses.replace(sc, tissue=dataclasses.replace(sc.tissue, poisson=nu))


@pytest.mark.parametrize("nu", [0.49, 0.499])
def test_near_incompressible_tissue_says_its_contact_pressure_oscillates(nu, capsys):
    sc = _with_poisson(nu)
    warn_pressure_near_incompressible2d(sc, "simulate", [0.0, 1.0e-3])
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"poisson = {nu:g}" in err and "surface_refine" in err
    k = 1.0e-3 / (sc.analysis.mesh_size_m / sc.analysis.surface_refine)
    assert f"here {k:.2g}" in err


def test_a_compressible_tissue_or_no_contact_says_nothing(capsys):
    warn_pressure_near_incompressible2d(_with_poisson(NU_PRESSURE_WARN - 0.01), "simulate", [1.0e-3])
    warn_pressure_near_incompressible2d(_with_poisson(0.499), "simulate", [0.0])
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("name, mixed", [("paper", True), ("block3d", False)])
def test_the_locking_warning_advises_what_the_scene_can_do(name, mixed):
    """2D: the mixed formulation for load A, and for the contact model (which has none) a finer surface; 3D (no
    mixed formulation at all): refine and compare."""
    sc = _with_poisson(0.499, name)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        warn_if_locking(sc)
    assert len(w) == 1
    msg = str(w[0].message)
    assert ('formulation = "mixed"' in msg) is mixed
    assert ("load B" in msg) is mixed and "refine" in msg
    assert math.isclose(float(msg.split("bulk modulus ")[1].split(" ")[0]), 2 * 1.499 / (3 * 0.002), rel_tol=1e-2)


# --- session 59's review of whole runs: the depth limit a shallow stone's warning suggests --------------------------

SHALLOW = """name = "rev-shallow"
[tissue]
width_m = 0.070
height_m = 0.050
youngs_pa = 2500.0
poisson = 0.4
[[stone]]
x_m = 0.042
depth_m = 0.0045
diameter_m = 0.004
youngs_pa = 5.0e9
poisson = 0.3
"""


def test_the_contact_floor_is_where_fems_own_force_feels_the_tissue(paper_prior):
    """The floor a hint may suggest: continued from the planned depths as depth^p it came out 2.0 mm on the paper
    section, where fem's force at the probes is 0.0298 N against the 0.030 N a run's driver needs (the review's next
    run stopped at its first probe). With fem's force it is the shallowest 0.1 mm step where every probe presses more
    than CONTACT_MARGIN x the threshold."""
    from planner.plan import plan_raster
    from planner.refine import CONTACT_MARGIN, contact_floor_m, prior_force

    plan = plan_raster(paper_prior, n_waypoints=15)
    force = prior_force(plan)
    target = CONTACT_MARGIN * plan.motion.contact_threshold_n
    floor = contact_floor_m(plan, force)
    assert floor >= contact_floor_m(plan) and 1e-3 < floor < plan.limits.depth_limit_m
    assert min(force(p, floor) for p in plan.probes) > target
    assert min(force(p, round(floor - 1e-4, 4)) for p in plan.probes) <= target
    # a plan too shallow to feel the tissue (the run refuses it, naming the floor): checked past its own limit
    from core.contracts import Limits
    shallow = plan_raster(paper_prior, n_waypoints=15, limits=Limits(depth_limit_m=0.0015))
    deeper = contact_floor_m(shallow, force, upto_m=shallow.tip_radius_m())
    assert deeper > shallow.limits.depth_limit_m and deeper == floor
    assert contact_floor_m(shallow, force) >= shallow.limits.depth_limit_m     # a hint needs to know no more than that


def test_a_run_whose_probes_cannot_feel_the_tissue_is_refused_before_any_motion(tmp_path, capsys):
    """`palpate run SCENE --sim --depth-limit-m 0.002` on the paper's tissue: every probe's prior force there is
    below 1.5 x the contact threshold, so the driver would stop at the first probe (exit 1, and the same command
    could never resume). It is refused with exit 2 before anything is written, naming the limit that works."""
    from app.cli import main

    scene = tmp_path / "shallow.toml"
    scene.write_text(SHALLOW)
    out = tmp_path / "run"
    assert main(["run", str(scene), "--sim", "--no-figure", "--depth-limit-m", "0.002", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("palpate: --depth-limit-m 0.002: refused before any motion: probe ")
    assert "from --depth-limit-m 0.0021" in err
    assert not (out / "probes.jsonl").exists()


def test_ctrl_c_while_localizing_says_no_result_and_the_run_resumes(tmp_path, capsys, monkeypatch):
    """A Ctrl-C between rounds (here in the first localization) ended with only `palpate: interrupted`; it now says
    NO RESULT as one during probing does, exits 130, keeps the round's probes, and the same command finishes."""
    import planner.refine as refine
    from app.cli import main
    from robot.records import read_records

    real = refine.localize

    def interrupted(*a, **k):
        raise KeyboardInterrupt
    monkeypatch.setattr(refine, "localize", interrupted)
    args = ["run", "paper", "--sim", "--no-figure", "--budget-probes", "25", "--out", str(tmp_path)]
    assert main(args) == 130
    err = capsys.readouterr().err
    assert "NO RESULT: interrupted (Ctrl-C or a stop signal) while the arm was at rest" in err
    assert f"(15 probes in {tmp_path})" in err
    assert len(read_records(tmp_path)) == 15 and not (tmp_path / "result.json").exists()
    monkeypatch.setattr(refine, "localize", real)
    assert main(args) == 0
    assert len(read_records(tmp_path)) == 25


# --- session 59's review of the planner ------------------------------------------------------------------------------

def test_a_plan_whose_elbow_goes_below_the_base_is_said(tmp_path, capsys):
    """`--branch 1,-1,-1` planned without a word with the elbow 0.15 m below the base's plane (the table the arm and,
    by default, the tissue stand on): only the tool is checked against the workspace. The plan command says so; the
    default branch says nothing. The joint origins are checked against the flange by the DH chain's own lengths."""
    from app.cli import main
    from core import ur5e

    q = [0.3, -1.2, 1.1, -1.4, -1.57, 0.2]
    origins = ur5e.joint_origins(q)
    assert origins[0] == pytest.approx([0.0, 0.0, ur5e.DH_D[0]], abs=1e-12)       # the shoulder: on the base axis
    assert np.linalg.norm(origins[1] - origins[0]) == pytest.approx(abs(ur5e.DH_A[1]), abs=1e-12)    # upper arm
    assert np.linalg.norm(ur5e.fk_flange(q)[:3, 3] - origins[4]) == pytest.approx(ur5e.DH_D[5], abs=1e-12)
    assert main(["plan", "paper", "--out", str(tmp_path / "down.json"), "--branch", "1,-1,-1"]) == 0
    err = capsys.readouterr().err
    assert "warning: the elbow joint sits " in err and "m below the base's plane" in err
    assert main(["plan", "paper", "--out", str(tmp_path / "up.json")]) == 0
    assert "below the base's plane" not in capsys.readouterr().err


def test_motion_options_are_refused_under_their_own_names(capsys):
    """`--probe-speed-m-s 1e-12` passed the option check and was refused later as plan field
    motion.probe_speed_m_s; the options now take the ranges the plan and the driver allow."""
    from app.cli import main

    for opt, bad, rng in (("--probe-speed-m-s", "1e-12", "[0.0001, 0.01] m/s"),
                          ("--approach-speed-m-s", "1e-5", "[0.001, 0.25] m/s"),
                          ("--approach-height-m", "1e-9", "[0.002, 0.05] m")):
        assert main(["plan", "paper", "--out", "/tmp/never-written.json", opt, bad]) == 2
        err = capsys.readouterr().err.strip()
        assert f"argument {opt}: must be a finite number in {rng}, got '{bad}'" in err


# --- session 59's review of the robot's safety -----------------------------------------------------------------------

def test_a_fault_during_a_descent_stops_the_arm_before_anything_is_written(tmp_path, monkeypatch):
    """A NaN reading 2 mm into probe 1's descent: the driver wrote the probe's record, its samples and run.json (with
    fsync: 15-70 ms, the tip descending meanwhile) before its first stopL. The arm is now stopped first: when the
    interrupted probe's record is written, it no longer moves; then the safe state retracts it as before."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).parent))
    from robot_fixtures import make_plan, make_sim
    from test_driver_faults import DEPTH, XS, at_probe

    from robot import records as records_mod
    from robot.driver import run_plan

    arm, c, r = make_sim()
    arm.inject("nan", when=at_probe(1, 0.002), duration_s=0.01)
    real = records_mod.RunLog.write_probe
    moving_when_written = []

    def write_probe(self, rec, raw=None):
        if rec.status != "ok":
            moving_when_written.append(arm.is_moving)
        return real(self, rec, raw)
    monkeypatch.setattr(records_mod.RunLog, "write_probe", write_probe)
    rep = run_plan(make_plan(XS, depth_m=DEPTH), c, r, tmp_path)
    assert rep.fault["kind"] == "invalid_reading" and rep.fault["stopped"] and rep.fault["retracted"]
    assert moving_when_written == [False], moving_when_written
    assert not any("first stopL" in n for n in rep.fault["notes"])


def test_a_resume_does_not_press_a_depth_limit_probe_again(tmp_path):
    """Measured probes were pressed again on a resume unless their whole round was measured: an ok probe was skipped,
    a depth_limit one (a measurement a repeat only repeats) was not. It is now; a force_limit stop, which may have
    been a sensor's spike, is still pressed again."""
    from core.contracts import ProbeRecord, ProbeStatus
    from robot.records import RunLog, done_indices

    log = RunLog(tmp_path)
    for i, st in enumerate((ProbeStatus.OK, ProbeStatus.DEPTH_LIMIT, ProbeStatus.FORCE_LIMIT, ProbeStatus.FAULT)):
        log.write_probe(ProbeRecord(index=i, x_m=0.01 * (i + 1), status=st))
    assert done_indices(tmp_path) == {0, 1}
    from app.runexec import resuming_note
    assert resuming_note(tmp_path).endswith("2 probes measured before are not pressed again (1 stopped at the force "
                                            "limit are pressed again: a stop there may have been a sensor's spike)")


def test_consecutive_force_limit_stops_do_not_say_the_same_command_resumes():
    """After "3 consecutive probes stopped at the force limit" the run said "the same command resumes", which pressed
    the same three probes again and stopped the same way, every time. It says what to change instead."""
    from app.runexec import FORCE_LIMIT_FIX, verdict

    fault = {"fault": {"kind": "force_limit", "message": "3 consecutive probes stopped at the force limit"}}
    line = verdict(None, None, "", "fault", fault)
    assert line.startswith("NO RESULT: the arm run ended with a fault (force_limit)") and line.endswith(FORCE_LIMIT_FIX)
    assert "resumes" not in line and "--depth-limit-m" in line and "--fresh" in line


def test_the_wrist_sensor_a_caller_made_on_the_raw_link_zeroes_through_the_guard():
    """On the real and simulated-controller paths the cell made the wrist sensor's source on the raw ur_rtde control
    interface, so its zeroFtSensor went around robot.safety.GuardedControl (the in-memory path went through it). The
    driver now takes such a source onto its guarded interface."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).parent))
    from robot_fixtures import make_plan, make_sim
    from test_driver_faults import DEPTH, XS

    from robot.driver import Driver
    from robot.forcesource import RtdeForce
    from robot.safety import GuardedControl

    _, c, r = make_sim()
    d = Driver(make_plan(XS, depth_m=DEPTH), c, r, force_source=RtdeForce(c, r))
    assert isinstance(d.c, GuardedControl) and d.fs.c is d.c and d.fs.r is r
