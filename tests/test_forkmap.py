"""planner.forkmap: the forked map gives the plain loop's results in order, falls back to the loop when the child
fails or dies, passes the parent's own exceptions on, and leaves no child process behind."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from planner.forkmap import fork_map

PARENT = os.getpid()


def _children() -> set[int]:
    """This process's child processes, running or not yet reaped (Linux: /proc)."""
    out: set[int] = set()
    for task in os.listdir("/proc/self/task"):
        with open(f"/proc/self/task/{task}/children") as f:
            out.update(int(p) for p in f.read().split())
    return out


@pytest.fixture(autouse=True)
def no_child_left_behind():
    """Every test ends with no child of fork_map left, running or unreaped (other tests' children are ignored)."""
    before = _children()
    yield
    assert _children() <= before


def _square_and_pid(x):
    return x * x, os.getpid()


@pytest.mark.parametrize("n", [0, 1, 2, 3, 7, 8])
def test_results_in_order_and_half_from_a_child(n):
    items = list(range(n))
    got = fork_map(_square_and_pid, items, workers=2)
    assert [v for v, _ in got] == [x * x for x in items]
    pids = [p for _, p in got]
    if n >= 2:          # the parent takes items 0, 2, 4, ...; one child the rest
        assert set(pids[0::2]) == {os.getpid()}
        assert len(set(pids[1::2])) == 1 and pids[1] != os.getpid()
    else:
        assert set(pids) <= {os.getpid()}


@pytest.mark.parametrize("workers", [3, 4, 9])
def test_more_workers_share_the_items_round_robin(workers):
    got = fork_map(_square_and_pid, range(10), workers=workers)
    assert [v for v, _ in got] == [x * x for x in range(10)]
    pids = [p for _, p in got]
    n = min(workers, 10)
    assert set(pids[0::n]) == {os.getpid()}
    others = [set(pids[k::n]) for k in range(1, n)]
    assert all(len(s) == 1 for s in others) and len(set().union(*others)) == n - 1 and os.getpid() not in pids[1::n]


def test_one_worker_is_the_plain_loop():
    got = fork_map(_square_and_pid, range(5), workers=1)
    assert got == [(x * x, os.getpid()) for x in range(5)]


def test_arrays_and_fit_results_come_back_bit_for_bit():
    """What the localizer sends back: scipy's OptimizeResult with arrays, equal to the serial fit's."""
    from scipy.optimize import least_squares
    rng = np.random.default_rng(1)
    t = np.linspace(0, 1, 40)
    y = 2.0 * np.exp(-3.0 * t) + rng.normal(0, 0.01, len(t))

    def fit(x0):
        return least_squares(lambda p: p[0] * np.exp(-p[1] * t) - y, x0, bounds=([0, 0], [10, 10]))
    starts = [np.array([1.0, 1.0]), np.array([5.0, 0.1]), np.array([0.5, 8.0])]
    for a, b in zip(fork_map(fit, starts, 2), [fit(s) for s in starts]):
        assert np.array_equal(a.x, b.x) and a.cost == b.cost and np.array_equal(a.jac, b.jac)
        assert np.array_equal(a.active_mask, b.active_mask) and a.nfev == b.nfev


def _fails_in_child(x):
    if os.getpid() != PARENT:
        raise RuntimeError("only the child fails")
    return x + 1


def _dies_in_child(x):
    if os.getpid() != PARENT:
        os.kill(os.getpid(), signal.SIGKILL)
    return x + 1


@pytest.mark.parametrize("fn", [_fails_in_child, _dies_in_child])
@pytest.mark.parametrize("workers", [2, 3])
def test_a_failed_child_is_replaced_by_the_parent(fn, workers):
    assert fork_map(fn, range(7), workers=workers) == [x + 1 for x in range(7)]


def _parent_fails(x):
    if os.getpid() == PARENT and x == 0:     # the parent's first item, while the children work
        raise ValueError("the parent's item 0")
    return x


