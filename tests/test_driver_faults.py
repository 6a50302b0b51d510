"""Injected faults end in a safe state with every completed probe on disk; a resumed run finishes the plan."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from robot_fixtures import make_plan, make_sim  # noqa: E402

from robot.driver import DriverConfig, run_plan, watchdog_rate_hz  # noqa: E402
from robot.records import done_indices, load_raw, read_records  # noqa: E402
from robot.sim import SimRTDEControl, SimRTDEReceive  # noqa: E402

XS = (0.02, 0.035, 0.05)
DEPTH = 0.003


def at_probe(i, min_depth_m):
    """Trigger: the tip is at probe i's x and at least min_depth_m below the surface."""
    return lambda a: abs(a.tip_in_tissue()[0] - XS[i]) < 1e-4 and a.tip_in_tissue()[1] >= min_depth_m


def run(tmp_path, c, r, **kw):
    return run_plan(make_plan(XS, depth_m=DEPTH), c, r, tmp_path, **kw)


def check_safe_end(rep, arm, tmp_path, kind, n_done=1, retracted=True):
    assert rep.status == "fault" and rep.fault["kind"] == kind, rep.fault
    assert not arm.is_moving
    recs = read_records(tmp_path)
    assert [x.index for x in recs if x.status == "ok"] == list(range(n_done))
    last = recs[-1]
    assert last.status == "fault" and last.index == n_done and kind in last.reason
    assert len(load_raw(tmp_path, last)["time_s"]) == last.n_samples_total > 0    # its samples are kept
    run_json = json.loads((tmp_path / "run.json").read_text())
    assert run_json["status"] == "fault" and run_json["fault"]["kind"] == kind
    assert rep.fault["retracted"] is retracted
    if retracted:
        assert arm.tip_in_tissue()[1] <= -0.003          # back at the approach height, out of the tissue
    return recs


def resume_and_check(tmp_path, c, r, n_done_before):
    rep = run(tmp_path, c, r)
    assert rep.status == "ok", rep.fault
    assert rep.n_skipped == n_done_before and rep.n_ok == len(XS) - n_done_before
    recs = read_records(tmp_path)
    for i in range(len(XS)):                              # finished probes were not repeated
        assert sum(1 for x in recs if x.index == i and x.status == "ok") == 1
    assert done_indices(tmp_path) == set(range(len(XS)))


def test_protective_stop_mid_indent_then_resume(tmp_path):
    arm, c, r = make_sim()
    arm.inject("protective_stop", when=at_probe(1, 0.0015))
    rep = run(tmp_path, c, r)
    check_safe_end(rep, arm, tmp_path, "protective_stop", retracted=False)
    assert rep.fault["stopped"] and "pendant" in " ".join(rep.fault["notes"])
    assert arm.tip_in_tissue()[1] > 0.001                 # halted in the tissue: cannot retract while stopped
    arm.clear_protective_stop()                          # the operator, on the pendant
    resume_and_check(tmp_path, c, r, 1)                  # the driver retracts first, then finishes


def test_protective_stop_seen_first_by_the_control_interface(tmp_path):
    """ur_rtde's two interfaces have separate data streams: a command (here the watchdog kick) can be refused
    before the receive interface reports the protective stop. The fault is still classified as one."""
    class LaggingReceive(SimRTDEReceive):
        def isProtectiveStopped(self):
            fired = [f["fired_s"] for f in self.arm.faults if f["fired_s"] is not None]
            return bool(fired) and self.arm.t_s - fired[0] > 0.008          # four periods late

    arm, c, _ = make_sim()
    arm.inject("protective_stop", when=at_probe(1, 0.0015))
    rep = run(tmp_path, c, LaggingReceive(arm))
    assert rep.fault["kind"] == "protective_stop", rep.fault
    assert "kickWatchdog" in rep.fault["message"]


def test_resume_refused_while_still_protective_stopped(tmp_path):
    arm, c, r = make_sim()
    arm.inject("protective_stop", when=at_probe(0, 0.001))
    assert run(tmp_path, c, r).fault["kind"] == "protective_stop"
    rep = run(tmp_path, c, r)
    assert rep.status == "fault" and "pendant" in rep.fault["message"]


