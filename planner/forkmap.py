"""``fork_map(fn, items, workers)``: ``[fn(x) for x in items]``, shared with forked copies of this process.

The localizer's independent fits (its starts, the depth profile's points) take most of a simulated run's second
half while the machine's other core idles. A fork costs a few milliseconds and needs nothing pickled but the
results: a child inherits the fit's closures, models and caches as they are. With ``workers`` = n, child k
(1 <= k < n) computes items k, k + n, k + 2n, ... and the parent items 0, n, 2n, ...; the results come back in the
items' order, so a caller that reduces them in order (the first of the least costs) gets what the serial loop
gets. Each item's result is the same, bit for bit: the same code on the same inputs in the same process image.

A child that cannot be forked, fails or is killed costs time only: the parent computes its items itself (an item
that raises there raises as the loop would). An exception in the parent's own items kills and reaps the children
and propagates. ``workers`` below 2, fewer than two items, or no ``os.fork`` (Windows): the plain loop.

Only a simulated run asks for more than one worker (app.commands.run, ``--fit-workers``): a process driving a real
arm holds ur_rtde's threads and sockets, which a fork would copy.
"""
from __future__ import annotations

import os
import pickle
import signal
import warnings
from collections.abc import Callable, Iterable
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def fork_map(fn: Callable[[T], R], items: Iterable[T], workers: int = 1) -> list[R]:
    items = list(items)
    n = min(int(workers), len(items))
    if n < 2 or not hasattr(os, "fork"):
        return [fn(x) for x in items]
    children = {k: _fork(fn, items[k::n]) for k in range(1, n)}       # k -> (pid, read end) or None
    out: list = [None] * len(items)
    try:
        out[0::n] = [fn(x) for x in items[0::n]]
        for k in range(1, n):
            child, children[k] = children[k], None
            got = None
            if child is not None:
                try:
                    got = _collect(*child)
                except BaseException:           # (Ctrl-C while waiting for it)
                    _end(child[0], kill=True)
                    raise
            if got is None or len(got) != len(items[k::n]):
                got = [fn(x) for x in items[k::n]]
            out[k::n] = got
    except BaseException:
        for child in children.values():
            if child is not None:
                os.close(child[1])
                _end(child[0], kill=True)
        raise
    return out


def _fork(fn, mine: list) -> tuple[int, int] | None:
    """A child computing ``[fn(x) for x in mine]`` into a pipe: (its pid, the pipe's read end); None if no fork."""
    r, w = os.pipe()
    try:
        with warnings.catch_warnings():         # Python 3.12+: "fork() may lead to deadlocks" with other threads
            warnings.simplefilter("ignore", DeprecationWarning)   # (the child runs numpy code only, then _exit)
            pid = os.fork()
    except OSError:
        os.close(r)
        os.close(w)
        return None
    if pid == 0:                                # the child: its items, pickled into the pipe, then gone
        code = 1
        try:
            os.close(r)
            data = pickle.dumps([fn(x) for x in mine], protocol=pickle.HIGHEST_PROTOCOL)
            with os.fdopen(w, "wb") as f:
                f.write(data)
            code = 0
        finally:
            os._exit(code)                      # no atexit handlers, no flushing of the parent's buffers
    os.close(w)
    return pid, r


def _collect(pid: int, r: int) -> list | None:
    """A child's results (None: it failed, died or sent something unreadable); the child is reaped."""
    with os.fdopen(r, "rb") as f:
        data = f.read()
    if not _end(pid, kill=False):
        return None
    try:
        return pickle.loads(data)
    except Exception:                           # noqa: BLE001 -- garbled: the parent computes those items
        return None


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
