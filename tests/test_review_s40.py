"""Session 40's review findings outside the driver, each as a test: `palpate run --host` connects within a deadline
and says in one line why it cannot (it hung for good on a controller that accepts but never answers, and a refused
connection was a traceback); palpate-cell refuses to resume an output directory into which another plan was run
(it counted the other plan's records as this one's probes)."""
from __future__ import annotations

import random
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from app import runexec
from app.errors import UsageError

ROOT = Path(__file__).resolve().parents[1]


def _silent_controller():
    """A listener on port 30004 (RTDE) of a loopback address of its own that accepts and never answers."""
    for _ in range(20):
        host = f"127.{random.randint(100, 200)}.{random.randint(0, 255)}.1"
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, 30004))
        except OSError:
            s.close()
            continue
        s.listen(5)
        held = []           # the accepted connections, kept open (returned with the listener)

        def accept():
            while True:
                try:
                    held.append(s.accept()[0])
                except OSError:         # the listener closed
                    return
        threading.Thread(target=accept, daemon=True).start()
        return host, s, held
    pytest.skip("no free loopback address for the silent controller")


def test_a_controller_that_never_answers_is_given_up_at_the_deadline(monkeypatch):
    host, s, held = _silent_controller()
    monkeypatch.setattr(runexec, "CONNECT_TIMEOUT_S", 2.0)
    t0 = time.monotonic()
    try:
        with pytest.raises(UsageError, match=rf"--host {host}: no answer from the controller within 2 s"):
            runexec.answers(host)
    finally:
        for c in [s, *held]:
            c.close()
    assert time.monotonic() - t0 < 10.0


