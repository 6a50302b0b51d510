"""Test-session settings: a private, empty disk cache (tests compute from scratch and never read a developer's
~/.cache/palpate; removed at the end), single-threaded BLAS (2 shared cores), a non-interactive matplotlib backend, and
Ctrl-C's handler as a terminal's process has it."""
import atexit
import os
import shutil
import signal
import tempfile

import pytest

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MPLBACKEND", "Agg")
# One cache for the whole session, shared by pytest-xdist's workers: the process that makes it (the controller, which
# loads this file before it starts the workers, or a run without xdist) hands it on through the environment, and
# only it removes it, as it ends (with the 3D operators a session leaves about 1.5 GB, and sessions left behind filled
# this machine's disk: 72 GB in /tmp). Until session 57 each worker made its own, and both built the same fem models
# (block3d's take 35-60 s each); the cache is safe for concurrent writers (fem.memo, tests/test_memo.py), and a test
# about a cold cache sets its own PALPATE_CACHE_DIR.
_CACHE_DIR = os.environ.get("PALPATE_TEST_SESSION_CACHE")
if _CACHE_DIR is None or not os.path.isdir(_CACHE_DIR):
    _CACHE_DIR = tempfile.mkdtemp(prefix="palpate-test-cache-")
    os.environ["PALPATE_TEST_SESSION_CACHE"] = _CACHE_DIR
    atexit.register(shutil.rmtree, _CACHE_DIR, ignore_errors=True)
os.environ["PALPATE_CACHE_DIR"] = _CACHE_DIR
# a suite started as a background job of a non-interactive shell (`nohup bash .ci/run &`) inherits SIGINT ignored,
# and Python then installs no KeyboardInterrupt handler: the Ctrl-C tests (which send it to themselves and their
# children) failed there, three of them in session 46's first rehearsal, while passing from a terminal
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

# Tests that drive the simulated UR controller or sensor box in real time (sockets, 500 Hz data, watchdogs and
# time-outs in wall-clock time): run on their own, after the rest, so no other test's CPU load delays their
# controller and turns a fault's classification (a host held up past the watchdog's period) into another one. The
# rest run on two workers (pytest-xdist). The README's test command does both. Single tests elsewhere that do so carry
# @pytest.mark.realtime themselves.
REALTIME_FILES = {"test_fault_drills.py", "test_simcontroller.py", "test_netft_cli.py", "test_netft.py",
                  "test_run_data_safety.py"}     # (test_run_sim.py marks its one controller test itself: session 58)


# The longest files (measured in session 57: test_run3d.py about 370 s of a 726 s run on two workers), started
# first: with --dist loadfile a file runs on one worker, and the longest, started last, ran alone for minutes while
# the other worker had finished. The README's command gives --no-loadscope-reorder, so xdist keeps this order (by
# default it starts the files with the most tests first).
LONG_FILES = ("test_run3d.py", "test_study.py", "test_review_s47.py", "test_review_s49.py", "test_run_pending.py",
              "test_mismatch_sim.py", "test_review_s40.py", "test_review_s39.py", "test_detect_rate.py")


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.name in REALTIME_FILES:
            item.add_marker(pytest.mark.realtime)
    rank = {name: i for i, name in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONG_FILES)))     # (stable: the rest keep their order)


# (the fixtures import palpate when first used: at the top, numpy would load before the BLAS settings above)
@pytest.fixture(scope="session")
def paper_prior():
    """The paper scene's prior (no stones): what the localizer is given."""
    from fem.scene import load
    return load("paper").prior()


@pytest.fixture(scope="session")
def paper_surrogate(paper_prior):
    """Its contrast table (shipped in planner/data, checked against today's fem by its fingerprint)."""
    from planner.surrogate import load_surrogate
    return load_surrogate(paper_prior)


@pytest.fixture
def exponentless_rule_before_s54(monkeypatch):
    """The depth limit of a plan without force exponents counted from the contact felt, as before session 54. Tests
    whose plans (robot_fixtures.make_plan) carry none and whose expectations (statuses, where drift is caught, the
    fast-forward's records) were set with that rule, and whose subjects are elsewhere, keep it; since session 54 the
    driver fits the surface with robot.driver.UNKNOWN_FORCE_EXPONENT (tests/test_depth_limit_s43.py,
    tests/test_review_s54.py)."""
    import robot.driver
    monkeypatch.setattr(robot.driver, "UNKNOWN_FORCE_EXPONENT", None)
