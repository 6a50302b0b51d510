"""Bad input found by an independent review (session 33): each is refused in one line naming the option or field,
exit 2, before any file is written; or (a [truth] table in a scene file without the .toml suffix) now read."""
from __future__ import annotations

import json

import pytest

from app.cli import main


def _run(argv, capsys) -> tuple[int, str]:
    try:
        rc = main(argv)
    except SystemExit as e:          # argparse's own refusal (usage, then the one error line)
        rc = e.code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, err.strip().splitlines()[-1] if err.strip() else ""


def _fake_run_dir(d):
    d.mkdir()
    (d / "run_options.json").write_text(json.dumps({"scene": "paper"}))
    (d / "plan_round0.json").write_text("{}")
    (d / "result.json").write_text("{}")


@pytest.mark.parametrize("name", ["run_options.json", "plan_round0.json", "result.json"])
def test_another_commands_output_never_replaces_a_runs_files(tmp_path, capsys, name):
    _fake_run_dir(tmp_path / "run")
    target = tmp_path / "run" / name
    before = target.read_text()
    rc, line = _run(["plan", "paper", "--waypoints", "3", "--out", str(target)], capsys)
    assert rc == 2 and "--out" in line and "run's data" in line
    rc, line = _run(["simulate", "paper", "--json", str(target)], capsys)
    assert rc == 2 and "--json" in line
    assert target.read_text() == before


def test_plan_json_is_not_the_plan_file(tmp_path, capsys):
    f = tmp_path / "same.json"
    rc, line = _run(["plan", "paper", "--waypoints", "3", "--out", str(f), "--json", str(f)], capsys)
    assert rc == 2 and "--json" in line and not f.exists()


@pytest.mark.parametrize("argv, opt", [
    (["run", "paper", "--host", "", "--yes"], "--host"),               # an unset $ROBOT_IP: never the simulator
    (["run", "paper", "--host", "a b", "--yes"], "--host"),
    (["run", "paper", "--sim", "--seed", "-1"], "--seed"),
    (["run", "paper", "--sim", "--refine-waypoints", "2"], "--refine-waypoints"),
    (["run", "block3d", "--sim", "--refine-waypoints", "3"], "--refine-waypoints"),
    (["run", "paper", "--sim", "--truth-relaxation-tau-s", "5"], "--truth-relaxation-tau-s"),
])
def test_run_options_refused_before_out_is_touched(tmp_path, capsys, argv, opt):
    rc, line = _run([*argv, "--out", str(tmp_path / "run")], capsys)
    assert rc == 2 and opt in line
    assert not (tmp_path / "run").exists()


def test_a_plan_and_a_raster_size_are_not_both_taken(tmp_path, capsys):
    plan = tmp_path / "plan.json"
    assert main(["plan", "paper", "--waypoints", "3", "--out", str(plan)]) == 0
    capsys.readouterr()
    rc, line = _run(["run", "paper", "--sim", "--plan", str(plan), "--waypoints", "9", "--out",
                     str(tmp_path / "run")], capsys)
    assert rc == 2 and "--waypoints" in line and not (tmp_path / "run").exists()


def test_a_stone_under_the_tip_is_refused_by_predict_in_one_line(tmp_path, capsys):
    scene = tmp_path / "stone_at_top.toml"
    scene.write_text("[tissue]\nwidth_m = 0.070\nheight_m = 0.050\nyoungs_pa = 2500.0\npoisson = 0.4\n"
                     "[[stone]]\nx_m = 0.035\ndepth_m = 0.0051\ndiameter_m = 0.010\n")
    rc, line = _run(["predict", str(scene), "--waypoints", "5", "--json", str(tmp_path / "p.json")], capsys)
    assert rc == 2 and "--depth-m" in line and "crushed" in line and not (tmp_path / "p.json").exists()


def test_an_infinite_dof_cap_is_named(monkeypatch, capsys):
    monkeypatch.setenv("PALPATE_MAX_DOFS", "inf")
    rc, line = _run(["simulate", "paper"], capsys)
    assert rc == 2 and "PALPATE_MAX_DOFS" in line


def test_a_truth_table_is_read_whatever_the_files_suffix(tmp_path):
    from fem.scene import dump_toml, load
    from robot.truth import conditions_of
    f = tmp_path / "truth_ok.txt"
    f.write_text(dump_toml(load("paper")) + "\n[truth]\nsurface_offset_m = 0.003\n")
    assert conditions_of(str(f)).surface_offset_m == 0.003
    assert conditions_of("paper").ideal


def test_a_sweep_without_stones_writes_no_nan(tmp_path):
    import math

    import numpy as np

    from fem import scene as S
    from fem.sweep import check_scene
    row = check_scene(S.load("paper").prior(), np.random.default_rng(0))
    assert row["min_gap_m"] is None
    json.dumps(row, allow_nan=False)
    assert all(not (isinstance(v, float) and not math.isfinite(v)) for v in row.values())


@pytest.mark.parametrize("argv, opt", [
    (["simulate", "paper", "--x-m", "0.03"], "--x-m"),                  # load A: the indentation's options
    (["simulate", "paper", "--load", "uniform", "--depth-m", "0.003"], "--depth-m"),
    (["simulate", "paper", "--indenter-radius-m", "0.003"], "--indenter-radius-m"),
    (["predict", "block3d", "--waypoints", "5"], "--waypoints"),        # a block's waypoints are a grid
    (["predict", "block3d", "--grid", "2x2", "--margin-m", "0.03"], "--margin-m"),
])
def test_options_that_would_be_ignored_are_refused(capsys, argv, opt):
    rc, line = _run(argv, capsys)
    assert rc == 2 and opt in line
