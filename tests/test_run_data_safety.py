"""`palpate run` never deletes a record (issue 13): kill -9 then resume, a failed re-run leaves every file as it was,
--fresh moves the old files aside, --json never onto measured data. In-memory simulated arm, small rasters."""
from __future__ import annotations

import collections
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from robot.simforce import CachedForce

REPO = Path(__file__).resolve().parents[1]
SMALL = ["--waypoints", "6", "--refine-waypoints", "4", "--budget-probes", "10", "--no-figure"]


def _env():
    env = dict(os.environ, PYTHONPATH=str(REPO), OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MPLBACKEND="Agg")
    return env


def _cmd(out, *extra, scene="paper"):
    return [sys.executable, "-m", "app.cli", "run", scene, "--sim", "--out", str(out), *SMALL, *extra]


def _run(out, *extra, scene="paper", timeout=600):
    return subprocess.run(_cmd(out, *extra, scene=scene), cwd=REPO, env=_env(), capture_output=True, text=True,
                          timeout=timeout)


def _lines(out: Path) -> list[dict]:
    p = out / "probes.jsonl"
    return [json.loads(s) for s in p.read_text().splitlines() if s.strip()] if p.exists() else []


def _snapshot(out: Path) -> dict:
    return {str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(out.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "R"
    r = _run(out)
    assert r.returncode == 0, r.stderr
    return out


def test_kill9_then_resume(tmp_path):
    out = tmp_path / "R"
    proc = subprocess.Popen(_cmd(out), cwd=REPO, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    t0 = time.monotonic()
    try:
        while len(_lines(out)) < 3:
            assert proc.poll() is None, f"the run ended before 3 records: {proc.stderr.read().decode()[-2000:]}"
            assert time.monotonic() - t0 < 400, "no 3 records in 400 s"
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    before = (out / "probes.jsonl").read_text()
    rec_before = _lines(out)
    assert proc.returncode == -signal.SIGKILL and len(rec_before) < 10
    r = _run(out)
    assert r.returncode == 0, r.stderr
    after = (out / "probes.jsonl").read_text()
    assert after.startswith(before.rstrip("\n"))                 # the records before are a prefix of those after
    recs = _lines(out)
    ok = collections.Counter(d["index"] for d in recs if d["status"] in ("ok", "force_limit"))
    assert ok and max(ok.values()) == 1, f"an index measured twice: {ok}"
    assert sorted(ok) == list(range(10))                          # the run completed: 6 + 4 probes
    res = json.loads((out / "result.json").read_text())
    assert res["status"] == "ok" and res["probes_used"] == 10
    assert "resuming" in r.stderr


@pytest.mark.parametrize("bad", ["scene", "option", "plan", "json-into-log", "other-options"])
def test_failed_rerun_changes_nothing(finished, bad, tmp_path):
    before = _snapshot(finished)
    if bad == "scene":
        r = _run(finished, scene="nosuch")
    elif bad == "option":
        r = _run(finished, "--target-uncertainty-m", "nan")
    elif bad == "plan":
        text = (finished / "plan_round0.json").read_text()
        (tmp_path / "p.json").write_text(text[: len(text) // 2])
        r = _run(finished, "--plan", str(tmp_path / "p.json"))
    elif bad == "json-into-log":
        r = _run(finished, "--json", str(finished / "probes.jsonl"))
    else:
        r = subprocess.run(_cmd(finished)[:-len(SMALL)] + ["--waypoints", "7", "--budget-probes", "10"], cwd=REPO,
                           env=_env(), capture_output=True, text=True, timeout=600)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()[-1]) > 10
    assert _snapshot(finished) == before


def test_same_options_rerun_presses_nothing(finished):
    before = (finished / "probes.jsonl").read_bytes()
    r = _run(finished)
    assert r.returncode == 0, r.stderr
    assert (finished / "probes.jsonl").read_bytes() == before


def test_fresh_moves_old_files_aside(tmp_path):
    out = tmp_path / "R"
    out.mkdir()
    (out / "probes.jsonl").write_text('{"index": 0, "x_m": 0.01, "status": "ok"}\n')
    (out / "run.json").write_text("{}")
    old = _snapshot(out)
    r = _run(out, "--fresh")
    assert r.returncode == 0, r.stderr
    prev = list(out.glob("previous-*"))
    assert len(prev) == 1 and _snapshot(prev[0]) == old
    assert len(_lines(out)) == 10


def test_cached_force_reports_beyond_range():
    def model(x, d):
        if d >= 0.005:
            raise ValueError("depth beyond the tip radius")
        return 1000 * d ** 1.5
    f = CachedForce(model)
    f(0.01, 0.00495)                        # within one grid step of the edge: a mild extrapolation, not reported
    assert f.range_report() is None
    f(0.01, 0.006)
    rep = f.range_report()
    assert rep and rep["samples_beyond_model_range"] == 1 and rep["deepest_m"] == pytest.approx(0.006)
