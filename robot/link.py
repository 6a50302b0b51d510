"""The real ur_rtde link: connect and disconnect (the driver takes whatever interfaces it is given)."""
from __future__ import annotations

import threading

ROBOT_MODE_RUNNING = 7          # ur_rtde getRobotMode(): powered on, brakes released
COMMAND_TIMEOUT_S = 2.0         # a command ur_rtde sends waits for the controller's answer (a few ms on a live link)
SLOW_COMMAND_TIMEOUT_S = 10.0   # reuploadScript, reconnect, stopScript: ur_rtde's own waits are up to 5 s
# ur_rtde calls that wait for the controller (each is bounded with call_within); the getters return the last values
# received and initPeriod/waitPeriod are local, so those never block
# kickWatchdog is made directly, every period, and only while the controller's data are fresh: through a worker it
# would cost 60 us median and over 1.5 ms at the 99th percentile on a busy 2-core machine, a period's budget; on a
# link that dies inside that one period it is bounded by ur_rtde's own ready time-out (a few seconds).
# KICK_BOUND_S: that bound, ur_rtde's UR_GET_READY_TIMEOUT (3 s) and one reconnect attempt (measured 4.0 s once in a
# partition drill, 2026-11-26); meanwhile no kick reaches the controller, whose RTDE watchdog stops the arm.
KICK_BOUND_S = 5.0
# ur_rtde 1.6.5's UR_GET_READY_TIMEOUT: a command or kick first waits for the control script's "ready for a command"
# state, which a running script shows again a cycle after the previous command's end; the wait ends in a refusal
# only after this (4 s: ur_rtde counts whole seconds), e.g. when the program stops in that cycle. A refusal for a
# program already stopped comes at once.
UR_READY_TIMEOUT_S = 3.0
BLOCKING_CALLS = frozenset({"moveL", "moveJ", "stopL", "stopJ", "speedStop", "zeroFtSensor", "setTcp", "setPayload",
                            "setWatchdog", "reuploadScript", "reconnect", "stopScript", "disconnect",
                            "triggerProtectiveStop"})
SLOW_CALLS = frozenset({"reuploadScript", "reconnect", "stopScript"})


class CallTimeout(RuntimeError):
    """A ur_rtde call got no answer within its deadline (a silent link); the call may still be pending."""


def call_within(fn, args=(), timeout_s: float = COMMAND_TIMEOUT_S):
    """``fn(*args)`` with a deadline: ur_rtde 1.6.5 waits up to its 300 s execution time-out for a controller that
    does not answer (a partition, a frozen controller). The call runs in a daemon thread (ur_rtde releases the GIL
    while it waits); past ``timeout_s`` CallTimeout is raised and the thread is abandoned. Exceptions pass through."""
    box: dict = {}

    def run():
        try:
            box["value"] = fn(*args)
        except BaseException as e:        # noqa: BLE001 -- handed to the caller
            box["error"] = e
    t = threading.Thread(target=run, daemon=True, name=f"ur_rtde-{getattr(fn, '__name__', 'call')}")
    t.start()
    t.join(timeout_s)
    if t.is_alive():
        raise CallTimeout(f"{getattr(fn, '__name__', fn)} got no answer within {timeout_s:g} s")
    if "error" in box:
        raise box["error"]
    return box.get("value")


class CallWorker:
    """One long-lived thread that makes every waiting ur_rtde call of a link, one at a time (the client is not
    thread-safe), each with a deadline: ``call(fn, args, timeout_s)``. Cheaper than a thread per call (the watchdog
    is kicked every 2 ms). After a call that got no answer the worker is stuck in it: every later call raises
    CallTimeout at once, so nothing is queued behind it."""

    def __init__(self):
        self._lock = threading.Lock()
        self._job = None
        self._have_job = threading.Event()
        self._stuck: str = ""
        self._thread = threading.Thread(target=self._run, daemon=True, name="ur_rtde-calls")
        self._thread.start()

    def _run(self):
        while True:
            self._have_job.wait()
            self._have_job.clear()
            fn, args, box, done = self._job
            try:
                box["value"] = fn(*args)
            except BaseException as e:        # noqa: BLE001 -- handed to the caller
                box["error"] = e
            done.set()

    def call(self, fn, args=(), timeout_s: float = COMMAND_TIMEOUT_S):
        with self._lock:
            if self._stuck:
                raise CallTimeout(f"{getattr(fn, '__name__', fn)} not sent: {self._stuck}")
            box: dict = {}
            done = threading.Event()
            self._job = (fn, args, box, done)
            self._have_job.set()
            if not done.wait(timeout_s):
                self._stuck = f"{getattr(fn, '__name__', fn)} got no answer within {timeout_s:g} s"
                raise CallTimeout(self._stuck)
        if "error" in box:
            raise box["error"]
        return box.get("value")


