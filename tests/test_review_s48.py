"""Session 48: a user's Ctrl-C during a simulated run is said as an interruption (exit 130, as palpate-cell and the
shell report one), not as a fault of the cell; the run resumes from its kept probes. result.json's detectability
names its quantities in SI units (a list of {depth_m, diameter_m}, not a dict keyed by millimetres)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from app.runexec import exit_code, verdict
from planner.detectability import describe_smallest, smallest_detectable

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
    if p.returncode == 0:                           # the run finished before the signal landed: nothing to check
        assert "STONE" in so
        return
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
    assert json.loads((out / "result.json").read_text())["verdict"] == "stone"


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
    from app.cli import join_negative_lists, main
    assert join_negative_lists(["plan", "--branch", "-1,1,1", "--x", "-0.5"]) == ["plan", "--branch=-1,1,1", "--x",
                                                                                   "-0.5"]
    assert join_negative_lists(["--", "-1,2"]) == ["--", "-1,2"]
    assert join_negative_lists(["--a=1", "-1,2"]) == ["--a=1", "-1,2"]
    assert main(["plan", "paper", "--branch", "-1,1,-1", "--out", str(tmp_path / "p.json")]) == 0
    assert json.loads((tmp_path / "p.json").read_text())["options"]["branch"] == [-1, 1, -1]
    assert main(["plan", "paper", "--branch", "-1,1,2", "--out", str(tmp_path / "q.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--branch" in err[0] and "'-1,1,2'" in err[0], err
