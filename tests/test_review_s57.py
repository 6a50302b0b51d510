"""Session 57: what session 56's bad-input review left for a next session."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from robot_fixtures import make_plan  # noqa: E402

from app import cell  # noqa: E402
from app.cli import main  # noqa: E402
from app.figure_names import PLAN_FIGURES  # noqa: E402
from core.textfile import InputFileError  # noqa: E402
from planner.tasks import array_of, load_piece, record_with, rows_with, run_pieces  # noqa: E402


def _double(shared, p):
    return [{"seed": p, "method": "x", "value": 2 * p}]


@pytest.mark.parametrize("text", ["42", '{"seed": 1}', '[{"seed": 1}]', '["a"]', "null"])
def test_a_study_piece_of_the_wrong_shape_is_named_not_a_traceback(tmp_path, text):
    """A piece that is valid JSON but not what its work writes (session 56's review: a traceback far from the file)
    is refused on reading, naming the file; a right one is read back and not computed again."""
    (tmp_path / "p1.json").write_text(text)
    with pytest.raises(InputFileError, match=r"p1\.json.*cannot be read back \(not a list of rows each with "
                                             r"'seed', 'method'\).*move it aside"):
        run_pieces(_double, None, [1, 2], ["p1", "p2"], store=tmp_path, shape=rows_with("seed", "method"))
    (tmp_path / "p1.json").unlink()
    (tmp_path / "p1.json").write_text('[{"seed": 1, "method": "x", "value": 7}]')
    got = run_pieces(_double, None, [1, 2], ["p1", "p2"], store=tmp_path, shape=rows_with("seed", "method"))
    assert got == [[{"seed": 1, "method": "x", "value": 7}], [{"seed": 2, "method": "x", "value": 4}]]


def test_record_and_array_shapes(tmp_path):
    (tmp_path / "r.json").write_text('{"index": 1}')
    with pytest.raises(InputFileError, match=r"not a record with 'rate'"):
        load_piece(tmp_path, "r", record_with("index", "rate"))
    assert load_piece(tmp_path, "r", record_with("index")) == {"index": 1}
    np.save(tmp_path / "a.npy", np.zeros((2, 3)))
    with pytest.raises(InputFileError, match=r"a\.npy.*not an array of numbers of shape \(3, 3\)"):
        load_piece(tmp_path, "a", array_of((3, 3)))
    assert load_piece(tmp_path, "a", array_of((2, 3))).shape == (2, 3)
    np.save(tmp_path / "s.npy", np.array(["a", "b"]))
    with pytest.raises(InputFileError, match=r"s\.npy.*not an array of numbers"):
        load_piece(tmp_path, "s", array_of((2,)))


def test_ft_reads_long_enough_to_count_a_rate(capsys):
    """`palpate ft --duration-s 1e-6` reported 0 records at 0 Hz, exit 0 (the box had sent nothing yet): a duration
    below 0.1 s is refused in one line; 0.1 s counts about a hundred records of the simulated box's 1 kHz."""
    assert main(["ft", "--ft", "netft", "--duration-s", "1e-6"]) == 2
    err = capsys.readouterr().err
    assert "--duration-s" in err and "[0.1, 600] s" in err and "'1e-6'" in err and "Traceback" not in err


@pytest.mark.parametrize("extra", [["--sensor", "ideal"], ["--seed", "3"], ["--force-model", "standin"],
                                   ["--sim-mesh-m", "0.004"]])
def test_the_cells_simulation_options_next_to_a_real_arm_are_refused(tmp_path, capsys, extra):
    """They did nothing with --host, silently (session 56's review): refused in one line before anything connects
    (127.0.0.9 has no controller: a connection attempt would be another error)."""
    path = tmp_path / "plan.json"
    make_plan().save(path)
    assert cell.main(["--host", "127.0.0.9", "--plan", str(path), "--out", str(tmp_path / "R"), "--yes"] + extra) == 2
    err = capsys.readouterr().err
    assert f"{extra[0]} " in err and "an option of the simulated arm (--sim)" in err and "Traceback" not in err
    assert not (tmp_path / "R").exists()


def test_a_run_next_to_a_real_arm_refuses_a_noise_seed(tmp_path, capsys):
    assert main(["run", "paper", "--host", "127.0.0.9", "--seed", "3", "--out", str(tmp_path / "R")]) == 2
    err = capsys.readouterr().err
    assert "--seed 3: the simulated sensor's noise seed" in err and not (tmp_path / "R").exists()


def test_an_injected_fault_that_cannot_fire_is_refused(tmp_path, capsys):
    """``disconnect-after-probes=99`` on 3 probes passed silently, the drill never run: refused, naming the count
    (and counting only the probes a resumed run still has to do); a depth trigger past the plan's depth limit is
    said."""
    path = tmp_path / "plan.json"
    plan = make_plan()
    plan.save(path)
    base = ["--sim", "--plan", str(path), "--out", str(tmp_path / "R"), "--force-model", "standin"]
    assert cell.main(base + ["--inject", "disconnect-after-probes=3"]) == 2      # (no move after the last probe)
    err = capsys.readouterr().err
    assert "--inject disconnect-after-probes=3: never fires: this run probes 3 times (N at most 2)" in err
    assert not (tmp_path / "R").exists()
    assert cell.main([*base[:4], str(tmp_path / "F"), *base[5:], "--inject", "disconnect-after-probes=2"]) == 1
    assert json.loads((tmp_path / "F" / "run.json").read_text())["fault"]["kind"] == "connection_lost"   # N = 2 fires
    capsys.readouterr()
    deep = plan.limits.depth_limit_m + 1e-3
    assert cell.main(base + ["--inject", f"stall-at-depth-m={deep}"]) == 0
    assert "fires only if the tip goes past the plan's depth limit" in capsys.readouterr().err
    assert json.loads((tmp_path / "R" / "run.json").read_text())["status"] == "ok"
    assert cell.main(base + ["--inject", "disconnect-after-probes=1"]) == 2      # all 3 done: this run probes none
    assert "this run probes 0 times (no after-probes fault can fire)" in capsys.readouterr().err


@pytest.mark.parametrize("cmd", [
    ["plan", "paper", "--out", "{d}/plan_joints.png", "--plots", "{d}"],
    ["plan", "paper", "--out", "{d}/p.json", "--json", "{d}/sub/../plan_raster.png", "--plots", "{d}"],
    ["predict", "paper", "--waypoints", "5", "--json", "{d}/fig11_predict.png", "--plots", "{d}"],
    ["simulate", "paper", "--json", "{d}/fig5_surface.png", "--plots", "{d}"],
    ["simulate", "paper", "--load", "indent", "--vtu", "{d}/x.vtu", "--json", "{d}/fig10_indent.png", "--plots", "{d}"],
])
def test_an_output_named_as_a_figure_of_plots_is_refused(tmp_path, capsys, cmd):
    """``plan --out X/plan_joints.png --plots X`` wrote the plan, then drew the figure over it, exit 0 (session 56's
    review): refused before any work, naming the option and the figure."""
    argv = [a.format(d=tmp_path) for a in cmd]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "is named as a figure that --plots" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_the_plan_figures_are_the_names_refused(tmp_path):
    """app.figure_names.PLAN_FIGURES (what plan refuses as an output) holds what plan --plots draws (2D here; the 3D
    plan's figures: tests/test_planner3d.py)."""
    assert main(["plan", "paper", "--waypoints", "5", "--out", str(tmp_path / "p.json"), "--plots", str(tmp_path)]) == 0
    assert {f.name for f in tmp_path.iterdir()} - {"p.json"} <= set(PLAN_FIGURES)