def deadline_for(name: str) -> float | None:
    """The deadline for a ur_rtde call by name (None: it does not block)."""
    if name not in BLOCKING_CALLS:
        return None
    return SLOW_COMMAND_TIMEOUT_S if name in SLOW_CALLS else COMMAND_TIMEOUT_S


class ArmNotReady(RuntimeError):
    """The arm cannot take a program now; the message says what the operator must do on the pendant."""


def check_ready(r) -> None:
    """Before uploading a program (which ur_rtde reports only as "Failed to start control script"): the arm must be
    out of emergency and protective stop, powered on, brakes released."""
    if r.isEmergencyStopped():
        raise ArmNotReady("the arm is emergency-stopped: release the emergency stop, power on and release the brakes "
                          "on the pendant, then run the same command again (finished probes are kept)")
    if r.isProtectiveStopped():
        raise ArmNotReady("the arm is protective-stopped: clear the stop on the pendant (or the dashboard's "
                          "'unlock protective stop'), check the tissue and the tip, then run the same command again "
                          "to resume (finished probes are kept; the driver first retracts along the tissue normal)")
    mode = r.getRobotMode()
    if mode != ROBOT_MODE_RUNNING:
        raise ArmNotReady(f"the arm's robot mode is {mode}, not running ({ROBOT_MODE_RUNNING}): power it on and "
                          f"release the brakes on the pendant, then run the same command again")


LOCAL_CONTROL = ("the arm is in local control: switch the pendant to remote control (the icon at its top right), "
                 "then run the same command again to resume (finished probes are kept)")


def remote_control(host: str) -> bool | None:
    """Whether the arm is in remote control, from its dashboard server (ur_rtde's DashboardClient), within
    COMMAND_TIMEOUT_S; None when that cannot be told (no answer, PolyScope < 5.6)."""
    import dashboard_client  # the compiled client, loaded only when a link is made

    def ask():
        db = dashboard_client.DashboardClient(host)
        db.connect(int(COMMAND_TIMEOUT_S * 1000))
        try:
            return bool(db.isInRemoteControl())
        finally:
            db.disconnect()
    try:
        return call_within(ask, (), 2 * COMMAND_TIMEOUT_S)
    except RuntimeError:           # CallTimeout, a refused connection, an old PolyScope
        return None


def dashboard_stop(host: str) -> bool:
    """Stop the control program through the dashboard server (ur_rtde's DashboardClient) within COMMAND_TIMEOUT_S:
    always safe, and the one way left when the client itself is gone. True if the dashboard answered."""
    import dashboard_client  # the compiled client, loaded only when a link is made

    def stop():
        db = dashboard_client.DashboardClient(host)
        db.connect(int(COMMAND_TIMEOUT_S * 1000))
        try:
            db.stop()
            return True
        finally:
            db.disconnect()
    try:
        return call_within(stop, (), 2 * COMMAND_TIMEOUT_S) is True
    except RuntimeError:
        return False


def connect(host: str):
    """The real ur_rtde interfaces (receive first: it does not upload a program; the arm's state -- e-stop,
    protective stop, power, remote control -- is checked before the control interface uploads one)."""
    import rtde_control  # the compiled client, loaded only when a link is made
    import rtde_receive
    r = rtde_receive.RTDEReceiveInterface(host)
    try:
        check_ready(r)
        if remote_control(host) is False:
            raise ArmNotReady(LOCAL_CONTROL)
        c = rtde_control.RTDEControlInterface(host)
    except RuntimeError:
        r.disconnect()
        raise
    return c, r


def receive_once(started, host: str) -> None:
    """Open and close ur_rtde's receive interface to ``host`` (it uploads no program): whether the controller
    answers, run in a child process that is killed at a deadline (app.runexec.answers); ``started()`` once it has."""
    import rtde_receive  # the compiled client, loaded only when a link is made
    r = rtde_receive.RTDEReceiveInterface(host)
    started()
    disconnect(r)


def disconnect(*interfaces) -> None:
    """Close ur_rtde interfaces that are still connected, each within COMMAND_TIMEOUT_S (ur_rtde 1.6.5: a call
    after a failed reconnect may block, so a lost link is left alone; the process's exit closes what is left)."""
    for iface in interfaces:
        try:
            if iface.isConnected():
                call_within(iface.disconnect, (), COMMAND_TIMEOUT_S)
        except RuntimeError:        # CallTimeout included: the process ends anyway
            pass


def end_session(c, r, clean: bool) -> None:
    """End a session with the arm: after a clean run (the arm at rest, the link healthy) stop the control script, so
    the program does not run on until its watchdog ends it; then disconnect both interfaces. After a fault only
    disconnect: a command on a bad link can block."""
    if clean:
        try:
            if c.isConnected():
                call_within(c.stopScript, (), SLOW_COMMAND_TIMEOUT_S)
        except RuntimeError:
            pass
    disconnect(c, r)
