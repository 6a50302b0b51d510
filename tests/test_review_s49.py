"""Session 49: bad input and small defects left from session 48's reviews."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

import fem.contact as fc
from app import cell
from app.cli import build_parser, main
from app.errors import UsageError
from app.runexec import check_resume, run_options, unplaced, verdict, verdict_kind
from core.contracts import PlanError
from fem import cachesize
from fem.scene import SceneError, Stone, block_file_defaults, from_dict, load, tip_taken_as_rigid
from fem.tip import treated_as_rigid
from planner.area import check_positions
from planner.localize import Localization
from planner.localize3d import Localization3D
from planner.surrogate import _forces, _past_the_crush_limit, stone_model

ROOT = Path(__file__).resolve().parents[1]
# the first argument of every call that names a cache entry's kind, the 3D table's calibrations, and KIND constants
_KIND_USE = re.compile(r"(?<!\w)(?:load_or_build|diskcache\.load|entry_path|memo|cached_fingerprint)\(\s*\"([a-z0-9]+)\"|"
                       r"^KIND = \"([a-z0-9]+)\"|f\"([a-z0-9]+)-\{key\}\.npz\"", re.M)


def test_the_cache_kinds_listed_are_exactly_those_the_code_writes():
    found = set()
    for f in (*ROOT.glob("fem/*.py"), *ROOT.glob("planner/*.py")):
        text = f.read_text()
        found |= {next(g for g in m.groups() if g) for m in _KIND_USE.finditer(text)}
        if "-cal-" in text:
            found |= {f"{k}-cal" for k in re.findall(r"def cache_path.*?f\"([a-z0-9]+)-\{key\}", text, re.S)}
    assert len(found) >= 15
    assert found == cachesize.KINDS


def test_cache_clear_refuses_a_kind_that_is_not_one(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path))
    assert main(["cache", "clear", "--kind", "factor3"]) == 2
    err = capsys.readouterr().err
    assert "--kind 'factor3'" in err and "factor3d" in err and len(err.strip().splitlines()) == 1
    assert main(["cache", "clear", "--kind", "factor3d"]) == 0       # a real kind with no entries: nothing to do
    assert "no entries of kind factor3d" in capsys.readouterr().out


def test_cell_says_a_bad_sim_mesh_as_its_option(tmp_path, capsys):
    assert main(["plan", "paper", "--out", str(tmp_path / "plan.json")]) == 0
    capsys.readouterr()
    rc = cell.main(["--sim", "--plan", str(tmp_path / "plan.json"), "--sim-mesh-m", "0.5", "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("palpate-cell: --sim-mesh-m 0.5: ") and "larger than half the tissue" in err
    assert not (tmp_path / "r" / "probes.jsonl").exists()


def test_a_prior_file_edited_between_runs_is_another_run(tmp_path):
    """The prior was compared by its path: a run resumed on a prior file edited since (another stiffness) mixed
    the two beliefs' rounds. Its content key is kept now, as the scene's."""
    prior = tmp_path / "belief.toml"
    prior.write_text('''name = "belief"
[tissue]
width_m = 0.07
height_m = 0.05
youngs_pa = 2500.0
poisson = 0.4
''')
    def opts(path):
        args = build_parser("run").parse_args(["run", "paper", "--sim", "--prior", str(path), "--out", "x"])
        return run_options(args, load("paper"), None, load(str(path)).prior())
    first = opts(prior)
    out = tmp_path / "run"
    out.mkdir()
    (out / "run_options.json").write_text(json.dumps(first))
    (out / "probes.jsonl").write_text("")
    copy = tmp_path / "copy.toml"
    copy.write_text(prior.read_text())
    assert check_resume(out, opts(copy), fresh=False)              # the same content by another path resumes
    prior.write_text(prior.read_text().replace("2500.0", "1800.0"))
    with pytest.raises(UsageError, match="prior_key was"):
        check_resume(out, opts(prior), fresh=False)
    older = {k: v for k, v in first.items() if k != "prior_key"}   # a run kept before the key: the path decides
    (out / "run_options.json").write_text(json.dumps(older))
    assert check_resume(out, opts(prior), fresh=False)


def test_fresh_refuses_an_input_that_is_one_of_the_runs_own_files(tmp_path, capsys):
    """`--fresh --plan OUT/plan_round1.json` kept that file in OUT as the command's input; the new run then took it
    for its own round 1 (the coarse raster again in place of the refinement)."""
    out = tmp_path / "run"
    out.mkdir()
    assert main(["plan", "paper", "--out", str(out / "plan_round1.json")]) == 0
    (out / "probes.jsonl").write_text("")
    (out / "run_options.json").write_text("{}")
    capsys.readouterr()
    rc = main(["run", "paper", "--sim", "--plan", str(out / "plan_round1.json"), "--fresh", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and "--plan " in err and "copy it out of" in err
    assert sorted(p.name for p in out.iterdir()) == ["plan_round1.json", "probes.jsonl", "run_options.json"]


def test_a_stone_near_the_far_side_is_found(tmp_path, capsys):
    """A 6 mm stone 7 mm from the right side, 10 mm deep: with the table's stone positions at 10-60 mm it was
    reported at x 31.3 +- 0.6 mm (LR 304, only a poor-fit warning); the table now reaches 5-65 mm, as the coarse
    raster does (62.84 +- 0.23 mm)."""
    scene = tmp_path / "edge63.toml"
    scene.write_text('name = "edge63"\n[tissue]\nwidth_m = 0.070\nheight_m = 0.050\nyoungs_pa = 2500\npoisson = 0.4\n'
                     '[[stone]]\nx_m = 0.063\ndepth_m = 0.010\ndiameter_m = 0.006\nyoungs_pa = 5.0e9\npoisson = 0.3\n')
    assert main(["run", str(scene), "--sim", "--out", str(tmp_path / "o"), "--no-figure"]) == 0
    final = capsys.readouterr().out.strip().splitlines()[-1]
    est = json.loads((tmp_path / "o" / "result.json").read_text())["estimate"]
    assert abs(est["x_m"]["value"] - 0.063) < 0.0015 and abs(est["depth_m"]["value"] - 0.010) < 0.002, final


@pytest.mark.parametrize("kind", ["device", "pipe", "deep-toml"])
def test_a_scene_that_is_no_regular_file_or_nested_too_deep_is_one_line(kind, tmp_path, capsys):
    """/dev/zero filled the memory (a MemoryError traceback under a memory limit), a pipe blocked the command for
    good, a file nested 5000 levels deep overflowed the TOML parser (a RecursionError traceback)."""
    import os
    spec = {"device": "/dev/zero", "pipe": str(tmp_path / "p.toml"), "deep-toml": str(tmp_path / "d.toml")}[kind]
    if kind == "pipe":
        os.mkfifo(spec)
    if kind == "deep-toml":
        Path(spec).write_text("name = " + "[" * 5000 + "]" * 5000 + "\n")
    assert main(["predict", spec, "--waypoints", "3", "--force-only"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and spec in err
    assert {"device": "is a device", "pipe": "is a pipe", "deep-toml": "nested too deeply"}[kind] in err


def test_a_plan_nested_too_deep_or_a_device_is_one_line(tmp_path, capsys):
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100000 + "]" * 100000)
    for plan in (str(deep), "/dev/zero"):
        rc = cell.main(["--sim", "--plan", plan, "--out", str(tmp_path / "r")])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and len(err.splitlines()) == 1 and plan in err, err


def _loc(cls=Localization, **k):
    base = dict(detected=True, lr=20.2, lr_threshold=20.0, x_m=0.0229, depth_m=0.010, diameter_m=0.017,
                sigma_x_m=0.0699, sigma_depth_m=0.276, sigma_diameter_m=0.436, chi2_0=3830.0, chi2_1=3810.0, dof_1=32)
    return cls(**{**base, **k})


def test_a_detection_the_fit_cannot_place_is_not_said_as_a_stone():
    """A session-49 review: a sensor drifting 0.01 N/s gave LR 20.2 (threshold 20) with chi2 3810 on 32 degrees
    of freedom, and the last line said STONE at x 22.93 +- 69.94 mm, depth 10 +- 276 mm."""
    tissue = load("paper").tissue
    line = verdict(_loc(), object(), "stone at x 22.93 +- 69.94 mm", "ok", None, None, tissue)
    assert line.startswith("NOT LOCALIZED: the likelihood ratio (20, threshold 20) says a stone") and "69.9 mm" in line
    assert verdict_kind(line) == "not_localized"
    # the studies' widest detected estimate (a 6.5 mm stone 39 mm deep: 5.4 mm across, 21.8 mm in depth) is a stone
    assert unplaced(_loc(sigma_x_m=0.0054, sigma_depth_m=0.0218), tissue) is None
    assert verdict(_loc(sigma_x_m=0.0054, sigma_depth_m=0.0218), object(), "s", "ok", None, None, tissue) == "STONE s"
    assert "depth sigma" in unplaced(_loc(sigma_x_m=0.001, sigma_depth_m=0.051), tissue)
    assert unplaced(_loc(detected=False), tissue) is None                  # NO STONE stays what it is
    assert "its x sigma" in unplaced(_loc(sigma_x_m=float("nan")), tissue)
    block = load("block3d").tissue
    assert "its y sigma" in unplaced(_loc(Localization3D, sigma_x_m=0.001, sigma_y_m=block.length_m / 3,
                                          sigma_depth_m=0.002), block)


def test_a_belief_with_another_tip_than_the_truths_is_refused(tmp_path, capsys):
    """A 3 mm truth tip under a 5 mm belief ran: the plan pressed 4 mm with the 3 mm tip (beyond its radius) and the
    line said STONE. The tip is the instrument: the belief and the simulated world share it, as they share the
    tissue's extent."""
    truth = tmp_path / "t3.toml"
    truth.write_text('name = "t3"\n[tissue]\nwidth_m = 0.07\nheight_m = 0.05\nyoungs_pa = 2500.0\npoisson = 0.4\n'
                     '[indenter]\nradius_m = 0.003\n')
    assert main(["run", str(truth), "--prior", "healthy", "--sim", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "indenter.radius_m = 0.005 m" in err and "is 0.003 m" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o" / "probes.jsonl").exists()


def test_a_refused_default_says_its_limit_and_that_it_was_a_default(tmp_path, capsys):
    """A 3 mm section without [analysis] was refused for 'analysis.mesh_size_m=0.002 is larger than half the
    tissue', a value the user never wrote, with no limit; load A's default on a 5 mm tissue the same."""
    thin = tmp_path / "thin.toml"
    thin.write_text('name = "thin"\n[tissue]\nwidth_m = 0.07\nheight_m = 0.003\nyoungs_pa = 2500.0\npoisson = 0.4\n')
    assert main(["predict", str(thin), "--depth-m", "0.0005", "--force-only"]) == 2
    err = capsys.readouterr().err
    assert "height_m (0.003 m)" in err and "mesh_size_m <= 0.0015" in err and "default" in err
    five = tmp_path / "five.toml"
    five.write_text(thin.read_text().replace("0.003", "0.005").replace('"thin"', '"five"'))
    assert main(["simulate", str(five), "--load", "uniform"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"palpate: scene {five}: ") and "default 0.005" in err and "at most 0.0015 m" in err


def test_a_3d_tip_with_a_2d_thickness_is_refused():
    d = load("block3d").to_dict()
    d["indenter"]["thickness_m"] = 5.0
    with pytest.raises(SceneError, match="indenter.thickness_m = 5.0 is a 2D tip's"):
        from_dict(d)


def test_compare_says_it_probes_the_reference_with_the_scenes_tip(tmp_path, capsys):
    ref = tmp_path / "ref.toml"
    ref.write_text('name = "ref"\n[tissue]\nwidth_m = 0.07\nheight_m = 0.05\nyoungs_pa = 2500.0\npoisson = 0.4\n'
                   '[indenter]\nradius_m = 0.003\n')
    assert main(["predict", "healthy", "--compare", str(ref), "--waypoints", "3", "--force-only"]) == 0
    assert "its [indenter] differs from scene healthy's" in capsys.readouterr().err
    same = tmp_path / "same.toml"          # a file's rigid default tip against the built-in's 60 MPa one: the same
    same.write_text(ref.read_text().replace("radius_m = 0.003", "radius_m = 0.005"))
    assert main(["predict", "healthy", "--compare", str(same), "--waypoints", "3", "--force-only"]) == 0
    assert "differs" not in capsys.readouterr().err


def test_a_soft_truth_tip_under_a_rigid_belief_is_refused(tmp_path, capsys):
    soft = tmp_path / "soft.toml"
    soft.write_text('name = "soft"\n[tissue]\nwidth_m = 0.07\nheight_m = 0.05\nyoungs_pa = 2500.0\npoisson = 0.4\n'
                    '[indenter]\nradius_m = 0.005\nyoungs_pa = 20000.0\n')
    assert main(["run", str(soft), "--prior", "paper", "--sim", "--out", str(tmp_path / "o")]) == 2
    assert "the tip is rigid but the simulated truth's" in capsys.readouterr().err


def test_cell_refuses_a_too_fine_sim_mesh_before_the_pre_flight(tmp_path, capsys):
    """A --sim-mesh-m too fine passed the early check and was refused after the pre-flight, naming the field."""
    assert main(["plan", "paper", "--out", str(tmp_path / "plan.json")]) == 0
    capsys.readouterr()
    rc = cell.main(["--sim", "--plan", str(tmp_path / "plan.json"), "--sim-mesh-m", "0.00001",
                    "--out", str(tmp_path / "r")])
    err = capsys.readouterr()
    assert rc == 2 and err.err.startswith("palpate-cell: --sim-mesh-m 1e-05: ") and "pre-flight" not in err.out
    assert "top-surface nodes" in err.err and not (tmp_path / "r").exists()


def test_cell_fresh_keeps_its_truth_file_in_out(tmp_path, capsys):
    """--fresh moved a --truth file kept in OUT aside with the previous run; the simulator then could not read it."""
    out = tmp_path / "co"
    out.mkdir()
    assert main(["plan", "paper", "--out", str(tmp_path / "plan.json")]) == 0
    truth = out / "truth.toml"
    truth.write_text('name = "t"\n[tissue]\nwidth_m = 0.07\nheight_m = 0.05\nyoungs_pa = 2500.0\npoisson = 0.4\n'
                     '[indenter]\nyoungs_pa = 6.0e7\npoisson = 0.3\n')
    (out / "run.json").write_text("{}")
    (out / "probes.jsonl").write_text("")
    rc = cell.main(["--sim", "--plan", str(tmp_path / "plan.json"), "--truth", str(truth), "--fresh",
                    "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    assert truth.exists() and len((out / "probes.jsonl").read_text().splitlines()) >= 15
    (moved,) = [p for p in out.iterdir() if p.name.startswith("previous-")]
    assert sorted(p.name for p in moved.iterdir()) == ["probes.jsonl", "run.json"]


def test_a_3d_waypoint_refusal_says_the_whole_face_not_none():
    """A block file's patch left out is the whole top face; the refusal printed 'analysis.patch_m = None'."""
    sc = from_dict(block_file_defaults({"name": "b40", "tissue": {"width_m": 0.04, "length_m": 0.04, "height_m": 0.03,
                                                                  "youngs_pa": 3000.0, "poisson": 0.45}}))
    with pytest.raises(PlanError, match=r"the whole top face \(analysis.patch_m not given\)") as e:
        check_positions(sc, [(0.001, 0.02)], "--positions")
    assert "None" not in str(e.value)


def test_the_table_takes_the_linear_models_force_past_the_crush_limit(monkeypatch):
    """The paper table was built before fem refused a probe pressing more than 75 % of the layer over a stone, and
    held the linear model's forces there; tables built since continued them with a power law, which fit the study's
    shallow stones' depths worse (67 % against 100 % within 2 sigma). The build asks fem past the limit again (and
    leaves fem's limit as it was); the accuracy study's truth keeps its own continuation."""
    prior = load("paper").prior().with_analysis(mesh_size_m=0.004)
    model = stone_model(prior.with_stones([Stone(x_m=0.035, depth_m=0.006, diameter_m=0.008)]))   # layer 2 mm
    levels, x0 = [0.001, 0.0015, 0.003], [0.035]
    with pytest.raises(ValueError, match="crushed"):
        model.force_n(0.035, 0.003)                             # fem itself still refuses it
    past = _forces(model, levels, x0)
    assert fc.STONE_LAYER_MAX == 0.75 and np.isfinite(past).all()
    continued = _forces(model, levels, x0, past_crush=False)
    assert np.allclose(past[:2], continued[:2])                 # within the limit: the same forces
    monkeypatch.setattr(fc, "STONE_LAYER_MAX", float("inf"))
    own = model.force_n(0.035, 0.003)                           # the linear model's own force there
    assert past[2, 0] == pytest.approx(own, rel=1e-12)
    assert abs(continued[2, 0] - own) > 1e-3 * own              # the power law's is another (2.2 % here)


def test_the_crush_limit_comes_back_when_the_last_overlapping_build_ends():
    """Two stones built at once in one process (a dask worker with two threads): the first to finish must not
    restore fem's limit under the second."""
    first, second = _past_the_crush_limit(), _past_the_crush_limit()
    first.__enter__()
    second.__enter__()
    first.__exit__(None, None, None)
    assert fc.STONE_LAYER_MAX == float("inf")
    second.__exit__(None, None, None)
    assert fc.STONE_LAYER_MAX == 0.75


@pytest.mark.parametrize("tip_pa", [None, 6.0e7, 2.5e6, 2.0e4])
def test_the_light_rigid_tip_test_is_fems(tip_pa):
    """fem.scene.tip_taken_as_rigid (for the CLI's checks, without importing fem.tip) says what fem models."""
    d = load("paper").to_dict()
    d["indenter"]["youngs_pa"] = tip_pa
    if tip_pa is None:
        del d["indenter"]["youngs_pa"]
    sc = from_dict(d)
    assert tip_taken_as_rigid(sc) == treated_as_rigid(sc)
