"""Session 56's bad-input review (an independent session attacking every command): each test fails on session 55's
code.

1. Abbreviated options were taken silently (``run --depth 0.003`` ran as ``--depth-limit-m 0.003``).
2. An output path equal to an input replaced it (``--json`` on the scene file or the plan, ``plan --out`` on the
   scene), exit 0.
3. A plan without ``scene.indenter`` ran on fem's default tip (the tip bounds the depth limit); a NaN in a plan's
   notes crashed the run after probing began.
4. ``[truth] relaxation_tau_s`` without a relaxation fraction was ignored silently.
5. A damaged finished piece of a study gave a traceback on resume; the study's JSON and CSV held NaN.
6. A second Ctrl-C during the fem memo's save at exit printed a traceback.
7. A force fault of 1e300 N was accepted (its records, beyond the contract, were then dropped silently on the
   cell's resume: that now says so).
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from robot_fixtures import make_plan  # noqa: E402

from app import cell, cli  # noqa: E402
from app.faultdrill import coarse_paper_scene  # noqa: E402
from core.contracts import Motion, Plan, PlanError  # noqa: E402
from core.jsonsafe import csv_row, nulled  # noqa: E402
from core.textfile import InputFileError  # noqa: E402
from fem import memo  # noqa: E402
from planner.tasks import load_piece  # noqa: E402
from robot.driver import unfelt_probes  # noqa: E402
from robot.simfaults import parse  # noqa: E402
from robot.truth import TruthConditions, TruthError  # noqa: E402


@pytest.mark.parametrize("argv, option", [
    (["run", "paper", "--sim", "--depth", "0.003", "--out", "R"], "--depth"),
    (["predict", "paper", "--way", "5"], "--way"),
])
def test_abbreviated_options_are_refused(argv, option, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert f"unrecognized arguments: {option}" in err and len(err.strip().splitlines()) == 1, err


def test_the_cells_abbreviated_options_are_refused(capsys, tmp_path):
    assert cell.main(["--sim", "--plan", "p.json", "--out", str(tmp_path / "R"), "--sens", "ideal"]) == 2
    assert "unrecognized arguments: --sens" in capsys.readouterr().err


@pytest.fixture()
def scene_file(tmp_path):
    return coarse_paper_scene(tmp_path / "s.toml")


@pytest.mark.parametrize("argv", [
    ["simulate", "{scene}", "--json", "{scene}"],
    ["predict", "{scene}", "--json", "{scene}"],
    ["plan", "{scene}", "--out", "{scene}"],
    ["plan", "{scene}", "--out", "{tmp}/p.json", "--json", "{scene}"],
    ["run", "{scene}", "--sim", "--json", "{tmp}/../{tmpname}/s.toml", "--out", "{tmp}/R"],    # another spelling
])
def test_an_output_on_an_input_is_refused(argv, scene_file, tmp_path, capsys):
    before = scene_file.read_bytes()
    argv = [a.format(scene=scene_file, tmp=tmp_path, tmpname=tmp_path.name) for a in argv]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "which the command reads" in err and "SCENE" in err, err
    assert scene_file.read_bytes() == before


def test_the_cells_json_on_its_plan_is_refused(tmp_path, capsys):
    plan = make_plan()
    path = tmp_path / "plan.json"
    plan.save(path)
    before = path.read_bytes()
    assert cell.main(["--sim", "--plan", str(path), "--json", str(path), "--out", str(tmp_path / "R")]) == 2
    assert "is --plan" in capsys.readouterr().err and path.read_bytes() == before


def _plan_dict() -> dict:
    return json.loads(json.dumps(make_plan().to_dict()))


@pytest.mark.parametrize("part", ["indenter", "analysis", "tissue"])
def test_a_plan_scene_without_its_tables_is_refused(part):
    d = _plan_dict()
    del d["scene"][part]
    with pytest.raises(PlanError, match=f"scene.{part} is missing"):
        Plan.from_dict(d)


def test_a_plan_with_a_nan_in_its_notes_is_refused():
    d = _plan_dict()
    d["notes"] = {"solver": {"time_s": math.nan}}
    with pytest.raises(PlanError, match="'notes' holds a number that is not finite"):
        Plan.from_dict(d)
    d["notes"] = {"solver": {"time_s": 1.0}}
    assert Plan.from_dict(d).notes == {"solver": {"time_s": 1.0}}


def test_a_relaxation_time_without_relaxation_is_refused():
    with pytest.raises(TruthError, match="relaxation_tau_s = 5.0 without a relaxation_fraction"):
        TruthConditions.from_dict({"relaxation_tau_s": 5.0})
    assert TruthConditions.from_dict({"relaxation_tau_s": 5.0, "relaxation_fraction": 0.2}).relaxation_tau_s == 5.0


@pytest.mark.parametrize("text", ['{"garbage": ', ""])
def test_a_damaged_study_piece_is_named(tmp_path, text):
    (tmp_path / "trial-00001.json").write_text(text)
    with pytest.raises(InputFileError, match="trial-00001.json.*cannot be read back.*move it aside"):
        load_piece(tmp_path, "trial-00001")
    (tmp_path / "trial-00002.json").write_text('[{"seed": 2}]')
    assert load_piece(tmp_path, "trial-00002") == [{"seed": 2}]
    assert load_piece(tmp_path, "trial-00003") is None


def test_study_outputs_hold_no_nan():
    d = {"a": math.nan, "b": [1.0, math.inf, {"c": -math.inf}], "d": 2, "e": "x"}
    assert json.dumps(nulled(d), allow_nan=False) == '{"a": null, "b": [1.0, null, {"c": null}], "d": 2, "e": "x"}'
    assert csv_row({"err_x_m": math.nan, "seed": 3}) == {"err_x_m": "", "seed": 3}


def test_a_ctrl_c_during_the_memos_save_at_exit_is_quiet(monkeypatch):
    def interrupted():
        raise KeyboardInterrupt
    monkeypatch.setattr(memo, "save_all", interrupted)
    memo._save_at_exit()            # no exception: the cache's unwritten rows are remade on demand


@pytest.mark.parametrize("spec", ["force-spike-at-depth-m=0.002:1e300", "side-push-at-s=1:5000",
                                  "ft-spike-at-s=1:-1e4"])
def test_an_absurd_injected_force_is_refused(spec):
    with pytest.raises(ValueError, match="a force X at most 1000 N"):
        parse(spec)
    assert parse("force-spike-at-depth-m=0.002:-999").x == -999.0


def test_the_cells_resume_in_another_world_is_refused(tmp_path, capsys):
    """A simulated cell run resumed with another sensor preset or seed (or truth, force model, mesh, force source)
    is refused before anything moves; with the same options it resumes (the review: 57 and 243 records of two
    worlds in one probes.jsonl, exit 0)."""
    path = tmp_path / "plan.json"
    make_plan().save(path)
    base = ["--sim", "--plan", str(path), "--out", str(tmp_path / "R"), "--force-model", "standin"]
    assert cell.main(base) == 0
    world = json.loads((tmp_path / "R" / "cell_world.json").read_text())
    assert world["sensor"] == "nano17" and world["arm"] == "simulated (inmemory)"
    before = (tmp_path / "R" / "probes.jsonl").read_bytes()
    capsys.readouterr()
    for extra, said in ((["--sensor", "ideal"], "sensor was 'nano17', now 'ideal'"), (["--seed", "5"], "seed was 0")):
        assert cell.main(base + extra) == 2
        err = capsys.readouterr().err
        assert "another arm or simulated world" in err and said in err, err
    assert (tmp_path / "R" / "probes.jsonl").read_bytes() == before
    assert cell.main(base) == 0
    assert cell.main(base + ["--sensor", "ideal", "--fresh"]) == 0        # (--fresh: the old run set aside)


def test_a_plan_whose_threshold_no_probe_can_pass_is_refused_before_anything(tmp_path, capsys):
    """The plan's contact threshold raised to 1.9 N (under the 2 N limit, so the plan checks pass) over probes
    predicted to press 0.1 N: `run --plan` and the cell refuse it in one line, exit 2, before anything moves (the
    review: exit 1 with contact_unfelt at the first probe, and "the same command resumes", which never could)."""
    plan = make_plan(motion=Motion(approach_height_m=0.004, dwell_s=0.2, contact_threshold_n=1.9))
    path = tmp_path / "plan.json"
    plan.save(path)
    assert cli.main(["run", "paper", "--sim", "--plan", str(path), "--out", str(tmp_path / "R")]) == 2
    assert cell.main(["--sim", "--plan", str(path), "--out", str(tmp_path / "C"), "--force-model", "standin"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all("refused before any motion: probe 0: the prior's force at the depth limit" in e
                                 and "motion.contact_threshold_n (1.9 N)" in e for e in err), err
    assert not (tmp_path / "R" / "probes.jsonl").exists() and not (tmp_path / "C" / "probes.jsonl").exists()
    ok = make_plan(motion=Motion(approach_height_m=0.004, dwell_s=0.2, contact_threshold_n=0.02))
    assert unfelt_probes(ok) == {}
