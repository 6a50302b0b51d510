"""Session 47: a depth the contact model cannot take names the option it came from (`--depth-m`, 2D and 3D), and
names the tighter of its bounds (the tip's radius or the linear model's strain limit), whichever that is."""
from __future__ import annotations

import dataclasses
import json
import os
import signal

import numpy as np
import pytest

from app.cli import main
from fem.contact import check_depth
from fem.scene import load


@pytest.mark.parametrize("argv", [["predict", "paper", "--waypoints", "3", "--force-only", "--quiet"],
                                  ["predict", "block3d", "--grid", "2x2", "--force-only", "--quiet"]])
@pytest.mark.parametrize("depth", ["0.05", "1e308"])
def test_predict_names_depth_m_when_fem_refuses_the_depth(argv, depth, capsys):
    assert main([*argv, "--depth-m", depth]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert f"--depth-m {float(depth):g} on scene " in err[0] and "tip radius" in err[0]


def test_the_tighter_bound_is_named():
    paper = load("paper")                     # tip radius 5 mm, tissue 50 mm: the tip's radius binds first
    with pytest.raises(ValueError, match="tip radius"):
        check_depth(paper, 0.02)
    # a 10 mm layer under a 20 mm cylinder: the strain limit (3 mm) binds first
    thin = dataclasses.replace(paper, tissue=dataclasses.replace(paper.tissue, height_m=0.01),
                               indenter=dataclasses.replace(paper.indenter, radius_m=0.02), stones=())
    with pytest.raises(ValueError, match="of the tissue height"):
        check_depth(thin, 0.005)
    with pytest.raises(ValueError, match="0 m or more"):
        check_depth(thin, -1e-3)
    check_depth(thin, 0.002)                 # within both


def test_a_users_own_dask_worker_preload_still_runs_beside_palpates(tmp_path, monkeypatch):
    """palpate's LocalCluster preloads its SIGINT hook (planner.tasks.dask_setup); an explicit preload replaces
    dask's distributed.worker.preload setting, so the user's own would silently not run: both run."""
    import dask
    import distributed  # noqa: F401 -- its config loaded first: set() would otherwise drop the whole section on exit

    from planner.tasks import Runner, dask_client
    (tmp_path / "users_preload_s47.py").write_text(
        "import os\n\ndef dask_setup(worker):\n"
        "    open(os.path.join(os.environ['S47_MARKS'], f'w{os.getpid()}'), 'w').close()\n")
    marks = tmp_path / "marks"
    marks.mkdir()
    monkeypatch.setenv("S47_MARKS", str(marks))
    monkeypatch.syspath_prepend(str(tmp_path))      # the nanny (here) and the workers it spawns import it
    with dask.config.set({"distributed.worker.preload": ["users_preload_s47"]}):
        with dask_client(Runner(workers=2, progress=False)) as client:
            handlers = client.run(lambda: signal.getsignal(signal.SIGINT))
            pids = client.run(os.getpid)
    assert set(handlers.values()) == {signal.SIG_IGN}                     # palpate's hook ran
    assert {p.name for p in marks.iterdir()} == {f"w{p}" for p in pids.values()}   # and the user's, in each worker


def test_a_block_file_that_leaves_out_the_tip_and_mesh_gets_a_blocks_not_a_sections(tmp_path):
    """A block's scene file with only [tissue] and a stone was refused for a cylinder it never named; given a
    sphere, it meshed 2D's 2 mm / 0.5 mm elements (about 700k DOFs) and was then refused for its patch's size."""
    from fem.scene import BLOCK3D_ANALYSIS, SceneError
    f = tmp_path / "blk.toml"
    stone = "[[stone]]\nx_m = 0.02\ny_m = 0.035\ndepth_m = 0.012\ndiameter_m = 0.008\n"
    f.write_text("[tissue]\nwidth_m = 0.05\nlength_m = 0.06\nheight_m = 0.03\nyoungs_pa = 6000\npoisson = 0.45\n"
                 + stone)
    sc = load(str(f))
    assert sc.indenter.shape == "sphere"
    a = sc.analysis
    assert (a.mesh_size_m, a.surface_refine, a.grade) == (BLOCK3D_ANALYSIS.mesh_size_m,
                                                          BLOCK3D_ANALYSIS.surface_refine, BLOCK3D_ANALYSIS.grade)
    assert a.patch_m is None                  # a face up to 50 mm across is probed whole
    # a wider face: a centred square with a 10 mm margin, at most block3d's 50 mm
    for width, patch in ((0.06, 0.04), (0.07, 0.05), (0.2, 0.05)):
        f.write_text(f"[tissue]\nwidth_m = {width}\nlength_m = 0.08\nheight_m = 0.03\nyoungs_pa = 6000\n"
                     f"poisson = 0.45\n" + stone)
        assert load(str(f)).analysis.patch_m == pytest.approx(patch)
    # what a file gives is kept; a section's defaults stay a section's
    f.write_text(f.read_text() + '[indenter]\nshape = "flat"\n[analysis]\nsurface_refine = 4.0\npatch_m = 0.03\n')
    sc = load(str(f))
    assert (sc.indenter.shape, sc.analysis.surface_refine, sc.analysis.patch_m) == ("flat", 4.0, 0.03)
    assert load("paper").indenter.shape == "cylinder" and load("paper").analysis.mesh_size_m == 0.002
    f.write_text(f.read_text().replace('"flat"', '"cylinder"'))
    with pytest.raises(SceneError, match="'sphere' or 'flat'"):
        load(str(f))


def test_a_block_file_reads_back_equal_or_is_not_written(tmp_path):
    """dump_toml writes what load_toml reads back equal; a block whose patch or grading is unset cannot be said in a
    file (a file without them gets a block file's defaults), so it is refused, not written to read back otherwise."""
    from fem.scene import dump_toml
    for sc in (load("block3d"), load("block3d-healthy").with_analysis(order=1)):
        f = tmp_path / "b.toml"
        f.write_text(dump_toml(sc))
        assert load(str(f)) == sc
    with pytest.raises(ValueError, match="patch_m or analysis.grade unset"):
        dump_toml(load("block3d").with_analysis(patch_m=None))


@pytest.mark.parametrize("changes", [{}, {"patch_m": None, "grade": None}, {"order": 1, "surface_refine": 3.0}])
def test_a_blocks_dict_reads_back_unchanged(changes):
    """plan.json and the studies' pieces carry the prior as Scene.to_dict(): a block's reads back equal, whatever
    the fields the block defaults fill in a hand-written file."""
    from fem.scene import from_dict
    for name in ("block3d", "block3d-healthy"):
        sc = load(name).with_analysis(**changes)
        assert from_dict(sc.to_dict(), default_name=sc.name) == sc


def test_a_tissue_parameter_at_its_bound_is_said(tmp_path, capsys):
    """A session-47 review: a rigid 8 mm stone 7 mm from the side (outside the table's stone positions) was
    reported 32 mm away with a 0.5 mm sigma; the fit had stretched the tissue's thickness to its bound, which no
    warning named (only the stone's own parameters were checked)."""
    from planner.localize import nuisance_at_bound
    names = (None, "stiffness_scale", "thickness_scale", "finite_strain_amplitude")
    lo, hi = np.array([-np.inf, -1.5, -0.25, 0.0]), np.array([np.inf, 1.5, 0.25, 5.0])
    free = np.array([True, True, True, True])
    assert nuisance_at_bound([1e9, 0.0, -0.25, 0.0], free, lo, hi, names) == ["thickness_scale"]   # a = 0: linear
    assert nuisance_at_bound([0.0, 1.5, 0.1, 5.0], free, lo, hi, names) == ["stiffness_scale",
                                                                              "finite_strain_amplitude"]
    assert nuisance_at_bound([0.0, 0.0], np.array([True, False, True, False]), lo, hi, names) == []
    scene = tmp_path / "edge7.toml"
    scene.write_text('name = "edge7"\n[tissue]\nwidth_m = 0.070\nheight_m = 0.050\nyoungs_pa = 2500\npoisson = 0.4\n'
                     '[[stone]]\nx_m = 0.007\ndepth_m = 0.012\ndiameter_m = 0.008\nyoungs_pa = 5.0e9\npoisson = 0.3\n')
    assert main(["run", str(scene), "--sim", "--out", str(tmp_path / "o"), "--no-figure"]) == 0
    final = capsys.readouterr().out.strip().splitlines()[-1]
    result = json.loads((tmp_path / "o" / "result.json").read_text())
    # session 47: 39 mm, with the thickness at its bound said; since session 49 the table's stone positions reach
    # 5 mm from the side (the coarse raster's first probe) and the stone is found (7.52 +- 0.15 mm, 11.47 mm deep)
    assert abs(result["estimate"]["x_m"]["value"] - 0.007) < 0.0015, final
    assert abs(result["estimate"]["depth_m"]["value"] - 0.012) < 0.002, final


@pytest.mark.parametrize("depth, warned", [("0.0002", True), ("0.003", False)])
def test_a_2d_contact_the_top_mesh_does_not_resolve_is_warned(depth, warned, capsys):
    """A session-47 review: 2D said nothing below one element across the contact (force -9 to +11 %, pressure and
    stress peaks to 50 % off), where 3D warns. The paper section's top elements are 0.5 mm: at 0.2 mm deep the
    half-width is 0.63 mm (1.3 elements), at 3 mm 2.6 mm (5.3)."""
    assert main(["simulate", "healthy", "--load", "indent", "--x-m", "0.035", "--depth-m", depth]) == 0
    err = [e for e in capsys.readouterr().err.splitlines() if "warning" in e]
    assert bool(err) == warned, err
    if warned:
        assert len(err) == 1 and "the contact half-width spans 1.3 of the top's elements (0.5 mm)" in err[0]


def test_a_tool_offset_edited_by_under_a_millimetre_is_refused():
    """A session-47 review: frames.tcp_offset z edited from 0.1 to 0.0991 m passed robot.safety.check_plan (the joint
    agreement's tolerance was 1 mm), and the real tip, with the tool unchanged, would go 0.9 mm past the depth
    limit. The planner's joints agree with its poses to round-off, so the tolerance is now 10 um."""
    from robot.safety import check_plan
    from tests.robot_fixtures import make_plan
    plan = make_plan()
    assert check_plan(plan) == ([], {})
    off = list(plan.frames.tcp_offset)
    off[2] -= 0.0009
    edited = dataclasses.replace(plan, frames=dataclasses.replace(plan.frames, tcp_offset=off))
    problems, bad = check_plan(edited)
    assert bad and all("does not reach its pose" in why for why in bad.values()), (problems, bad)


@pytest.mark.parametrize("extra", [["--tcp-offset", "0", "0", "0.1", "3.14159", "0", "0"],
                                   ["--tcp-offset", "0", "0.05", "0.08", "1.5708", "0", "0"]])
def test_a_plan_whose_flange_would_go_into_the_tissue_is_refused(extra, tmp_path, capsys):
    """A session-47 review: only the tip was checked; a tool rotated about x put the flange under the tissue's
    surface. `palpate plan` and robot.safety.check_plan (which the run and the driver apply) now refuse it."""
    says = "the flange lies"
    out = tmp_path / "p.json"
    assert main(["plan", "paper", "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the driver would refuse this plan" in err[0] and says in err[0], err
    assert not out.exists()
    assert main(["plan", "paper", "--out", str(out)]) == 0          # the default branch and tool are clear
