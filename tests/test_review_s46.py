"""Session 46: a Ctrl-C at the terminal while a dask LocalCluster works (a study, or the surrogate table a run builds
in the background) ends with the caller's one line, not a KeyboardInterrupt traceback from every worker; and the
cluster's scheduler no longer warns that dask's port 8787 is taken when another cluster runs on the machine. And what
an adversarial review of the less-travelled options found: each now one line naming the option, exit 2."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from app.cli import main
from app.options import is_measured
from robot.safety import check_plan
from tests.robot_fixtures import make_plan, solve_joints

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
    held = socket.socket()                      # dask's port taken, as by another cluster on this machine
    try:
        held.bind(("", 8787))
        held.listen()
    except OSError:                             # taken already
        pass
    p, marker = _start(tmp_path, "run")
    try:
        _wait_started(p, marker)
        os.killpg(p.pid, signal.SIGINT)         # Ctrl-C: the whole process group, the workers included
        _, err = p.communicate(timeout=60)
    finally:
        held.close()
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate()
    assert p.returncode == 130, err
    assert err.strip() == "interrupted", err


@pytest.fixture
def a_run(tmp_path) -> Path:
    """A run's directory: its measured probes and raw samples."""
    run = tmp_path / "run"
    (run / "raw").mkdir(parents=True)
    (run / "probes.jsonl").write_text("{}\n")
    return run


@pytest.mark.parametrize("argv, starts", [
    # the empty path wrote nothing and said nothing (every other command refused it)
    (["cache", "list", "--json", ""], "palpate: --json '': an empty path"),
    # 1e308 overflowed inside the planner ("math domain error"); a 5 m tool blamed --tissue-pose; a tool pointing
    # back through the flange was planned
    (["plan", "paper", "--out", "P", "--tcp-offset", "0", "0", "0.1", "0", "0", "1e308"],
     "palpate: --tcp-offset 0 0 0.1 0 0 1e+308: the rotation vector"),
    (["plan", "paper", "--out", "P", "--tcp-offset", "0", "0", "5", "0", "0", "0"],
     "palpate: --tcp-offset 0 0 5 0 0 0: the tip must lie beyond the flange (z > 0) and within 0.3 m"),
    (["plan", "paper", "--out", "P", "--tcp-offset", "0", "0", "-0.1", "0", "0", "0"],
     "palpate: --tcp-offset 0 0 -0.1 0 0 0: the tip must lie beyond the flange"),
    (["plan", "paper", "--out", "P", "--tissue-pose", "0.4", "-0.035", "1e308", "0", "0", "0"],
     "palpate: --tissue-pose 0.4 -0.035 1e+308 0 0 0: out of reach"),
    # the 3D study's coarse grid is 36 probes whatever the budget: a smaller one was silently exceeded
    (["study", "accuracy3d", "--out", "S", "--budget-probes", "20"],
     "palpate: --budget-probes 20: the accuracy3d study's coarse grid alone is 6 x 6 = 36 probes"),
    (["bench", "--out", "B", "--bench-dir", "/nonexistent-bench", "--only", "sweep"],
     "palpate bench: --bench-dir /nonexistent-bench: no bench_runtime_error.py there"),
    # the simulated box's options were ignored for a real one
    (["ft", "--netft", "192.0.2.1", "--ft-range-n", "25", "--ft-range-nm", "0.25", "--seed", "3"],
     "palpate: --seed 3: only for the simulated box"),
    # a depth far below an atom: the stresses underflowed, and a von Mises peak of 0 Pa was reported at x = 0
    (["simulate", "paper", "--load", "indent", "--x-m", "0.035", "--depth-m", "1e-300"],
     "palpate: --depth-m 1e-300: below 1e-12 m"),
    (["predict", "paper", "--waypoints", "5", "--depth-m", "1e-300"], "palpate: --depth-m 1e-300: below 1e-12 m"),
])
def test_the_reviews_bad_options_are_one_line_and_exit_2(argv, starts, tmp_path, capsys):
    argv = [str(tmp_path / a) if a in ("P", "S", "B") else a for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(starts), err
    assert list(tmp_path.iterdir()) == []                  # nothing written


def test_a_blank_cache_directory_is_refused(tmp_path, monkeypatch, capsys):
    """It was used as a directory named by the blanks, in the current directory."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PALPATE_CACHE_DIR", "  ")
    assert main(["cache", "list"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("palpate: PALPATE_CACHE_DIR=") and "a blank path" in err
    assert list(tmp_path.iterdir()) == []


def test_a_runs_raw_folder_and_directory_are_refused_as_outputs(a_run, capsys):
    """`--plots RUN/raw` wrote figures among the raw samples (the guard checked raw's parents only), and `study
    --out RUN` put a study's pieces into a run's directory."""
    assert is_measured(a_run / "raw") and is_measured(a_run)
    assert main(["plan", "paper", "--out", str(a_run.parent / "p.json"), "--plots", str(a_run / "raw")]) == 2
    assert "--plots" in capsys.readouterr().err
    assert main(["study", "accuracy", "--quick", "--out", str(a_run)]) == 2
    assert capsys.readouterr().err.startswith(f"palpate: --out {a_run}: a run's directory")
    # through a link, and not for a path that only passes through raw/ ("RUN/raw/../figs" is RUN/figs)
    link = a_run.parent / "rawlink"
    link.symlink_to(a_run / "raw")
    assert main(["plan", "paper", "--out", str(a_run.parent / "p.json"), "--plots", str(link / "sub")]) == 2
    assert "inside a run's raw/" in capsys.readouterr().err
    link.unlink()
    assert not is_measured(a_run / "raw" / ".." / ".." / "other")
    assert sorted(p.name for p in a_run.iterdir()) == ["probes.jsonl", "raw"] and not list((a_run / "raw").iterdir())


def test_a_hand_edited_plan_whose_tool_points_back_through_the_flange_is_refused():
    plan = solve_joints(make_plan())
    assert check_plan(plan)[0] == []
    plan.frames.tcp_offset = [0.0, 0.0, -0.1, 0.0, 0.0, 0.0]
    assert any("z must be positive" in p for p in check_plan(plan)[0])


def test_a_scene_files_error_names_the_file(tmp_path, capsys):
    """Errors whose words contain 'scene' ("in a 2D scene") were taken as naming it, and the file went unnamed."""
    f = tmp_path / "sphere2d.toml"
    f.write_text('[tissue]\nwidth_m = 0.07\nheight_m = 0.05\nyoungs_pa = 2500.0\npoisson = 0.4\n'
                 '[indenter]\nshape = "sphere"\n')
    assert main(["predict", str(f), "--waypoints", "5", "--force-only"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"palpate: scene {f}: indenter.shape must be"), err