def test_disconnect_mid_descent(tmp_path):
    arm, c, r = make_sim()
    arm.inject("disconnect", when=at_probe(1, 0.001))
    rep = run(tmp_path, c, r)
    assert not rep.fault["stopped"] and "bounded moveL" in " ".join(rep.fault["notes"])
    arm.run_until_still()          # the controller's watchdog has stopped the program (and the move)
    check_safe_end(rep, arm, tmp_path, "connection_lost", retracted=False)
    assert arm.tip_in_tissue()[1] <= DEPTH + 1e-9        # no deeper than planned
    arm.connected = True                                 # link back: new interfaces, resume
    c2, r2 = SimRTDEControl(arm), SimRTDEReceive(arm)
    resume_and_check(tmp_path, c2, r2, 1)


@pytest.mark.parametrize("watchdog_hz", [5.0, 0.0])
def test_lost_link_watchdog_stops_the_motion(tmp_path, watchdog_hz):
    """A lost link mid-descent: the driver can send nothing, so the controller must stop the arm by itself. With
    the RTDE watchdog (the default) the program, and the motion, stop within 1/watchdog_hz of the last input; without
    it the async moveL runs on to the planned depth, unsupervised (what the hypothesis search once caught: 30 N
    against a 7.7 N limit, ended only by the controller's own force protective stop)."""
    arm, c, r = make_sim()
    arm.inject("disconnect", when=at_probe(1, 0.0005))
    rep = run(tmp_path, c, r, config=DriverConfig(watchdog_hz=watchdog_hz))
    arm.run_until_still()
    assert rep.fault["kind"] == "connection_lost" and not arm.is_moving
    t_loss = arm.faults[0]["fired_s"]
    depth_now = arm.tip_in_tissue()[1]
    if watchdog_hz:
        v = make_plan(XS, depth_m=DEPTH).motion.probe_speed_m_s
        rate = watchdog_rate_hz(DriverConfig(watchdog_hz=watchdog_hz), v)
        assert rate == watchdog_hz                      # 2 mm/s: the 5 Hz floor already bounds travel to 0.4 mm
        assert arm.watchdog_fired_s is not None and not arm.program_running
        assert arm.watchdog_fired_s - t_loss <= 1.0 / rate + 2 * arm.period_s
        assert depth_now <= 0.0005 + v * (1.0 / rate + 3 * arm.period_s) + 1e-6
    else:
        assert arm.watchdog_fired_s is None and abs(depth_now - DEPTH) < 1e-6


def test_watchdog_stop_while_at_rest_restarts_the_program(tmp_path, monkeypatch):
    """The host is busy for 0.5 s after each probe (writing its record) while the controller runs on: the watchdog
    ends the program with the arm at rest. Before the next probe the driver uploads the program again (TCP, payload
    and watchdog are set before every probe anyway), and the run completes."""
    from robot import driver as drv
    arm, c, r = make_sim()
    write = drv.RunLog.write_probe

    def slow_write(self, rec, raw=None):
        out = write(self, rec, raw)
        for _ in range(250):                             # 0.5 s of controller time with no input from the host
            arm.step()
        return out
    monkeypatch.setattr(drv.RunLog, "write_probe", slow_write)
    calls = []
    set_tcp = c.setTcp
    c.setTcp = lambda pose: calls.append(arm.t_s) or set_tcp(pose)
    rep = run(tmp_path, c, r)
    assert rep.status == "ok" and rep.n_ok == len(XS), rep.fault
    assert arm.watchdog_fired_s is not None              # it did fire ...
    assert rep.program_restarts == len(XS) - 1           # ... the program was uploaded before probes 2 and 3 ...
    assert len(calls) == 1 + len(XS)                     # ... and set-up and every probe set the TCP
    assert max(rec.force_peak_n for rec in read_records(tmp_path)) < 2.0


