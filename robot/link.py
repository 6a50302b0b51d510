"""The real ur_rtde link: connect and disconnect (the driver takes whatever interfaces it is given)."""
from __future__ import annotations


def connect(host: str):
    """The real ur_rtde interfaces (receive first: it does not upload a program)."""
    import rtde_control  # the compiled client, loaded only when a link is made
    import rtde_receive
    r = rtde_receive.RTDEReceiveInterface(host)
    try:
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
