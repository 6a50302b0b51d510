"""Session 60's independent review of 2D fem and planning on extreme scenes of its own: a section under 10 mm wide
was refused for every contact command (the fields' factor key was made with the default 5 mm tip, which such a
section refuses); a tip pressed 1 um in between two top nodes gave force 0 without a word; the unresolved-contact
warning understated what a review measured (force +28 %, peaks -80 % with one node in contact); and `run --plan`
refused a plan made with a smaller --min-depth-m, the very fix its own message recommends, because its detectability
check chose depths with the default minimum."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app import entry, runexec
from app.cli import main
from app.resolution import warn_unresolved2d
from app.runexec import resuming_note
from fem.scene import load
from robot.records import RunLog

ROOT = Path(__file__).resolve().parents[1]

NARROW = """name = "narrow"
[tissue]
width_m = 0.009
height_m = 0.005
youngs_pa = 1000000.0
poisson = 0.3
[indenter]
shape = "cylinder"
radius_m = 0.001
[analysis]
mesh_size_m = 0.0005
"""

COARSE = """name = "coarse"
[tissue]
width_m = 0.07
height_m = 0.05
youngs_pa = 2500.0
poisson = 0.4
[analysis]
mesh_size_m = 0.004
"""

STIFF = """name = "stiff"
[tissue]
width_m = 0.07
height_m = 0.05
youngs_pa = 1000000.0
poisson = 0.4
[[stone]]
x_m = 0.035
depth_m = 0.025
diameter_m = 0.015
"""


def _toml(tmp_path, text: str, name: str) -> str:
    p = tmp_path / f"{name}.toml"
    p.write_text(text)
    return str(p)


def test_a_section_under_10_mm_wide_takes_the_tip_load(tmp_path, monkeypatch):
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "narrow.json"
    assert main(["simulate", _toml(tmp_path, NARROW, "narrow"), "--load", "indent", "--x-m", "0.0045",
                 "--depth-m", "0.0001", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["force_n"] > 0 and r["max_von_mises_pa"] > 0


def test_a_tip_between_two_nodes_is_said_to_touch_none(tmp_path, monkeypatch, capsys):
    """1 um deep, a 5 mm cylinder's footprint is 0.2 mm wide; the coarse top's nodes are 0.5 mm apart (1 mm P2
    elements): at x = 15.25 mm none lies under it, and the force 0 is said to be the mesh's."""
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "r.json"
    assert main(["simulate", _toml(tmp_path, COARSE, "coarse"), "--load", "indent", "--x-m", "0.01525",
                 "--depth-m", "1e-6", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["force_n"] == 0.0
    err = capsys.readouterr().err
    assert "touched no node of the top" in err and "0.2 mm wide" in err and "0.5 mm apart" in err


def test_the_unresolved_warnings_say_what_was_measured(capsys):
    sc = load("paper")
    warn_unresolved2d(sc, "simulate", [0.0], depths_m=[0.0])              # not pressed: nothing to say
    warn_unresolved2d(sc, "predict", [0.0, 2e-3])                          # no depths given: the old behaviour
    assert capsys.readouterr().err == ""
    warn_unresolved2d(sc, "simulate", [1e-4])
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "+28 %" in err and "80 %" in err


def test_run_takes_a_plan_made_with_a_smaller_minimum_depth(tmp_path, monkeypatch):
    """1 MPa tissue pushes back 5.6 N at the default 1 mm minimum depth: `run` refuses it and says to plan with a
    smaller --min-depth-m and run that plan, which it then refused too (exit 2). Now the plan's own options choose
    the detectability's depths, and the run finds the stone (truth x 35 mm)."""
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path / "cache"))
    scene = _toml(tmp_path, STIFF, "stiff")
    assert main(["run", scene, "--sim", "--no-figure", "--out", str(tmp_path / "refused")]) == 2
    plan = tmp_path / "plan.json"
    assert main(["plan", scene, "--out", str(plan), "--min-depth-m", "0.0001"]) == 0
    assert main(["run", scene, "--plan", str(plan), "--sim", "--budget-probes", "15", "--no-figure",
                 "--out", str(tmp_path / "run")]) == 0
    res = json.loads((tmp_path / "run" / "result.json").read_text())
    est = res["estimate"] if "estimate" in res else res
    x = est.get("x_m") or est.get("stone", {}).get("x_m")
    assert x["value"] == pytest.approx(0.035, abs=max(1e-3, 3 * x["sigma"]))


# ---- the same session's review of data integrity and resume (interrupts, damaged directories, the cache) ----------

def _short_run(tmp_path, out: str = "run") -> tuple:
    d = tmp_path / out
    assert main(["run", "paper", "--sim", "--budget-probes", "15", "--no-figure", "--out", str(d)]) == 0
    return d, sorted((d / "raw").glob("probe_*.npz"))


def test_a_resumed_run_draws_noise_of_its_own(tmp_path, monkeypatch, capsys):
    """The review's SIGKILL and resume: the first probe pressed after the resume repeated probe 0's free-air noise
    sample for sample (the simulated sensor restarted from the seed). A resumed process now draws from (seed, the
    probes recorded): reproducible, and not the first process's stream."""
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path / "cache"))
    d, raws = _short_run(tmp_path)
    assert runexec.noise_seed(0, d, resume=False) == (0, "")
    seed, said = runexec.noise_seed(0, d, resume=True)
    assert seed != 0 and said.startswith("; resumed after 15 probe records") and runexec.noise_seed(0, d, True)[0] == seed
    assert runexec.noise_seed(1, d, resume=True)[0] not in (seed, 1)
    lines = (d / "probes.jsonl").read_text().splitlines(keepends=True)
    (d / "probes.jsonl").write_text("".join(lines[:8]))          # as if killed after 8 records: 7 pressed again
    capsys.readouterr()
    assert main(["run", "paper", "--sim", "--budget-probes", "15", "--no-figure", "--out", str(d)]) == 0
    assert "resumed after 8 probe records: noise stream" in capsys.readouterr().err
    with np.load(raws[0]) as z0:
        first = z0["force_n"][:200]
    again = sorted(set((d / "raw").glob("probe_*.npz")) - set(raws))
    assert len(again) == 7
    with np.load(again[0]) as z:
        assert not np.array_equal(z["force_n"][:200], first)


