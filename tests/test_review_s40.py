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
    assert line.startswith("NO RESULT") and "once the sensor is steady in free air" in line
    assert "--approach-height-m" in verdict(None, None, "", "fault", {"fault": {"kind": "surface_high"}})
    other = verdict(None, None, "", "fault", {"fault": {"kind": "connection_lost"}})
    assert other.endswith("the same command resumes")
