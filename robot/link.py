"""The real ur_rtde link: connect and disconnect (the driver takes whatever interfaces it is given)."""
from __future__ import annotations

ROBOT_MODE_RUNNING = 7          # ur_rtde getRobotMode(): powered on, brakes released


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


def connect(host: str):
    """The real ur_rtde interfaces (receive first: it does not upload a program; the arm's state is checked before
    the control interface uploads one)."""
    import rtde_control  # the compiled client, loaded only when a link is made
    import rtde_receive
    r = rtde_receive.RTDEReceiveInterface(host)
    try:
        check_ready(r)
        c = rtde_control.RTDEControlInterface(host)
    except RuntimeError:
        r.disconnect()
        raise
    return c, r


def disconnect(*interfaces) -> None:
    """Close ur_rtde interfaces that are still connected (ur_rtde 1.6.5: a call after a failed reconnect may block,
    so a lost link is left alone)."""
    for iface in interfaces:
        try:
            if iface.isConnected():
                iface.disconnect()
        except RuntimeError:
            pass


def end_session(c, r, clean: bool) -> None:
    """End a session with the arm: after a clean run (the arm at rest, the link healthy) stop the control script, so
    the program does not run on until its watchdog ends it; then disconnect both interfaces. After a fault only
    disconnect: a command on a bad link can block."""
    if clean:
        try:
            if c.isConnected():
                c.stopScript()
        except RuntimeError:
            pass
    disconnect(c, r)
