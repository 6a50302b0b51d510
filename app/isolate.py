"""Run the part of a command that holds the vendor client (ur_rtde) in a child process.

ur_rtde 1.6.5 can crash its process (SIGSEGV in its own reconnect threads, seen when a link drops and it reconnects
by itself) and leaves threads behind that may block at interpreter exit. The robot-cell script therefore keeps the
link in a forked child: the driver writes every record to disk as it goes, and if the child dies the parent still
reports what happened, from those files, and exits with a fault instead of a crash.
"""
from __future__ import annotations

import multiprocessing as mp
import signal
import traceback


class ChildDied(RuntimeError):
    """The child ended without a result (killed by a signal, or exited)."""

    def __init__(self, exitcode: int | None):
        self.exitcode = exitcode
        if exitcode is not None and exitcode < 0:
            try:
                name = signal.Signals(-exitcode).name
            except ValueError:
                name = f"signal {-exitcode}"
            what = f"killed by {name}"
        else:
            what = f"exited with code {exitcode} without a result"
        super().__init__(f"the process holding the arm's link was {what}")


class ChildError(RuntimeError):
    """An exception in the child: its type name, message and traceback text (exceptions may not pickle)."""

    def __init__(self, type_name: str, message: str, trace: str):
        super().__init__(message)
        self.type_name, self.trace = type_name, trace


def _child(conn, fn, args):
    signal.signal(signal.SIGINT, signal.default_int_handler)   # Ctrl-C reaches the driver (it records, stops)
    try:
        conn.send(("ok", fn(*args)))
    except BaseException as e:            # noqa: BLE001 -- every outcome goes back to the parent
        conn.send(("error", (type(e).__name__, str(e), traceback.format_exc())))
    finally:
        conn.close()
    # multiprocessing ends a forked child with os._exit: threads ur_rtde leaves behind cannot hold up the exit


def run_in_child(fn, *args):
    """``fn(*args)`` in a forked child; its return value (picklable), or ChildError for an exception it raised, or
    ChildDied if it died. Ctrl-C is left to the child (the parent ignores it while waiting)."""
    ctx = mp.get_context("fork")
    parent_end, child_end = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(child_end, fn, args), daemon=False)
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        proc.start()
        child_end.close()
        try:
            kind, value = parent_end.recv()
        except EOFError:
            proc.join()
            raise ChildDied(proc.exitcode) from None
        proc.join()
    finally:
        signal.signal(signal.SIGINT, old)
    if kind == "error":
        raise ChildError(*value)
    return value