def test_a_refused_connection_is_one_line_and_exit_2(tmp_path):
    plan = tmp_path / "plan.json"
    subprocess.run([sys.executable, "-m", "app.cli", "plan", "paper", "--waypoints", "4", "--out", str(plan)],
                   cwd=ROOT, check=True, capture_output=True)
    p = subprocess.run([sys.executable, "-m", "app.cli", "run", "paper", "--plan", str(plan), "--host", "127.0.0.1",
                        "--yes", "--out", str(tmp_path / "run")], cwd=ROOT, capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2, p.stderr
    ours = [ln for ln in p.stderr.splitlines() if ln.startswith("palpate")]
    assert ours[-1].startswith("palpate: --host 127.0.0.1: cannot connect:") and "Traceback" not in p.stderr


def test_the_cell_refuses_to_resume_another_plans_records(tmp_path):
    plans = []
    for n in (4, 5):
        plans.append(tmp_path / f"plan{n}.json")
        subprocess.run([sys.executable, "-m", "app.cli", "plan", "paper", "--waypoints", str(n), "--out",
                        str(plans[-1])], cwd=ROOT, check=True, capture_output=True)

    def cell(plan, *more):
        return subprocess.run([sys.executable, "-m", "app.cell", "--sim", "--plan", str(plan), "--out",
                               str(tmp_path / "out"), *more], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert cell(plans[0]).returncode == 0
    before = (tmp_path / "out" / "probes.jsonl").read_bytes()
    p = cell(plans[1])
    assert p.returncode == 2 and "holds records of another plan (probe 1 at x" in p.stderr, p.stderr
    assert (tmp_path / "out" / "probes.jsonl").read_bytes() == before          # nothing written, nothing moved
    again = cell(plans[0])
    assert again.returncode == 0 and "4 from the log" in again.stdout           # its own plan resumes
    assert cell(plans[1], "--fresh").returncode == 0                           # --fresh moves them aside


def test_a_fault_a_resumed_run_meets_again_says_what_to_change_first():
    """A drifting sensor or a surface at the approach height ends every resumed run the same way (the review's
    re-runs each added one probe and faulted again): the last line says what must change first."""
    from app.runexec import verdict
    line = verdict(None, None, "", "fault", {"fault": {"kind": "free_air_force"}})
    assert line.startswith("NO RESULT") and "once the sensor reads steady in free air with its force sign" in line
    high = verdict(None, None, "", "fault", {"fault": {"kind": "surface_high"}})
    assert "palpate plan --approach-height-m" in high and "--fresh" in high      # a new plan: not a resume
    other = verdict(None, None, "", "fault", {"fault": {"kind": "connection_lost"}})
    assert other.endswith("the same command resumes")


def test_the_refinement_design_survives_probes_stopped_at_a_surface_5_mm_high():
    """`palpate run paper --sim --truth-surface-offset-m 0.005` (inside the truth's allowed range) crashed after
    round 0: every probe stopped at the depth limit, their nominal depths about 0 (-22 um for the median), and the
    design asked fem for the prior's force there (fem: depth must lie in [0, H)). The design's depth is now held
    inside fem's range; a whole run at +5 mm finds the stone (docs/robot.md)."""
    import numpy as np

    sys.path.insert(0, str(Path(__file__).parent))
    from test_localize import ToySurrogate

    from fem.scene import load
    from planner.localize import Localization, Measurements
    from planner.refine import design_positions
    prior = load("paper").prior()
    x = np.linspace(0.005, 0.065, 15)
    depth = np.linspace(-4e-5, 3e-5, 15)                 # nominal depths reached: about 0, some below
    meas = Measurements(x, depth, np.full(15, 0.1), np.full(15, 2e-3), np.full(15, 7.25), np.arange(15))
    loc = Localization(detected=True, lr=100.0, lr_threshold=25.0, x_m=0.035, depth_m=0.025, diameter_m=0.015,
                       sigma_x_m=2e-4, sigma_depth_m=2e-3, sigma_diameter_m=2e-3,
                       nuisance={"fixed": [], "surface_offset_m": (0.005, 1e-4)})
    class Toy(ToySurrogate):      # (fem's table has no force above the surface: 0 there)
        def contrast(self, x0, depth, *stone):
            return super().contrast(x0, np.maximum(np.asarray(depth, float), 0.0), *stone)
    pos = design_positions(loc, meas, 10, Toy(), 0.070, 0.005, prior=prior)
    assert len(pos) == 10 and np.all((pos >= 0.005) & (pos <= 0.065)) and np.all(np.isfinite(pos))


def test_the_run_figure_draws_the_prior_at_depths_fem_has_and_at_most_four():
    """The same run then failed in its figure: a prior curve at every distinct depth reached (each depth-limited
    probe its own, some at 0 or above the nominal surface)."""
    import numpy as np

    from fem.scene import load
    from planner.plots_run import MAX_CURVES, curve_depths
    prior = load("paper").prior()
    depth = np.r_[np.full(10, 0.004), np.full(5, 0.003), np.linspace(-3e-4, 6e-3, 30)]
    got = curve_depths(prior, depth)
    assert 0.004 in got and 0.003 in got and len(got) <= MAX_CURVES
    assert np.all(got > 0) and np.all(got < prior.indenter.radius_m)
    spread = np.linspace(-2e-4, 3e-3, 40)          # every probe its own depth (stopped at the depth limit)
    mid = curve_depths(prior, spread)
    inside = spread[spread > 0]
    assert len(mid) == MAX_CURVES and np.all(np.abs(mid - np.median(inside)) < 0.2e-3)    # not the shallowest four
    assert len(curve_depths(prior, np.full(5, -1e-4))) == 0


def test_3d_detectability_names_no_stone_that_cannot_fit_in_the_block():
    """A 35 mm block's line named "12 mm at 30 mm depth", a stone whose bottom would be 1 mm above the floor (the
    localizer keeps 2 mm of tissue below a candidate)."""
    from types import SimpleNamespace

    import numpy as np

    from core.contracts import SENSORS, Limits, Motion
    from fem.scene import load
    from planner.detect3d import detectability3d
    from planner.surrogate3d import load_surrogate3d
    sur = load_surrogate3d(load("block3d").prior(), build=False)

    class Thinner:                 # block3d's table, said to be for a 35 mm block
        def __getattr__(self, name):
            return getattr(sur, name)

        def bounds(self):
            return {**sur.bounds(), "height_m": 0.035}
    g = np.linspace(0.02, 0.05, 6)
    plan = SimpleNamespace(probes=[SimpleNamespace(x_m=a, y_m=b, depth_m=0.004) for a in g for b in g],
                           limits=Limits(), motion=Motion())
    det = detectability3d(plan, Thinner(), 0.07, sensor_spec=SENSORS["nano17"])
    for r in det["rows"]:
        fits = r["depth_m"] + r["diameter_m"] / 2 <= 0.035 - 2e-3
        assert (r.get("note") == "does not fit in the block") is (not fits), r
    assert all(s["depth_m"] + s["diameter_m"] / 2 <= 0.033 for s in det["smallest_detectable"])
    full = detectability3d(plan, sur, 0.07, sensor_spec=SENSORS["nano17"])       # block3d itself: all fit
    assert not any(r.get("note") == "does not fit in the block" for r in full["rows"])


def test_a_3d_prior_fem_cannot_model_is_said_without_an_unrelated_hint(tmp_path):
    """A block with a 2D section's mesh (0.5 mm elements over a 60 mm face: a 36 GB compliance; what a block's file
    without [analysis] got before session 47) was refused with a hint about the depth limit and the tip's radius
    appended, which had nothing to do with it."""
    scene = tmp_path / "n01.toml"
    scene.write_text('name = "n01"\n[tissue]\nwidth_m = 0.060\nheight_m = 0.040\nlength_m = 0.060\n'
                     'youngs_pa = 3000.0\npoisson = 0.4\n[indenter]\nshape = "sphere"\nradius_m = 0.005\n'
                     '[analysis]\nmesh_size_m = 0.002\nsurface_refine = 4.0\n')
    p = subprocess.run([sys.executable, "-m", "app.cli", "run", str(scene), "--sim", "--out", str(tmp_path / "o")],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert p.returncode == 2, p.stderr
    last = p.stderr.strip().splitlines()[-1]
    assert "lower analysis.patch_m or analysis.surface_refine" in last and "radius" not in last, last