def _operator_stop_in_flight(arm, c, call: str, after_zeros: int = 3):
    """An operator stops the control program (the pendant's or the dashboard's stop) at rest before probe 1 while
    the driver's ur_rtde call ``call`` is in flight (after ``after_zeros`` zeroings: set-up, probe 0, probe 1):
    ``zeroFtSensor`` is refused at once; ``kickWatchdog`` -- the kick right after that zeroing, which ur_rtde holds
    until the program's script is ready for a command again -- is refused only at ur_rtde's ready time-out (3-4 s
    of waiting, stepped here), since a stopped script never gets ready. Returns the controller times of every
    reuploadScript (the driver must not restart what an operator stopped)."""
    zero, kick, upload = c.zeroFtSensor, c.kickWatchdog, c.reuploadScript
    n, uploads = [0], []

    def zeroFtSensor():
        n[0] += 1
        if call == "zeroFtSensor" and n[0] == after_zeros:
            arm.stop_program()
        return zero()

    def kickWatchdog():
        if call == "kickWatchdog" and n[0] == after_zeros and arm.program_running:
            arm.stop_program()
            for _ in range(int(4.0 / arm.period_s)):      # ur_rtde waits for the script's ready state
                arm.step()
            return False
        return kick()

    def reuploadScript():
        uploads.append(arm.t_s)
        return upload()
    c.zeroFtSensor, c.kickWatchdog, c.reuploadScript = zeroFtSensor, kickWatchdog, reuploadScript
    return uploads


@pytest.mark.parametrize("call", ["zeroFtSensor", "kickWatchdog"])
def test_operator_stop_racing_a_call_is_program_stopped(tmp_path, call):
    """The fault drill program-stop-rest through the real client on a loaded machine (app/faultdrill.py): the
    operator's stop met a call in flight and was reported as command_failed -- the refused zeroFtSensor was not
    checked against the program's state, and a kick refused after ur_rtde's 4 s wait was judged by the time it came
    back, long enough for the watchdog, so the safe state even uploaded the program again. It is program_stopped,
    and the program stays stopped: the motion stopped, the records kept, no retract (no program to run one)."""
    arm, c, r = make_sim()
    uploads = _operator_stop_in_flight(arm, c, call)
    rep = run(tmp_path, c, r, config=DriverConfig(fast_forward=False))    # every period's kick through ur_rtde
    check_safe_end(rep, arm, tmp_path, "program_stopped", retracted=False)
    assert uploads == [] and rep.program_restarts == 0 and not arm.program_running, uploads
    assert "not by its watchdog" in rep.fault["message"]


def test_watchdog_stop_met_by_a_kick_is_not_taken_for_an_operator(tmp_path):
    """The other side of the test above: the host held up for 0.5 s at rest just before a kick (probe 1's zeroing),
    so the watchdog did end the program; the refused kick cannot be an operator's stop, and the safe state uploads
    the program again (as between probes) and checks the tip."""
    arm, c, r = make_sim()
    zero, kick, n = c.zeroFtSensor, c.kickWatchdog, [0]

    def zeroFtSensor():
        n[0] += 1
        return zero()

    def kickWatchdog():
        if n[0] == 3 and arm.program_running:
            for _ in range(int(0.5 / arm.period_s)):      # no input from the host meanwhile
                arm.step()
        return kick()
    c.zeroFtSensor, c.kickWatchdog = zeroFtSensor, kickWatchdog
    rep = run(tmp_path, c, r, config=DriverConfig(fast_forward=False))
    assert arm.watchdog_fired_s is not None
    assert rep.fault["kind"] == "command_failed" and "kickWatchdog" in rep.fault["message"], rep.fault
    assert rep.program_restarts == 1 and rep.fault["retracted"] and not arm.is_moving


def test_transient_disconnect_reconnects_and_retracts(tmp_path):
    arm, c, r = make_sim()
    arm.inject("disconnect", when=at_probe(1, 0.001), reconnectable=True)
    rep = run(tmp_path, c, r)
    check_safe_end(rep, arm, tmp_path, "connection_lost", retracted=True)
    assert rep.fault["stopped"]


class LostLinkReceive(SimRTDEReceive):
    """ur_rtde 1.6.5 when the controller goes away: the getters keep returning the last values (no exception) and
    isConnected() turns False."""

    def __init__(self, arm):
        super().__init__(arm)
        self.last = {}

    def _get(self, fn):
        key = sys._getframe(1).f_code.co_name
        if self.arm.connected:
            self.last[key] = super()._get(fn)
        return self.last[key]


class LostLinkControl(SimRTDEControl):
    """... and a command sent then may block for good: here any command after the loss fails the test."""

    def __init__(self, arm):
        super().__init__(arm)
        self.progress, self.reconnect_at = -1, []

    def _link(self):
        if not self.arm.connected:
            raise AssertionError("a command was sent while ur_rtde reports no connection (it could block for good)")

    def getAsyncOperationProgress(self):
        if self.arm.connected:
            self.progress = super().getAsyncOperationProgress()
        return self.progress

    def reconnect(self):
        self.reconnect_at.append(self.arm.t_s)
        return super().reconnect()


