"""Run the part of a command that holds the vendor client (ur_rtde) in a child process.

ur_rtde 1.6.5 can crash its process (SIGSEGV in its own reconnect threads, seen when a link drops and it reconnects
by itself) and leaves threads behind that may block at interpreter exit. The robot-cell script therefore keeps the
link in a forked child: the driver writes every record to disk as it goes, and if the child dies the parent still
reports what happened, from those files, and exits with a fault instead of a crash.
"""
from __future__ import annotations

import ctypes
import multiprocessing as mp
import os
import signal
import traceback

PR_SET_PDEATHSIG = 1


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


class ChildTimeout(RuntimeError):
    """The child did not report its start within the deadline; it was killed."""


def _die_with_parent() -> None:
    """Linux: SIGINT to this process when its parent dies (the driver then records, stops and ends), so a run is
    never left going with nobody to report it."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGINT)
    except (OSError, AttributeError):
        pass


def _child(conn, fn, args):
    # a process group of its own (first: a terminal's Ctrl-C must not reach both this process and, passed on, the
    # parent's copy): a terminal's Ctrl-C (sent to the foreground group) reaches the parent only, which passes a
    # SIGINT on, as it does a SIGINT or SIGTERM sent to its process ID alone. A background group's output or input
    # on the terminal would stop it (SIGTTOU with `stty tostop`, SIGTTIN): ignored, so it writes on (a read fails)
    _own_group()
    signal.signal(signal.SIGTTOU, signal.SIG_IGN)
    signal.signal(signal.SIGTTIN, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.default_int_handler)   # Ctrl-C reaches the driver (it records, stops)
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # so does a supervisor's SIGTERM
    _die_with_parent()
    try:
        conn.send(("ok", fn(lambda: conn.send(("started", None)), *args)))
    except BaseException as e:            # noqa: BLE001 -- every outcome goes back to the parent
        conn.send(("error", (type(e).__name__, str(e), traceback.format_exc())))
    finally:
        conn.close()
    # multiprocessing ends a forked child with os._exit: threads ur_rtde leaves behind cannot hold up the exit


def _own_group(pid: int = 0) -> None:
    try:
        os.setpgid(pid, pid)
    except OSError:          # (the child's own call came first, or it has already ended)
        pass


def run_in_child(fn, *args, start_timeout_s: float | None = None, start_method: str = "fork"):
    """``fn(started, *args)`` in a forked child; its return value (picklable), or ChildError for an exception it
    raised, or ChildDied if it died. ``fn`` calls ``started()`` once its unbounded start is over (ur_rtde's
    constructors have no time-out of their own against a controller that accepts but never answers); without that
    within ``start_timeout_s`` the child is killed and ChildTimeout raised. The child runs in a process group of its
    own; a SIGINT or SIGTERM to the parent (a terminal's Ctrl-C too) is passed on to it as one SIGINT.
    ``start_method`` "spawn": a fresh interpreter (``fn`` must then be importable by name), for a caller whose other
    threads may hold locks a forked child would inherit held."""
    ctx = mp.get_context(start_method)
    parent_end, child_end = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(child_end, fn, args), daemon=False)
    # Ctrl-C, and a supervisor's SIGINT or SIGTERM to this process, reach the child as Ctrl-C: it records and stops
    # (before session 45 a SIGINT to this process alone was ignored: only a terminal's, sent to the whole group,
    # stopped the arm). One SIGINT passed on for each received; installed before the child starts, one received
    # before it has started is passed on once it has
    early = []

    def forward(*_):
        if proc.pid is None:
            early.append(True)
        elif proc.is_alive():
            os.kill(proc.pid, signal.SIGINT)
    old = signal.signal(signal.SIGINT, forward)
    old_term = signal.signal(signal.SIGTERM, forward)
    try:
        proc.start()
        _own_group(proc.pid)        # (as the child does: whichever runs first)
        if early:
            forward()
        child_end.close()
        if start_timeout_s is not None and not parent_end.poll(start_timeout_s):
            proc.kill()
            proc.join()
            raise ChildTimeout(f"no start within {start_timeout_s:g} s")
        try:
            kind, value = parent_end.recv()
            while kind == "started":
                kind, value = parent_end.recv()
        except EOFError:
            proc.join()
            raise ChildDied(proc.exitcode) from None
        proc.join()
    finally:
        signal.signal(signal.SIGINT, old)
        signal.signal(signal.SIGTERM, old_term)
    if kind == "error":
        raise ChildError(*value)
    return value
