"""The run's figure drawn by a child process (app.figchild): the same file as drawn in the run's own process, and a
child that cannot draw costs a warning line, never the figure."""
from __future__ import annotations

import sys
import time

import numpy as np
import pytest

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


def test_the_child_draws_with_the_parents_code_wherever_it_is_started(tmp_path, monkeypatch):
    """The child searches the parent's module path: a directory it is started from that holds other ``app`` or
    ``planner`` packages (an old checkout) is not where its code comes from."""
    for pkg in ("app", "planner"):
        (tmp_path / pkg).mkdir()
        (tmp_path / pkg / "__init__.py").write_text("raise ImportError('the wrong checkout')\n")
    monkeypatch.chdir(tmp_path)
    said = []
    assert FigureChild().draw(tmp_path / "f.png", _fig2d(), said.append) == "child" and not said


def test_no_child_on_a_single_core(monkeypatch):
    import os
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0}, raising=False)
    said = []
    assert FigureChild.start(said.append) is None and not said      # a choice, not a failure: nothing to say


def test_a_child_that_cannot_start_costs_a_warning_not_the_run(tmp_path, monkeypatch):
    import os
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)      # two cores
    said = []
    assert FigureChild.start(said.append, [str(tmp_path / "no-such-python")]) is None
    assert len(said) == 1 and said[0].startswith("warning: no child process for the figure")


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
    silent = [sys.executable, "-c", "import sys; sys.stdin.buffer.read()"]     # ends well, draws nothing
    said = []
    assert FigureChild(silent).draw(tmp_path / "h.png", _fig2d(), said.append) == "here"
    assert (tmp_path / "h.png").stat().st_size > 10_000 and "it wrote no file" in said[0]


def test_an_unused_child_ends_when_closed_without_being_waited_for(tmp_path):
    c = FigureChild()
    t = time.perf_counter()
    c.close()
    c.close()                                           # twice: nothing more to do
    assert time.perf_counter() - t < 0.2                # not waited for (its warm-up takes about 0.5 s)
    assert c.proc.wait(timeout=30) == 0                 # it ends on its own


def test_only_a_simulated_run_with_a_figure_starts_a_child(tmp_path, monkeypatch):
    """Next to a real arm (--host) the control host's cores are left to the driver: no child is started."""
    import app.cli
    import app.commands.run as run_command
    started = []
    monkeypatch.setattr(run_command.FigureChild, "start", classmethod(lambda cls, say, cmd=None: started.append(1)))

    class Planned(Exception):
        """Raised where the run plans: after the figure child is (or is not) started, before any arm is reached."""

    def plan_raster(*a, **k):
        raise Planned
    monkeypatch.setattr(run_command, "plan_raster", plan_raster)
    for i, (where, n) in enumerate(((["--host", "192.0.2.1"], 0), (["--sim", "--no-figure"], 0), (["--sim"], 1))):
        args = app.cli.build_parser("run").parse_args(["run", "paper", *where, "--out", str(tmp_path / str(i))])
        with pytest.raises(Planned):
            args.func(args)
        assert len(started) == n, where


@pytest.mark.parametrize("where, cores, workers", [(["--sim"], 2, 2), (["--sim"], 1, 1),
                                                   (["--host", "192.0.2.1"], 2, 1), (["--sim", "--fit-workers", "3"], 1, 3),
                                                   (["--sim", "--fit-workers", "1"], 2, 1),
                                                   (["--host", "192.0.2.1", "--fit-workers", "1"], 2, 1)])
def test_only_a_simulated_run_forks_its_fits(tmp_path, monkeypatch, where, cores, workers):
    """The localizer's fits go on two processes (planner.forkmap) in a simulated run on two cores, or on
    --fit-workers; next to a real arm the driver's process never forks (it holds ur_rtde's threads and sockets), nor
    by default on one core."""
    import app.cli
    import app.commands.run as run_command
    import app.runexec
    monkeypatch.setattr(run_command.FigureChild, "start", classmethod(lambda cls, say, cmd=None: None))
    monkeypatch.setattr(app.runexec, "usable_cores", lambda: cores)
    monkeypatch.setattr(run_command, "choose_executor", lambda *a: (None, "test arm", None))
    seen = []

    class Probing(Exception):
        """Raised where the run starts probing: the fits' workers are decided by then."""

    def adaptive(*a, **k):
        seen.append(k["workers"])
        raise Probing
    monkeypatch.setattr(run_command, "adaptive", adaptive)
    args = app.cli.build_parser("run").parse_args(["run", "paper", *where, "--out", str(tmp_path / "run")])
    with pytest.raises(Probing):
        args.func(args)
    assert seen == [workers]


@pytest.mark.parametrize("value, what", [("2", "next to a real arm"), ("0", "--fit-workers"), ("x", "--fit-workers")])
def test_a_real_arms_run_refuses_more_fit_workers(tmp_path, capsys, value, what):
    """--fit-workers above 1 with --host, or not a count from 1: a line naming the option (after argparse's usage
    for a malformed value), exit 2, nothing written."""
    from app.cli import main
    try:
        rc = main(["run", "paper", "--host", "192.0.2.1", "--fit-workers", value, "--out", str(tmp_path / "run")])
    except SystemExit as e:          # argparse's own refusal
        rc = e.code
    err = capsys.readouterr().err
    assert rc == 2 and what in err.strip().splitlines()[-1] and "Traceback" not in err
    assert not (tmp_path / "run").exists()
