"""Session 46: a Ctrl-C at the terminal while a dask LocalCluster works (a study, or the surrogate table a run builds
in the background) ends with the caller's one line, not a KeyboardInterrupt traceback from every worker; and the
cluster's scheduler no longer warns that dask's port 8787 is taken when another cluster runs on the machine."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _slow(marker: str, piece: int) -> int:
    """A piece that says it has started, then works for longer than the test waits."""
    Path(f"{marker}.{piece}").touch()
    time.sleep(60)
    return piece


SCRIPT = textwrap.dedent("""
    import sys, warnings
    sys.path.insert(0, {root!r})
    warnings.simplefilter("always")       # dask's port warning is a UserWarning: shown, whoever imported what
    from planner.tasks import Runner, run_pieces
    from tests.test_review_s46 import _slow
    try:
        run_pieces(_slow, {marker!r}, [0, 1], ["a", "b"], Runner(workers=2, progress=False))
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
""")


def _start(tmp_path, name: str) -> tuple[subprocess.Popen, str]:
    marker = str(tmp_path / name)
    p = subprocess.Popen([sys.executable, "-c", SCRIPT.format(root=str(ROOT), marker=marker)], cwd=tmp_path,
                         start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))   # as a terminal's job
    return p, marker


def _wait_started(p: subprocess.Popen, marker: str) -> None:
    deadline = time.monotonic() + 120
    while not (os.path.exists(f"{marker}.0") and os.path.exists(f"{marker}.1")):
        assert p.poll() is None, p.communicate()[1]
        assert time.monotonic() < deadline, "the workers never started their pieces"
        time.sleep(0.1)


def test_ctrl_c_during_a_local_cluster_ends_in_one_line_without_worker_tracebacks(tmp_path):
    first, m1 = _start(tmp_path, "first")       # a cluster already running on this machine: its port is taken
    second, m2 = _start(tmp_path, "second")
    try:
        _wait_started(first, m1)
        _wait_started(second, m2)
        os.killpg(second.pid, signal.SIGINT)    # Ctrl-C: the whole process group, the workers included
        _, err = second.communicate(timeout=60)
    finally:
        for p in (first, second):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.communicate()
    assert second.returncode == 130, err
    assert err.strip() == "interrupted", err
