"""Session 47: a depth the contact model cannot take names the option it came from (`--depth-m`, 2D and 3D), and
names the tighter of its bounds (the tip's radius or the linear model's strain limit), whichever that is."""
from __future__ import annotations

import dataclasses

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
