"""Session 54's safety review of the driver and the cell: each test fails on session 53's code.

1. A probe that would feel no contact (the plan's threshold, or the sensor's noise, above its predicted force) had
   no depth limit from the true surface: 6 mm into tissue 2 mm higher than registered against a 4 mm limit.
2. ``--ft-sensor-pose`` took rotations typed in degrees (180 read 0.6 N per newton).
3. A full disk mid-run said exit 2 (the code for bad input); on ``--host`` the driver's error after its stop was a
   traceback.
(The missing or small force exponent: tests/test_depth_limit_s43.py.)
"""
from __future__ import annotations

import errno
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from robot_fixtures import make_plan, make_sim  # noqa: E402

from app import cell, cli  # noqa: E402
from app.isolate import ChildError  # noqa: E402
from core.contracts import FaultKind, Limits, Motion  # noqa: E402
from robot import records as records_mod  # noqa: E402
from robot.driver import run_plan  # noqa: E402
from robot.records import read_records  # noqa: E402
from robot.simforce import standin_force_model  # noqa: E402

HIGH = 0.002                   # the true surface this far above the registered one


def _deepest_below_true_surface(out: Path) -> float:
    recs = read_records(out)
    return max(float(records_mod.load_raw(out, r)["depth_m"].max()) for r in recs if r.n_samples) + HIGH


def test_a_probe_that_cannot_feel_contact_faults_before_its_descent(tmp_path):
    """The plan's contact threshold raised to 0.2 N over probes predicted to press 0.1 N, the surface 2 mm high: the
    first probe faults (contact_unfelt) at its approach pose; the tip never enters the tissue. With the plan's own
    threshold the same probes stop at the depth limit below the true surface."""
    force = standin_force_model(k_n_per_m15=300.0, stones=())
    mo = Motion(approach_height_m=0.004, dwell_s=0.2, contact_threshold_n=0.2)
    plan = make_plan((0.02, 0.035), depth_m=0.004, predicted=0.1, motion=mo, limits=Limits(depth_limit_m=0.004))
    arm, c, r = make_sim(force, surface_height_m=lambda x: HIGH)
    rep = run_plan(plan, c, r, tmp_path / "high-thr")
    assert rep.status == "fault" and rep.fault["kind"] == FaultKind.CONTACT_UNFELT, rep.fault
    msg = rep.fault["message"]
    assert "probe 0 might feel no contact before the depth limit" in msg and "motion.contact_threshold_n" in msg, msg
    assert arm.tip_in_tissue()[1] < -HIGH              # above the true surface: never pressed
    # the plan's own threshold (20 mN): felt, and the limit counted from the true surface
    plan = make_plan((0.02, 0.035), depth_m=0.004, predicted=0.1, motion=Motion(approach_height_m=0.004, dwell_s=0.2),
                     limits=Limits(depth_limit_m=0.004))
    arm, c, r = make_sim(force, surface_height_m=lambda x: HIGH)
    assert run_plan(plan, c, r, tmp_path / "ok").status == "ok"
    assert _deepest_below_true_surface(tmp_path / "ok") < 0.004 + 2.5e-4


def test_a_shallow_probe_runs_where_the_prior_feels_contact_before_the_limit(tmp_path):
    """The review of the first version of the check: a shallow probe the prior predicts below the threshold at its own
    depth (0.4 mm, 10 mN against 20 mN) still feels contact before the limit where the surface is high (its force
    continued to 4 mm: 0.1 N at least), so it runs (session 52's no-contact note). One predicted at 1 mN (10 mN at the
    limit: under 1.5 thresholds) faults, unless depth plus approach height stays within the limit."""
    for predicted, approach, status in ((0.01, 0.010, "ok"), (0.001, 0.010, "fault"), (0.001, 0.0035, "ok"),
                                        (0.0, 0.010, "ok")):     # (0: no prediction, nothing to judge by)
        plan = make_plan((0.02,), depth_m=0.0004, predicted=predicted, motion=Motion(approach_height_m=approach,
                                                                                        dwell_s=0.2))
        arm, c, r = make_sim()
        rep = run_plan(plan, c, r, tmp_path / f"a{predicted}-{approach}")
        assert rep.status == status, (predicted, approach, rep.fault)
        if status == "fault":
            assert rep.fault["kind"] == FaultKind.CONTACT_UNFELT and "1.5 x the contact threshold" in \
                rep.fault["message"], rep.fault


