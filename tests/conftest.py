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
_CACHE_DIR = tempfile.mkdtemp(prefix="palpate-test-cache-")
os.environ["PALPATE_CACHE_DIR"] = _CACHE_DIR
# removed when the session's process ends (each xdist worker has its own): with the 3D operators a session leaves
# about 1.5 GB, and sessions left behind filled this machine's disk (72 GB in /tmp)
atexit.register(shutil.rmtree, _CACHE_DIR, ignore_errors=True)
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
                  "test_run_sim.py", "test_run_data_safety.py"}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.name in REALTIME_FILES:
            item.add_marker(pytest.mark.realtime)


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