@pytest.mark.parametrize("workers", [2, 3])
def test_the_parents_exception_passes_and_the_children_are_reaped(workers):
    with pytest.raises(ValueError, match="item 0"):
        fork_map(_parent_fails, range(6), workers=workers)


def _raises_everywhere(x):
    if x == 3:
        raise KeyError("item 3")
    return x


def test_an_items_exception_is_raised_as_the_loop_would():
    """Item 3 is the child's: it fails there, the parent computes the child's items and raises the loop's error."""
    with pytest.raises(KeyError, match="item 3"):
        fork_map(_raises_everywhere, range(6), workers=2)


def _interrupted_in_child(x):
    if os.getpid() != PARENT:
        raise KeyboardInterrupt
    return x + 1


def _ctrl_c_in_child(x):
    if os.getpid() != PARENT:
        os.kill(os.getpid(), signal.SIGINT)     # the child's SIGINT is the default action: it just ends
        time.sleep(5)
    return x + 1


@pytest.mark.parametrize("fn", [_interrupted_in_child, _ctrl_c_in_child])
def test_an_interrupted_child_never_unwinds_into_the_caller(fn):
    """A child interrupted anywhere ends through os._exit (its caller's code, atexit handlers and buffers are the
    parent's alone); the parent computes its items."""
    assert fork_map(fn, range(5), workers=2) == [x + 1 for x in range(5)]
    assert os.getpid() == PARENT


def _ctrl_c_in_parent(x):
    if os.getpid() == PARENT and x == 0:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(1)                       # (the interrupt is raised here)
    if os.getpid() != PARENT:
        time.sleep(5)
    return x


def test_ctrl_c_in_the_parent_ends_the_children():
    t = time.perf_counter()
    with pytest.raises(KeyboardInterrupt):
        fork_map(_ctrl_c_in_parent, range(6), workers=3)
    assert time.perf_counter() - t < 4      # the children were killed, not waited for


def _hangs_in_child(x):
    if os.getpid() != PARENT:
        time.sleep(60)
    return -x


def test_a_child_that_does_not_answer_is_killed_and_its_items_computed_here(monkeypatch):
    import planner.forkmap as fm
    monkeypatch.setattr(fm, "CHILD_TIMEOUT_S", 0.5)
    t = time.perf_counter()
    assert fork_map(_hangs_in_child, range(4), workers=2) == [0, -1, -2, -3]
    assert time.perf_counter() - t < 5


def test_a_child_dies_with_its_parent(tmp_path):
    """Linux: a run killed outright (SIGKILL) leaves no fits computing (PR_SET_PDEATHSIG)."""
    if not sys.platform.startswith("linux"):
        pytest.skip("PR_SET_PDEATHSIG is Linux's")
    pidfile = tmp_path / "child.pid"
    code = (f"import os, sys, time; sys.path.insert(0, {str(Path(__file__).parents[1])!r})\n"
            "from planner.forkmap import fork_map\n"
            "parent = os.getpid()\n"
            "def f(x):\n"
            "    if os.getpid() != parent:\n"
            f"        open({str(pidfile)!r}, 'w').write(str(os.getpid())); time.sleep(60)\n"
            "    else:\n"
            "        time.sleep(60)\n"
            "fork_map(f, [0, 1], 2)\n")
    proc = subprocess.Popen([sys.executable, "-c", code])
    try:
        for _ in range(200):
            if pidfile.exists() and pidfile.read_text():
                break
            time.sleep(0.05)
        child = int(pidfile.read_text())
    finally:
        proc.kill()
        proc.wait()
    for _ in range(100):                    # the child is init's now: gone once the kernel has killed it
        if not Path(f"/proc/{child}").exists() or "Z" in Path(f"/proc/{child}/stat").read_text().split()[2]:
            break
        time.sleep(0.05)
    else:
        os.kill(child, signal.SIGKILL)
        pytest.fail("the child outlived its killed parent")