@pytest.mark.parametrize("pose", ["0,0,0.025,0,0,90", "0,0,0.025,180,0,0", "0,0,0.025,0,15,0"])
def test_a_sensor_pose_in_degrees_is_refused_in_one_line(tmp_path, capsys, pose):
    code = cli.main(["run", "paper", "--sim", "--ft", "netft", "--ft-sensor-pose", pose, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--ft-sensor-pose" in err[0] and "degrees?" in err[0], err
    assert not (tmp_path / "o").exists()


def test_a_half_turn_in_radians_is_a_sensor_pose():
    from app.ftoptions import pose6
    assert pose6("0,0,0.025,3.14159,0,0")[3] == pytest.approx(3.14159)


def test_a_full_disk_mid_run_is_exit_1_in_one_line_and_keeps_what_was_written(tmp_path, capsys, monkeypatch):
    plan_file = tmp_path / "plan.json"
    make_plan((0.02, 0.035, 0.05), depth_m=0.003).save(plan_file)
    real = records_mod.RunLog.write_probe
    calls = []

    def full(self, *a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "o" / "probes.jsonl"))
        return real(self, *a, **k)
    monkeypatch.setattr(records_mod.RunLog, "write_probe", full)
    code = cell.main(["--sim", "--plan", str(plan_file), "--out", str(tmp_path / "o"), "--force-model", "standin"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1, err
    assert "No space left on device" in err[-1] and "what was written before is kept" in err[-1] and "not the command's input" in err[-1], err
    assert "Traceback" not in "\n".join(err)
    recs = read_records(tmp_path / "o")
    assert recs[0].index == 0 and recs[0].status == "ok"            # the first probe's record stays


def test_the_drivers_error_on_a_host_is_one_line_and_exit_1(tmp_path, capsys, monkeypatch):
    """--host: the driver runs in a child (app.isolate); an error it raises after stopping the arm comes back as
    ChildError, which was a traceback."""
    plan_file = tmp_path / "plan.json"
    make_plan((0.02,), depth_m=0.003).save(plan_file)

    def child(*a, **k):
        raise ChildError("OSError", "[Errno 28] No space left on device: 'raw/probe_002.npz'", "trace")
    monkeypatch.setattr(cell, "run_in_child", child)
    monkeypatch.setattr(cell, "_preflight_host", lambda *a, **k: None, raising=False)
    code = cell.main(["--host", "127.0.0.1", "--plan", str(plan_file), "--out", str(tmp_path / "o"), "--yes"])
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "\n".join(err), err
    assert code == 1 and "the process holding the arm's link failed: OSError" in err[-1], err


def test_a_run_whose_readings_are_mostly_left_out_is_not_called_no_stone(tmp_path, capsys):
    """A session-54 review: a sensor drifting 3 mN/s (the localizer's prior allows about 1) stopped every probe early,
    9 of 15 readings were left out of the fit as no tissue's force, and the rest said NO STONE over the paper's
    15 mm stone, with no warning. The left-out probes are now said, and with most of them out the verdict is NOT
    LOCALIZED."""
    import json
    code = cli.main(["run", "paper", "--sim", "--truth-sensor-drift-n-per-s", "0.003", "--seed", "0", "--no-figure",
                     "--out", str(tmp_path / "o")])
    out = capsys.readouterr()
    r = json.loads((tmp_path / "o" / "result.json").read_text())
    assert code == 0 and r["verdict"] == "not_localized", r["verdict"]
    odd = r["implausible_probes"]
    assert 2 * odd["n"] >= odd["of"] and "not tissue" in odd["first_reason"], odd
    assert f"warning: {odd['n']} of {odd['of']} probes read forces no tissue gives" in out.err
    assert out.out.startswith("NOT LOCALIZED: "), out.out


def test_a_stone_reaching_below_the_tissues_bottom_is_flagged():
    """A session-54 review: a 4 mm stone fitted 36.7 mm deep in 35 mm tissue, unflagged. A stone whose bottom lies
    below the tissue's (as its thickness is fitted) is in at_bound as "below the bottom", with a warning, and is
    never called converged."""
    from planner.localize import BELOW_BOTTOM, Localization, below_bottom
    from planner.refine import caveats
    assert below_bottom(0.0367, 0.004, 0.035, 0.0) and not below_bottom(0.0367, 0.004, 0.035, 0.12)
    assert not below_bottom(0.030, 0.008, 0.035, 0.0) and below_bottom(0.030, 0.008, 0.035, -0.05)
    loc = Localization(detected=True, lr=116.0, lr_threshold=20.0, x_m=0.045, depth_m=0.0367, diameter_m=0.004,
                       sigma_x_m=1e-4, sigma_depth_m=1e-4, sigma_diameter_m=1e-4, at_bound=[BELOW_BOTTOM])
    text = caveats(loc)
    assert "reaches below the tissue's bottom" in text and "tissue's below" not in text, text



def test_a_resumed_run_keeps_the_report_it_replaces(tmp_path):
    """run.json is the latest run's report; the one it replaces goes to run_history.jsonl first (a session-54 safety
    review: after four interrupts and a resume only "ok" was left), a damaged one as its text."""
    import json

    from robot.records import HISTORY, RunLog
    log = RunLog(tmp_path)
    log.write_run({"status": "fault", "fault": {"kind": "timeout"}})
    assert not (tmp_path / HISTORY).exists()
    log.write_run({"status": "interrupted"})
    (tmp_path / "run.json").write_text("{torn")
    log.write_run({"status": "ok"})
    log.close()
    hist = [json.loads(x) for x in (tmp_path / HISTORY).read_text().splitlines()]
    assert hist == [{"status": "fault", "fault": {"kind": "timeout"}}, {"unparsed_run_json": "{torn"}]
    assert json.loads((tmp_path / "run.json").read_text()) == {"status": "ok"}
