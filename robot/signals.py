"""Signals around the arm's motion: a supervisor's SIGTERM is a Ctrl-C, and neither may cut the safe stop short.

``terminate_as_interrupt()``: while the driver runs, SIGTERM (systemd's stop, ``kill``) raises KeyboardInterrupt as
Ctrl-C does, so the driver records the probe, stops and retracts instead of the process dying with the tip in
tissue. ``deferred_signals()``: while the driver brings the arm to its safe state, a second Ctrl-C or a SIGTERM is
noted (the yielded list names them) instead of raised. Both act in the main thread only (Python runs signal
handlers there); elsewhere they change nothing.
"""
from __future__ import annotations

import contextlib
import signal
import threading

NAMES = {signal.SIGINT: "Ctrl-C (SIGINT)", signal.SIGTERM: "SIGTERM"}


def _terminate(signum, frame):
    raise KeyboardInterrupt("SIGTERM")


def _main() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextlib.contextmanager
def terminate_as_interrupt():
    if not _main():
        yield
        return
    old = signal.getsignal(signal.SIGTERM)
    if old is not signal.SIG_DFL:               # someone (app.isolate's child, or outside Python) handles it
        yield
        return
    signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


@contextlib.contextmanager
def deferred_signals():
    held: list[str] = []
    if not _main():
        yield held
        return
    old = {n: signal.getsignal(n) for n in NAMES}
    for n in NAMES:
        signal.signal(n, lambda signum, frame: held.append(NAMES[signum]))
    try:
        yield held
    finally:
        for n, h in old.items():
            signal.signal(n, signal.SIG_DFL if h is None else h)     # None: a handler set outside Python