def test_lost_link_as_ur_rtde_sees_it_sends_no_command(tmp_path):
    """Stale data with isConnected() False is a lost connection (not a time-out); the fault record is on disk; no
    command is sent while the link is down, and reconnect() is tried only after ``reconnect_after_s``."""
    arm, _, _ = make_sim()
    c, r = LostLinkControl(arm), LostLinkReceive(arm)
    arm.inject("disconnect", when=at_probe(1, 0.001))
    rep = run(tmp_path, c, r)
    assert "no connection" in rep.fault["message"]
    check_safe_end(rep, arm, tmp_path, "connection_lost", retracted=False)
    assert not rep.fault["stopped"] and "no command sent" in " ".join(rep.fault["notes"])
    assert len(c.reconnect_at) == 1 and c.reconnect_at[0] - arm.faults[0]["fired_s"] >= DriverConfig().reconnect_after_s
    assert arm.tip_in_tissue()[1] <= DEPTH + 1e-9        # the bounded moveL ended the motion


def test_force_spike_stops_and_retracts_then_continues(tmp_path):
    arm, c, r = make_sim()
    arm.inject("force_spike", when=at_probe(1, DEPTH - 1e-6), magnitude_n=5.0, duration_s=0.05)
    rep = run(tmp_path, c, r)
    assert rep.status == "ok" and rep.n_ok == 2 and rep.n_force_limit == 1
    rec = [x for x in rep.records if x.index == 1][0]
    assert rec.status == "force_limit" and rec.force_peak_n > 2.0
    assert not arm.is_moving and arm.tip_in_tissue()[1] < 0
    assert arm.max_contact_force_n < 1.0                   # a sensor spike: the tissue itself was never overloaded
    rep2 = run(tmp_path, c, r)                             # resume re-probes only the force-limited one
    assert rep2.n_ok == 1 and rep2.n_skipped == 2


def test_nan_reading_is_a_fault(tmp_path):
    arm, c, r = make_sim()
    arm.inject("nan", when=at_probe(1, 0.002), duration_s=0.01)
    rep = run(tmp_path, c, r)
    check_safe_end(rep, arm, tmp_path, "invalid_reading")
    resume_and_check(tmp_path, c, r, 1)


def test_stalled_move_times_out(tmp_path):
    arm, c, r = make_sim()
    arm.inject("stall", when=at_probe(1, 0.001))
    rep = run(tmp_path, c, r)
    check_safe_end(rep, arm, tmp_path, "timeout")
    resume_and_check(tmp_path, c, r, 1)


class FrozenReceive(SimRTDEReceive):
    """Controller data stop updating (timestamp frozen) after t_s."""

    def __init__(self, arm, t_s):
        super().__init__(arm)
        self.t_s, self.frozen = t_s, None

    def getTimestamp(self):
        t = super().getTimestamp()
        if t >= self.t_s:
            self.frozen = self.frozen if self.frozen is not None else t
            return self.frozen
        return t


def test_silent_link_sends_no_command_and_the_watchdog_stops_the_arm(tmp_path):
    """Controller data stale while ur_rtde still reports a connection (a partition or a frozen controller): the record
    is written first, and no command follows (a stopL would wait for ur_rtde's 300 s time-out on a real link); the
    controller's watchdog, no longer kicked, stops the motion."""
    arm, c, _ = make_sim()
    calls = []
    for name in ("stopL", "moveL", "reconnect", "zeroFtSensor"):
        def spy(*a, _f=getattr(c, name), _n=name, **k):
            calls.append((_n, arm.t_s))
            return _f(*a, **k)
        setattr(c, name, spy)
    rep = run(tmp_path, c, FrozenReceive(arm, 7.0))
    assert rep.status == "fault" and rep.fault["kind"] == "connection_lost", rep.fault
    assert "stopped updating" in rep.fault["message"] and "silent link" in " ".join(rep.fault["notes"])
    assert not arm.is_moving and rep.n_ok == 1
    assert not [cl for cl in calls if cl[1] > 7.0 + 0.2], calls     # nothing sent once the data went stale
    recs = read_records(tmp_path)
    assert recs[-1].status == "fault" and recs[-1].index == 1          # the interrupted probe is on disk


