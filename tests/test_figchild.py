"""The run's figure drawn by a child process (app.figchild): the same file as drawn in the run's own process, and a
child that cannot draw costs a warning line, never the figure."""
from __future__ import annotations

import sys

import numpy as np

from app.figchild import FigureChild, draw
from planner.draw_run import RunFigure
from planner.draw_run3d import RunFigure3D, Section3D


def _fig2d(detected=True) -> RunFigure:
    rng = np.random.default_rng(3)
    x = np.sort(rng.uniform(0.005, 0.065, 20))
    xx = np.linspace(4.0, 66.0, 200)
    f0 = 0.05 + 0.001 * xx
    c = 0.02 * np.exp(-((xx - 35.0) / 6.0) ** 2)
    return RunFigure(width_m=0.07, height_m=0.05, x_m=x, force_n=rng.uniform(0.05, 0.1, 20),
                     sigma_n=np.full(20, 0.003), contrast_n=rng.normal(0, 0.004, 20), round_of=np.repeat([0, 1], 10),
                     curve_x_mm=xx, depths_m=[0.004], prior_n=[f0], fitted_n=[f0 + c if detected else None],
                     fit_contrast_n=[c if detected else None], detected=detected, lr=120.5, lr_threshold=15.0,
                     peak_x_m=0.0351, x_est_m=0.0352, depth_est_m=0.024, diameter_m=0.014, sigma_diameter_m=0.002,
                     sigma_x_m=2e-4, sigma_depth_m=2e-3, depth95_m=(0.021, 0.029),
                     truth_stones_m=[(0.035, 0.025, 0.0075)], title="a test figure")


def _fig3d() -> RunFigure3D:
    rng = np.random.default_rng(4)
    x, y = rng.uniform(0.01, 0.06, 30), rng.uniform(0.01, 0.06, 30)
    sel = np.zeros(30, bool)
    sel[:6] = True
    sec = [Section3D(along=a, fixed_m=0.035, levels_m=[0.004], selected=[sel], curve_m=[np.linspace(0.01, 0.06, 200)],
                     curve_n=[0.01 * np.sin(np.linspace(0, 3, 200))]) for a in (0, 1)]
    return RunFigure3D(x_m=x, y_m=y, sigma_n=np.full(30, 0.003), contrast_n=rng.normal(0, 0.01, 30), sections=sec,
                       detected=True, x_est_m=0.035, y_est_m=0.036, diameter_m=0.014,
                       cov_xy_m2=np.array([[4e-8, 1e-8], [1e-8, 9e-8]]), region_m=(0.01, 0.06, 0.01, 0.06),
                       truth_stones_m=[(0.035, 0.035, 0.007)], title="a 3D test figure")


def test_child_draws_the_same_file_as_this_process(tmp_path):
    for name, fig in (("a", _fig2d()), ("b", _fig2d(detected=False)), ("c", _fig3d())):
        said = []
        assert FigureChild().draw(tmp_path / f"{name}-child.png", fig, said.append) == "child" and not said
        draw(tmp_path / f"{name}-here.png", fig)
        child, here = (tmp_path / f"{name}-child.png").read_bytes(), (tmp_path / f"{name}-here.png").read_bytes()
        assert len(here) > 10_000 and child == here, name


def test_a_child_that_fails_or_hangs_costs_a_warning_not_the_figure(tmp_path):
    fails = [sys.executable, "-c", "import sys; sys.stdin.buffer.read(); print('ValueError: boom', file=sys.stderr); "
                                   "sys.exit(3)"]
    said = []
    assert FigureChild(fails).draw(tmp_path / "f.png", _fig2d(), said.append) == "here"
    assert (tmp_path / "f.png").stat().st_size > 10_000
    assert len(said) == 1 and "ValueError: boom" in said[0] and said[0].startswith("warning:")
    hangs = FigureChild([sys.executable, "-c", "import time; time.sleep(60)"])
    hangs.timeout_s = 0.5
    said = []
    assert hangs.draw(tmp_path / "g.png", _fig3d(), said.append) == "here"
    assert (tmp_path / "g.png").stat().st_size > 10_000 and "no answer within 0.5 s" in said[0]
    assert hangs.proc.returncode is not None           # killed, not left running


def test_an_unused_child_ends_when_closed(tmp_path):
    c = FigureChild()
    c.close()
    assert c.proc.returncode == 0
    c.close()                                           # twice: nothing more to do
