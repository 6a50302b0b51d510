"""``fork_map(fn, items, workers)``: ``[fn(x) for x in items]``, shared with forked copies of this process.

The localizer's independent fits (its starts, the depth profile's points) take most of a simulated run's second
half while the machine's other core idles. A fork costs a few milliseconds and needs nothing pickled but the
results: a child inherits the fit's closures, models and caches as they are. With ``workers`` = n, child k
(1 <= k < n) computes items k, k + n, k + 2n, ... and the parent items 0, n, 2n, ...; the results come back in the
items' order, so a caller that reduces them in order (the first of the least costs) gets what the serial loop
gets. Each item's result is the same, bit for bit: the same code on the same inputs in the same process image.

A child that cannot be forked, fails, is killed or gives no answer within CHILD_TIMEOUT_S of the parent's own share
costs time only: the parent computes its items itself. When items raise, an exception propagates, though not
necessarily the one of the first failing item (the parent's own items are computed before the children's are
read). An exception or Ctrl-C in the parent kills and reaps the children; a child never runs the caller's code,
atexit handlers or buffered output (it ends with ``os._exit`` whatever happens, Ctrl-C included), and on Linux it
dies with the parent. ``workers`` below 2, fewer than two items, or no ``os.fork`` (Windows): the plain loop.

Only a simulated run asks for more than one worker (app.commands.run, ``--fit-workers``): a process driving a real
arm holds ur_rtde's threads and sockets, which a fork would copy.
"""
from __future__ import annotations

import ctypes
import os
import pickle
import select
import signal
import time
import warnings
from collections.abc import Callable, Iterable
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

CHILD_TIMEOUT_S = 60.0      # a child's answer after the parent's share is done (a fit takes 10-100 ms)
_SIGNALS = {signal.SIGINT, signal.SIGTERM}
# Python 3.12+ warns on any fork of a process with threads (the run has its call worker's); the child runs numpy
# code only, then _exit (a filter for this module's forks only: catch_warnings would reset the registries)
warnings.filterwarnings("ignore", message=r"This process .* is multi-threaded, use of fork\(\)",
                        category=DeprecationWarning, module=__name__)


def fork_map(fn: Callable[[T], R], items: Iterable[T], workers: int = 1) -> list[R]:
    items = list(items)
    n = min(int(workers), len(items))
    if n < 2 or not hasattr(os, "fork"):
        return [fn(x) for x in items]
    children: dict[int, tuple[int, int]] = {}           # k -> (pid, read end), while not yet collected
    out: list = [None] * len(items)
    try:
        for k in range(1, n):
            _fork(fn, items[k::n], children, k)
        out[0::n] = [fn(x) for x in items[0::n]]
        for k in range(1, n):
            got = _collect(*children.pop(k)) if k in children else None    # (it closes and reaps, come what may)
            if got is None or len(got) != len(items[k::n]):
                got = [fn(x) for x in items[k::n]]
            out[k::n] = got
    except BaseException:
        for pid, r in children.values():
            _close(r)
            _end(pid, kill=True)
        raise
    return out


def _fork(fn, mine: list, children: dict, k: int) -> None:
    """Fork a child computing ``[fn(x) for x in mine]`` into a pipe; ``children[k]`` = (its pid, the read end).
    Nothing recorded when no pipe or fork can be had. Ctrl-C and SIGTERM are held while the child is made, and a
    child leaves through ``os._exit`` from anywhere (an interrupt pending from before the fork included)."""
    r = w = pid = -1
    code, done = 1, False
    old = signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
    try:
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:                            # the child: its items, pickled into the pipe, then gone
            for s in _SIGNALS:                  # an interrupt now ends it quietly (the parent recomputes)
                signal.signal(s, signal.SIG_DFL)
            _die_with_parent()
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
            os.close(r)
            data = pickle.dumps([fn(x) for x in mine], protocol=pickle.HIGHEST_PROTOCOL)
            with os.fdopen(w, "wb") as f:
                f.write(data)
            code = 0
        else:
            os.close(w)
            w = -1
            children[k] = (pid, r)
            done = True
    except OSError:                             # no pipe or no fork: the parent computes these items
        pass
    finally:
        if pid == 0:
            os._exit(code)                      # no atexit handlers, no flushing of the parent's buffers
        if not done:
            _close(r)
            _close(w)
            if pid > 0:
                _end(pid, kill=True)
        signal.pthread_sigmask(signal.SIG_SETMASK, old)     # (an interrupt held meanwhile is raised now)


def _die_with_parent() -> None:
    """Linux: SIGKILL to this child when its parent dies (a killed run leaves no fits computing)."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)      # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _collect(pid: int, r: int) -> list | None:
    """A child's results (None: it failed, died, timed out or sent something unreadable); the child is reaped."""
    chunks, deadline, ok = [], time.monotonic() + CHILD_TIMEOUT_S, False
    try:
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([r], [], [], left)[0]:
                break                           # no answer in time
            chunk = os.read(r, 1 << 16)
            if not chunk:
                ok = True
                break
            chunks.append(chunk)
    finally:
        _close(r)
        ok = _end(pid, kill=not ok) and ok
    if not ok:
        return None
    try:
        return pickle.loads(b"".join(chunks))
    except Exception:                           # noqa: BLE001 -- garbled: the parent computes those items
        return None


def _close(fd: int) -> None:
    if fd >= 0:
        try:
            os.close(fd)
        except OSError:
            pass


def _end(pid: int, kill: bool) -> bool:
    """Reap the child (killed first when ``kill``); whether it exited 0."""
    if kill:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    try:
        _, status = os.waitpid(pid, 0)
    except ChildProcessError:
        return False
    return os.waitstatus_to_exitcode(status) == 0