class InterruptingReceive(SimRTDEReceive):
    def __init__(self, arm, when):
        super().__init__(arm)
        self.when, self.fired = when, False

    def getActualTCPForce(self):
        if not self.fired and self.when(self.arm):
            self.fired = True
            raise KeyboardInterrupt
        return super().getActualTCPForce()


def test_ctrl_c_stops_and_retracts(tmp_path):
    arm, c, _ = make_sim()
    rep = run(tmp_path, c, InterruptingReceive(arm, at_probe(1, 0.002)))
    assert rep.status == "interrupted" and rep.fault["kind"] == "interrupted"
    assert rep.fault["stopped"] and rep.fault["retracted"] and not arm.is_moving
    assert arm.tip_in_tissue()[1] < 0
    recs = read_records(tmp_path)
    assert [x.status for x in recs] == ["ok", "interrupted"]
    resume_and_check(tmp_path, c, SimRTDEReceive(arm), 1)


def test_builtin_sensor_refused_at_2n_limit(tmp_path):
    arm, c, r = make_sim(sensor="ur5e-builtin")
    rep = run(tmp_path, c, r)
    assert rep.status == "fault" and rep.fault["kind"] == "sensor_noise"
    assert arm.max_contact_force_n == 0.0 and rep.fault["retracted"]        # never touched the tissue


def test_torn_last_line_is_ignored(tmp_path):
    arm, c, r = make_sim()
    assert run(tmp_path, c, r).status == "ok"
    with open(tmp_path / "probes.jsonl", "a") as f:
        f.write('{"index": 1, "status": "fa')                # a crash mid-write
    assert done_indices(tmp_path) == {0, 1, 2}


@pytest.mark.parametrize("method", ["zeroFtSensor", "setTcp", "moveL"])
def test_false_returns_are_faults(tmp_path, method):
    arm, c, r = make_sim()
    orig = getattr(c, method)
    calls = []

    def failing(*a, **k):
        calls.append(1)
        return False if len(calls) == 2 or method == "setTcp" else orig(*a, **k)
    setattr(c, method, failing)
    rep = run(tmp_path, c, r)
    assert rep.status == "fault" and rep.fault["kind"] == "command_failed" and method in rep.fault["message"]
    assert not arm.is_moving


@pytest.mark.realtime          # wall-clock: run on its own (tests/conftest.py)
def test_unanswered_command_is_bounded_and_nothing_follows(tmp_path, monkeypatch):
    """A command that never gets its answer (the link went silent just as it was sent: ur_rtde would wait up to its
    300 s execution time-out) is abandoned after its deadline; the interrupted probe is recorded, no further command
    is sent on that link, and the controller's watchdog, no longer kicked, stops the motion."""
    import threading
    import time

    from robot import link

    monkeypatch.setattr(link, "COMMAND_TIMEOUT_S", 0.5)
    arm, c, r = make_sim()
    hang, sent = threading.Event(), []
    real_move = c.moveL

    def move(pose, *a):
        sent.append(("moveL", arm.t_s))
        if sum(s[0] == "moveL" for s in sent) == 4:     # probe 1's approach: no answer, ever (until the test ends)
            hang.wait(30)
        return real_move(pose, *a)
    c.moveL = move
    for name in ("stopL", "zeroFtSensor", "reconnect", "setTcp", "setWatchdog"):
        def spy(*a, _f=getattr(c, name), _n=name):
            sent.append((_n, arm.t_s))
            return _f(*a)
        setattr(c, name, spy)
    w0 = time.monotonic()
    try:
        rep = run(tmp_path, c, r)
    finally:
        hang.set()
    assert time.monotonic() - w0 < 10.0
    assert rep.status == "fault" and rep.fault["kind"] == "connection_lost", rep.fault
    assert "got no answer within 0.5 s" in rep.fault["message"]
    assert not rep.fault["stopped"] and "a command got no answer" in " ".join(rep.fault["notes"])
    n_at_hang = [i for i, s in enumerate(sent) if s[0] == "moveL"][3]
    assert sent[n_at_hang + 1:] == [], sent[n_at_hang:]          # nothing sent after the unanswered moveL
    assert not arm.is_moving and arm.watchdog_fired_s is not None  # the unkicked watchdog ended the program
    recs = read_records(tmp_path)
    assert [(x.index, x.status) for x in recs] == [(0, "ok"), (1, "fault")]
