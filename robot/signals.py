"""Signals around the arm's motion: a supervisor's SIGTERM is a Ctrl-C, and neither may cut the safe stop short.

``SignalGate`` (``with SignalGate() as gate:`` around a run, main thread only; elsewhere it does nothing): SIGINT
raises KeyboardInterrupt, and so does SIGTERM (systemd's stop, ``kill``) unless someone other than Python's default
handler (app.isolate's child installs that one) handles it already. The first signal that raises closes the gate, and
so does ``gate.hold()`` (the driver's fault handler, first thing): from then on a signal is only noted
(``gate.held``), so nothing cuts the safe stop short. The handlers are restored on leaving, with both signals blocked
meanwhile (a signal between two restores must not leave the other one's handler noting for good).
"""
from __future__ import annotations

import signal
import threading

NAMES = {signal.SIGINT: "Ctrl-C (SIGINT)", signal.SIGTERM: "SIGTERM"}


class SignalGate:
    def __init__(self):
        self.held: list[str] = []
        self.holding = False
        self._old: dict = {}

    def hold(self) -> None:
        self.holding = True

    def _handler(self, signum, frame):
        if self.holding:
            self.held.append(NAMES[signum])
            return
        self.holding = True                  # the first raises; any later one waits for the safe stop
        raise KeyboardInterrupt("SIGTERM" if signum == signal.SIGTERM else "")

    def __enter__(self) -> "SignalGate":
        if threading.current_thread() is not threading.main_thread():
            return self
        for n in NAMES:
            old = signal.getsignal(n)
            if n == signal.SIGTERM and old not in (signal.SIG_DFL, signal.default_int_handler):
                continue                     # someone's own SIGTERM handling stands
            self._old[n] = old
            signal.signal(n, self._handler)
        return self

    def __exit__(self, *exc) -> None:
        if not self._old:
            return
        blocked = set(self._old)
        signal.pthread_sigmask(signal.SIG_BLOCK, blocked)
        try:
            for n, h in self._old.items():
                signal.signal(n, signal.SIG_DFL if h is None else h)     # None: a handler set outside Python
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, blocked)
