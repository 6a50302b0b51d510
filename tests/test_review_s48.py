"""Session 48: a user's Ctrl-C during a simulated run is said as an interruption (exit 130, as palpate-cell and the
shell report one), not as a fault of the cell; the run resumes from its kept probes. result.json's detectability
names its quantities in SI units (a list of {depth_m, diameter_m}, not a dict keyed by millimetres)."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from app.cli import check_environment, join_negative_lists, main
from app.errors import UsageError
from app.runexec import check_resume, exit_code, resuming_note, verdict
from core.contracts import Limits, Plan, PlanError, ProbeRecord
from fem.scene import SceneError, from_dict, load
from planner.detectability import describe_smallest, smallest_detectable
from planner.plan import plan_raster
from robot.records import RunLog, move_aside, read_records

ROOT = Path(__file__).resolve().parents[1]


def test_an_interrupted_run_is_said_as_one_and_exits_130():
    line = verdict(None, None, "", "interrupted", {"fault": {"kind": "interrupted"}})
    assert line.startswith("NO RESULT: interrupted") and "fault" not in line and "resumes" in line
    other = verdict(None, None, "", "fault", {"fault": {"kind": "sensor_lost"}})
    assert other.startswith("NO RESULT: the arm run ended with a fault (sensor_lost)")
    assert (exit_code("ok"), exit_code("interrupted"), exit_code("fault")) == (0, 130, 1)


def test_ctrl_c_in_a_simulated_run_stops_keeps_the_probes_and_the_run_resumes(tmp_path):
    out = tmp_path / "run"
    cmd = [sys.executable, "-c", "import sys; from app.entry import palpate; sys.exit(palpate())",
           "run", "paper", "--sim", "--no-figure", "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    probes = out / "probes.jsonl"
    deadline = time.monotonic() + 600
    while not (probes.exists() and len(probes.read_text().splitlines()) >= 3):
        assert p.poll() is None, p.communicate()
        assert time.monotonic() < deadline, "no probe measured in 600 s"
        time.sleep(0.05)
    os.killpg(p.pid, signal.SIGINT)                 # a terminal's Ctrl-C: the whole foreground group
    so, se = p.communicate(timeout=120)
    before = probes.read_text().splitlines()
    kept = len(before)
    assert p.returncode == 130, (p.returncode, se)
    last = so.strip().splitlines()[-1]
    assert last.startswith("NO RESULT: interrupted") and "fault" not in last.split(";")[0], last
    assert json.loads((out / "result.json").read_text())["verdict"] == "no_result"
    assert "Traceback" not in se, se
    r = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    assert "resum" in r.stderr.lower(), r.stderr
    after = probes.read_text().splitlines()
    assert len(after) > kept and after[:kept] == before            # the kept probes untouched, more measured after
    r = json.loads((out / "result.json").read_text())
    assert r["verdict"] == "stone"
    # the resumed run's plan time is that of the probes it pressed (every round's whole plan was counted before,
    # against the arm time of the probes pressed now)
    assert abs(r["time"]["robot_s"] - r["time"]["planned_s"]) < 0.03 * r["time"]["planned_s"], r["time"]


def test_smallest_detectable_is_si_and_by_depth():
    rows = [{"depth_m": 0.02, "diameter_m": 0.008, "detectable": True},
            {"depth_m": 0.01, "diameter_m": 0.006, "detectable": False},
            {"depth_m": 0.01, "diameter_m": 0.0085, "detectable": True},
            {"depth_m": 0.02, "diameter_m": 0.006, "detectable": True},
            {"depth_m": 0.03, "diameter_m": 0.017, "detectable": None}]
    s = smallest_detectable(rows)
    assert s == [{"depth_m": 0.01, "diameter_m": 0.0085}, {"depth_m": 0.02, "diameter_m": 0.006}]
    assert describe_smallest(s) == "depth 10 mm: >= 8.5 mm, depth 20 mm: >= 6 mm"
    assert smallest_detectable([]) == [] and describe_smallest([]) == ""


def test_a_list_option_starting_with_a_minus_is_taken_as_its_value(tmp_path, capsys):
    """``--branch -1,1,1`` read "expected one argument" (argparse took the list for an option); now it is the
    option's value, as ``--branch=-1,1,1`` is, and a bad one is still refused naming the option."""
    assert join_negative_lists(["plan", "--branch", "-1,1,1", "--x", "-0.5"]) == ["plan", "--branch=-1,1,1", "--x",
                                                                                   "-0.5"]
    assert join_negative_lists(["--", "-1,2"]) == ["--", "-1,2"]
    assert join_negative_lists(["--", "--x", "-1,2"]) == ["--", "--x", "-1,2"]
    assert join_negative_lists(["--a=1", "-1,2"]) == ["--a=1", "-1,2"]
    assert main(["plan", "paper", "--branch", "-1,1,-1", "--out", str(tmp_path / "p.json")]) == 0
    assert json.loads((tmp_path / "p.json").read_text())["options"]["branch"] == [-1, 1, -1]
    capsys.readouterr()         # (that plan's warning line: its elbow below the base's plane, since session 59)
    assert main(["plan", "paper", "--branch", "-1,1,2", "--out", str(tmp_path / "q.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--branch" in err[0] and "'-1,1,2'" in err[0], err


@pytest.mark.parametrize("edit, names", [
    (lambda d: d["limits"].pop("force_limit_n"), "limits.force_limit_n is missing"),
    (lambda d: d.update(limits={}), "limits.force_limit_n is missing"),
    (lambda d: d["limits"].pop("workspace_max_m"), "limits.workspace_max_m is missing"),
    (lambda d: d["motion"].pop("contact_threshold_n"), "motion.contact_threshold_n is missing"),
    (lambda d: d["motion"].pop("probe_speed_m_s"), "motion.probe_speed_m_s is missing"),
    (lambda d: d.pop("options"), "'options' is missing"),
    (lambda d: d["options"].pop("branch"), "options.branch is missing"),
    (lambda d: d["probes"][1].pop("x_m"), r"probes\[1\].x_m is missing"),
    (lambda d: d["probes"][1].update(foo=1), r"probes\[1\].foo is unknown"),
])
def test_a_plan_missing_a_limit_or_motion_field_is_refused_not_defaulted(edit, names):
    """A review's hand-edited plan without limits.force_limit_n ran on palpate-cell with the 2 N default, four times
    its planned 0.5 N; a missing workspace, probe speed or contact threshold took defaults the same way."""
    d = json.loads(json.dumps(plan_raster(load("paper").prior(), n_waypoints=3,
                                          limits=Limits(force_limit_n=0.5)).to_dict()))
    assert Plan.from_dict(json.loads(json.dumps(d))).limits.force_limit_n == 0.5
    edit(d)
    with pytest.raises(PlanError, match=names):
        Plan.from_dict(d)


def test_an_older_2d_plan_may_lack_y_but_a_3d_plan_may_not():
    d = plan_raster(load("paper").prior(), n_waypoints=3).to_dict()
    for p in d["probes"]:
        del p["y_m"]
    assert [p.y_m for p in Plan.from_dict(d).probes] == [0.0, 0.0, 0.0]
    d3 = plan_raster(load("paper").prior(), n_waypoints=3).to_dict()
    d3["scene"]["tissue"]["length_m"] = 0.07             # a block's plan (the field rule comes before its checks)
    del d3["probes"][2]["y_m"]
    with pytest.raises(PlanError, match=r"probes\[2\].y_m is missing"):
        Plan.from_dict(d3)


def test_a_plans_time_is_the_simulated_drivers(tmp_path):
    """The plan's timing counts the driver's free-air zeroing before each descent and its slow retract (a helper's
    phase-by-phase comparison: the plan was 7 % short on the paper section, 0.18 s zeroing and 0.41 s retract of
    8.60 s a probe; now measured within 0.3 %). The coarse raster alone, every probe to its planned depth."""
    assert main(["plan", "paper", "--out", str(tmp_path / "p.json")]) == 0
    assert main(["run", "paper", "--sim", "--plan", str(tmp_path / "p.json"), "--budget-probes", "15",
                 "--no-figure", "--out", str(tmp_path / "run")]) == 0
    r = json.loads((tmp_path / "run" / "result.json").read_text())
    assert r["probes_used"] == 15
    planned, robot = r["time"]["planned_s"], r["time"]["robot_s"]
    assert abs(robot - planned) < 0.01 * planned, (robot, planned)


def test_damaged_record_lines_are_listed_and_never_reach_the_fit(tmp_path):
    """A review's edits of probes.jsonl: a garbage line mid-file was dropped without a word (its probe pressed again
    silently), and a NaN or 1e308 force reached the localizer (a traceback). Now each is listed with its line and
    why, skipped, and said when the run resumes; a torn final line (a crash mid-write) is still skipped quietly."""

    src = ROOT / "tests" / "data" / "mismatch-trial-0048"
    lines = (src / "probes.jsonl").read_text().splitlines()
    good = len(lines)
    edits = {3: "garbage{", 5: ("force_mean_n", float("nan")), 6: ("force_mean_n", 1e308),
             7: ("depth_reached_m", "deep"), 8: ("x_m", None)}
    for k, e in edits.items():
        if isinstance(e, str):
            lines[k - 1] = e
        else:
            d = json.loads(lines[k - 1])
            d[e[0]] = e[1]
            lines[k - 1] = json.dumps(d)
    (tmp_path / "probes.jsonl").write_text("\n".join(lines) + "\n" + '{"index": 99, "x_')    # + a torn last line
    damaged: list = []
    recs = read_records(tmp_path, damaged)
    assert [k for k, _ in damaged] == sorted(edits) and len(recs) == good - len(edits)
    assert "force_mean_n = 1e+308" in dict(damaged)[6] and "NaN" in dict(damaged)[5]
    note = resuming_note(tmp_path)
    assert f"warning: {len(edits)} line(s)" in note and "line 3:" in note
    (tmp_path / "probes.jsonl").unlink()
    (tmp_path / "raw").mkdir()
    shutil.copy(src / "probes.jsonl", tmp_path / "raw" / "probe_000.npz")      # (any file of that name)
    assert "is missing but" in resuming_note(tmp_path)


def _a_run_dir(tmp_path, opts: dict) -> Path:
    out = tmp_path / "run"
    out.mkdir()
    (out / "run_options.json").write_text(json.dumps(opts))
    (out / "probes.jsonl").write_text("")
    return out


def test_resume_takes_an_option_at_its_default_and_a_scene_by_another_path(tmp_path):
    """A review's resumes refused as "other options": --depth-limit-m given at its default (0.004) after a run
    without it, and the same scene file as ./st.toml after st.toml. A real change is still refused."""
    base = {"scene": "st.toml", "scene_key": "abc", "seed": 0}
    out = _a_run_dir(tmp_path, base)
    assert check_resume(out, dict(base, depth_limit_m=0.004), fresh=False)
    assert check_resume(out, dict(base, scene="./st.toml"), fresh=False)
    with pytest.raises(UsageError, match=r"depth_limit_m was not given \(default 0.004\), now 0.003"):
        check_resume(out, dict(base, depth_limit_m=0.003), fresh=False)
    with pytest.raises(UsageError, match="scene_key"):
        check_resume(out, dict(base, scene="./st.toml", scene_key="def"), fresh=False)
    out2 = tmp_path / "b"
    out2.mkdir()
    (out2 / "run_options.json").write_text(json.dumps(dict(base, depth_limit_m=0.004)))
    (out2 / "probes.jsonl").write_text("")
    assert check_resume(out2, base, fresh=False)


def test_fresh_leaves_the_commands_own_input_files_in_place(tmp_path):
    """--fresh moved everything in OUT aside, the scene file the command was running included: the next run with
    the same command then failed for a missing scene file."""
    out = tmp_path / "K"
    out.mkdir()
    for n in ("mine.toml", "notes.txt", "probes.jsonl", "plan.json"):
        (out / n).write_text(n)
    dest = move_aside(out, keep=[str(out / "mine.toml"), str(tmp_path / "K" / "." / "plan.json"), "paper"])
    assert sorted(p.name for p in out.iterdir() if p != dest) == ["mine.toml", "plan.json"]
    assert sorted(p.name for p in dest.iterdir()) == ["notes.txt", "probes.jsonl"]
    assert move_aside(out, keep=[str(out / "mine.toml"), str(out / "plan.json")]) is None     # nothing else to move


@pytest.mark.parametrize("name", ["a\nSTONE fake line", "red\x1b[31m", "", "   ", "tab\there"])
def test_a_scene_name_that_would_garble_the_output_is_refused(name):
    d = load("healthy").to_dict()
    with pytest.raises(SceneError, match="name = .*printable"):
        from_dict(dict(d, name=name))
    assert from_dict(dict(d, name="kidney 7 (left)")).name == "kidney 7 (left)"
    long = from_dict(dict(d, name="n" * 200))           # (its prior's name, with "-prior", reads back too)
    assert from_dict(long.prior().to_dict()).name == "n" * 200 + "-prior"


@pytest.mark.parametrize("value, ok", [("1.5", False), ("abc", False), ("-3", False), ("inf", False), ("0", False),
                                       ("500000", True), ("2e6", True)])
def test_palpate_max_dofs_is_a_whole_positive_number(value, ok, monkeypatch):
    monkeypatch.setenv("PALPATE_MAX_DOFS", value)
    if ok:
        check_environment()
    else:
        with pytest.raises(UsageError, match="PALPATE_MAX_DOFS"):
            check_environment()


def test_ft_seed_is_range_checked(capsys):
    assert main(["ft", "--ft", "netft", "--seed", "-200000", "--duration-s", "0.2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--seed" in err[0] and "[0, 4294967295]" in err[0]


def test_a_real_controllers_clock_and_a_torn_line_are_not_damage(tmp_path):
    """A review's two false alarms: t_s is the controller's clock (seconds since it started: past 1e6 after 11.6
    days of uptime), and a bound on it made every record of such an arm "damaged" (none reached the fit, every probe
    pressed again); a line torn by a crash, ended by the next run's log and then mid-file, was called damaged. Now
    times need only be finite, and the torn line is set aside in probes.jsonl.torn (kept, never read)."""

    def rec(i, **kw):
        return ProbeRecord(index=i, x_m=0.01 * i, status="ok", force_mean_n=0.5, t_s=1_036_800.0, **kw)
    (tmp_path / "probes.jsonl").write_text(json.dumps(rec(0).to_dict(), default=str) + "\n" + '{"index": 1, "x_')
    log = RunLog(tmp_path)
    log.write_probe(rec(1))
    log.close()
    damaged: list = []
    assert [r.index for r in read_records(tmp_path, damaged)] == [0, 1] and damaged == []
    assert (tmp_path / "probes.jsonl.torn").read_text() == '{"index": 1, "x_\n'
    assert "warning" not in resuming_note(tmp_path)
    with pytest.raises(ValueError, match="force_mean_n"):
        ProbeRecord.from_dict(dict(rec(2).to_dict(), status="ok", force_mean_n=2e6))
    assert ProbeRecord.from_dict(dict(rec(2).to_dict(), status="ok", later_field=1e300)).index == 2