def test_a_damaged_or_missing_raw_file_is_said_on_resume(tmp_path, monkeypatch):
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path / "cache"))
    d, raws = _short_run(tmp_path)
    assert "missing or damaged" not in resuming_note(d)
    raws[3].write_bytes(raws[3].read_bytes()[:1000])
    raws[5].unlink()
    note = resuming_note(d)
    assert "the raw samples of 2 probe(s) measured before are missing or damaged" in note
    assert "probe_003.npz" in note and "probe_005.npz" in note


def test_sigterm_between_rounds_ends_as_ctrl_c_does(tmp_path):
    """A supervisor's SIGTERM while the run plans (not the arm's motion, whose gate handled it already): the one
    line and exit 130, not a silent death by the signal (exit -15)."""
    env = dict(os.environ, PALPATE_CACHE_DIR=str(tmp_path / "cache"), PYTHONPATH=str(ROOT))
    p = subprocess.Popen([sys.executable, "-m", "app.cli", "run", "paper", "--sim", "--no-figure", "--out",
                          str(tmp_path / "run")], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
                         env=env, cwd=ROOT)
    lines = []
    for line in p.stderr:
        lines.append(line)
        if "planning a 15-waypoint raster" in line:
            p.send_signal(signal.SIGTERM)
            break
    lines += p.stderr.readlines()
    assert p.wait(timeout=120) == 130, "".join(lines)
    assert lines[-1].strip() == "palpate: interrupted"


def test_the_console_script_takes_sigterm_as_ctrl_c_from_its_first_import(monkeypatch):
    monkeypatch.setattr(signal, "getsignal", lambda s: signal.SIG_DFL)
    installed = {}
    monkeypatch.setattr(signal, "signal", lambda s, h: installed.setdefault(s, h))
    monkeypatch.setattr(entry.importlib, "import_module", lambda name: (_ for _ in ()).throw(KeyboardInterrupt()))
    assert entry.palpate() == 130
    assert installed == {signal.SIGTERM: signal.default_int_handler}


def test_a_run_refuses_a_studys_directory_and_json_spares_what_a_resume_set_aside(tmp_path, capsys):
    study = tmp_path / "study"
    (study / "pieces" / "mismatch-abc").mkdir(parents=True)
    assert main(["run", "paper", "--sim", "--no-figure", "--out", str(study)]) == 2
    assert list(study.iterdir()) == [study / "pieces"]
    run = tmp_path / "run"
    run.mkdir()
    (run / "probes.jsonl").write_text("")
    for name in ("probes.jsonl.torn", "fig_run.png"):
        (run / name).write_bytes(b"kept")
        assert main(["predict", "paper", "--waypoints", "3", "--depth-m", "0.002", "--force-only", "--json",
                     str(run / name)]) == 2
        assert (run / name).read_bytes() == b"kept" and "would overwrite a run's data" in capsys.readouterr().err


def test_run_json_says_running_while_a_round_runs(tmp_path, monkeypatch):
    """A run killed mid-round (SIGKILL) left run.json saying "ok" from its last finished round; each round now
    writes "running" before its first motion and its ending status after."""
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path / "cache"))
    written = []
    real = RunLog.write_run
    monkeypatch.setattr(RunLog, "write_run", lambda self, summary: written.append(summary["status"]) or
                        real(self, summary))
    d = tmp_path / "run"                          # the coarse raster and a refinement round: two driver runs
    assert main(["run", "paper", "--sim", "--budget-probes", "25", "--no-figure", "--out", str(d)]) == 0
    assert written.count("running") >= 2
    assert written[0] == "running" and written[-1] == "ok" and written.count("running") == written.count("ok")
    assert json.loads((d / "run.json").read_text())["status"] == "ok"
    h = d / "run_history.jsonl"                   # (one round per driver run: the earlier rounds' reports)
    history = [json.loads(line) for line in h.read_text().splitlines()] if h.exists() else []
    assert len(history) == written.count("ok") - 1 and all(h["status"] == "ok" for h in history)   # no own marker


def test_sigterm_after_gmsh_has_meshed_is_still_ctrl_c():
    """gmsh's initialize sets SIGTERM back to the default at the C level (Python still reports its own handler):
    after the first mesh of a cold command, a SIGTERM killed palpate silently (exit -15; session 60's third review).
    fem.mesh re-arms the handler Python believes in."""
    code = ("import os, signal, time\n"
            "signal.signal(signal.SIGTERM, signal.default_int_handler)\n"
            "from fem.scene import load\n"
            "from fem.scene_mesh import mesh_for\n"
            "mesh_for(load('paper').with_analysis(mesh_size_m=0.01, surface_refine=1.0), use=False)\n"
            "try:\n"
            "    os.kill(os.getpid(), signal.SIGTERM)\n"
            "    time.sleep(5)\n"
            "except KeyboardInterrupt:\n"
            "    print('interrupted')\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120,
                       env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert r.returncode == 0 and r.stdout.strip() == "interrupted", (r.returncode, r.stderr[-500:])
