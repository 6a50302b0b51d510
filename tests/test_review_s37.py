"""What session 37's independent review of the command line found, each refused or handled since: an output path
that is a device, a symlink into a run's data, a write that fails; Ctrl-C during IPOPT; a coarse raster too small to
fit; a tip thinner than the run's depth limit; two processes in one run directory; a ratio that is 0/0; a peak
between two stones; a reference scene of another size; a doubtful estimate printed as if sure; warnings in Python's
two-line format."""
from __future__ import annotations

import json
import math
import os
import signal
import stat
import subprocess
import sys
import warnings
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from test_bad_input_s34 import SCENE_2D as SCENE
from test_bad_input_s34 import _run

from app.errors import UsageError, guarded
from app.outlock import holding
from app.runexec import localized, verdict
from core.peak import or_null, parabola_peak, ratio_of, upper_window
from planner.interrupt import interruptible
from planner.localize import MIN_MEASUREMENTS, Localization
from planner.refine import AdaptiveResult, caveats, describe, too_few

ROOT = Path(__file__).resolve().parent.parent


# ---- output paths ----------------------------------------------------------------------------------------------

def test_plan_out_refuses_a_path_that_is_not_a_regular_file(tmp_path, capsys):
    """plan.json is written beside its path and renamed over it: a device (/dev/null, /dev/full) or a pipe there
    was replaced by a regular file."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    rc, _, err = _run(["plan", "paper", "--out", str(fifo)], capsys)
    assert rc == 2 and "--out" in err and "not a regular file" in err and len(err.strip().splitlines()) == 1
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)                  # still the pipe


def test_json_refuses_a_symlink_into_a_runs_data(tmp_path, capsys):
    run = tmp_path / "run"
    (run / "raw").mkdir(parents=True)
    (run / "probes.jsonl").write_text('{"index": 0}\n')
    link = tmp_path / "out.json"
    link.symlink_to(run / "probes.jsonl")
    rc, _, err = _run(["simulate", "paper", "--load", "indent", "--json", str(link)], capsys)
    assert rc == 2 and "--json" in err and "would overwrite a run's data" in err
    assert (run / "probes.jsonl").read_text() == '{"index": 0}\n'


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full")
def test_a_json_write_that_fails_names_the_option(capsys):
    from app.commands.output import write_json
    with pytest.raises(UsageError, match=r"^--json /dev/full: No space left on device$"):
        write_json("/dev/full", {"a": 1})


# ---- Ctrl-C during IPOPT ---------------------------------------------------------------------------------------

class _SigintAtIteration(ca.Callback):
    """IPOPT's iteration callback: SIGINT to this process at the third iteration (a Ctrl-C in the solve)."""

    def __init__(self, nx: int):
        ca.Callback.__init__(self)
        self.nx, self.k = nx, 0
        self.construct("sigint", {})

    def get_n_in(self):
        return ca.nlpsol_n_out()

    def get_n_out(self):
        return 1

    def get_sparsity_in(self, i):
        name = ca.nlpsol_out(i)
        if name == "f":
            return ca.Sparsity.scalar()
        return ca.Sparsity.dense(self.nx) if name in ("x", "lam_x") else ca.Sparsity(0, 0)

    def eval(self, arg):
        self.k += 1
        if self.k == 3:
            os.kill(os.getpid(), signal.SIGINT)
        return [0]


def _solver():
    x = ca.MX.sym("x", 2)
    cb = _SigintAtIteration(2)
    s = ca.nlpsol("s", "ipopt", {"x": x, "f": (x[0] - 1) ** 4 + (x[1] - 2) ** 4},
                  {"iteration_callback": cb, "ipopt.print_level": 0, "print_time": False})
    return s, cb


def test_ctrl_c_inside_ipopt_is_raised_after_the_solve():
    """CasADi turns the KeyboardInterrupt into a failed solve and the interrupt is gone (the first half shows it);
    ``interruptible`` raises it once the solve returns."""
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    s, cb = _solver()
    s(x0=[10, 10])                                  # swallowed: returns, the solve stopped early
    assert not s.stats()["success"] and cb.k == 3
    s, cb = _solver()
    with pytest.raises(KeyboardInterrupt):
        interruptible(lambda: s(x0=[10, 10]))
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler      # restored
    assert interruptible(lambda: 7) == 7


def test_the_planner_solves_through_interruptible():
    src = (ROOT / "planner" / "plan.py").read_text()
    assert "interruptible(lambda: self.solver(" in src


# ---- a run that cannot fit ---------------------------------------------------------------------------------------

def test_run_refuses_a_coarse_raster_too_small_to_fit(tmp_path, capsys):
    rc, _, err = _run(["run", "paper", "--sim", "--waypoints", "3", "--out", str(tmp_path / "r")], capsys)
    assert rc == 2 and "--waypoints" in err and f"[{MIN_MEASUREMENTS}," in err
    assert _run(["plan", "paper", "--waypoints", "3", "--out", str(tmp_path / "p.json")], capsys)[0] == 0
    rc, _, err = _run(["run", "paper", "--sim", "--plan", str(tmp_path / "p.json"), "--out", str(tmp_path / "r")],
                      capsys)
    assert rc == 2 and "--plan" in err and "3 waypoints" in err and f"at least {MIN_MEASUREMENTS}" in err
    assert not (tmp_path / "r").exists()


def test_too_few_usable_says_how_many_a_fit_needs_and_blames_failures_only_when_there_were_some():
    assert too_few(2, 2, 4) == "too few usable measurements: 2 of 2 probes, a fit needs at least 4"
    assert too_few(1, 3, 4).endswith("(the others failed or read forces no tissue gives: see probes.jsonl's "
                                     "status, reason and implausible)")


def test_a_run_without_a_fit_says_not_localized_not_no_stone():
    loc = Localization(detected=False, lr=float("nan"), lr_threshold=float("nan"))
    res = AdaptiveResult(loc, None, stop_reason=too_few(2, 2, 4))
    assert not localized(loc)
    assert verdict(loc, res, describe(loc), "ok", None) == "NOT LOCALIZED: " + too_few(2, 2, 4)
    fit = Localization(detected=False, lr=3.0, lr_threshold=20.0, peak_contrast_n=0.001)
    assert localized(fit) and verdict(fit, res, describe(fit), "ok", None).startswith("NO STONE no stone (LR 3.0")


def test_run_refuses_a_tip_thinner_than_its_depth_limit(tmp_path, capsys):
    scene = tmp_path / "tip.toml"
    scene.write_text(SCENE + "[indenter]\nradius_m = 0.003\n")
    # (since session 52 a 3 mm tip plans to 2.4 mm by default: refused when a limit at or past its radius is given)
    rc, _, err = _run(["run", str(scene), "--sim", "--out", str(tmp_path / "r"), "--depth-limit-m", "0.003"], capsys)
    assert rc == 2 and "indenter.radius_m = 0.003" in err and "give --depth-limit-m D" in err
    assert not (tmp_path / "r").exists()


def test_run_plans_to_its_depth_limit_and_resumes_only_with_the_same(tmp_path, capsys):
    out = tmp_path / "r"
    argv = ["run", "paper", "--sim", "--no-figure", "--budget-probes", "15", "--out", str(out)]
    rc, _, err = _run(argv + ["--depth-limit-m", "0.003"], capsys)
    assert rc == 0, err
    plan = json.loads((out / "plan_round0.json").read_text())
    assert plan["limits"]["depth_limit_m"] == 0.003 and max(p["depth_m"] for p in plan["probes"]) <= 0.003
    assert json.loads((out / "run_options.json").read_text())["depth_limit_m"] == 0.003
    rc, _, err = _run(argv + ["--depth-limit-m", "0.0035"], capsys)          # other options: refused, kept
    assert rc == 2 and "--out" in err
    rc, _, err = _run(["run", "paper", "--sim", "--plan", str(out / "plan_round0.json"), "--depth-limit-m", "0.002",
                       "--out", str(tmp_path / "r2")], capsys)
    assert rc == 2 and "drop --depth-limit-m" in err
    rc, _, err = _run(argv[:-1] + [str(tmp_path / "r3"), "--depth-limit-m", "0.0005"], capsys)
    assert rc == 2 and "shallowest useful probe" in err


# ---- one process per run directory ---------------------------------------------------------------------------------

def test_a_second_process_is_refused_a_run_directory_in_use(tmp_path):
    out = tmp_path / "run"
    code = ("import sys; from pathlib import Path; from app.outlock import holding; from app.errors import UsageError\n"
            "try:\n    holding(Path(sys.argv[1])).__enter__()\nexcept UsageError as e:\n    print(e)\n"
            "else:\n    print('held')")
    with holding(out):
        other = subprocess.run([sys.executable, "-c", code, str(out)], capture_output=True, text=True, cwd=ROOT)
        assert "another palpate process is writing there now" in other.stdout
        assert list(out.iterdir()) == []                   # no file of its own in the directory
    other = subprocess.run([sys.executable, "-c", code, str(out)], capture_output=True, text=True, cwd=ROOT)
    assert other.stdout.strip() == "held"                  # released when the block ended


# ---- predict's ratios ------------------------------------------------------------------------------------------------

def test_a_ratio_without_a_reference_force_is_null_not_nan():
    r = ratio_of([1.0, 0.0, 2.0, 3.0], [2.0, 0.0, 0.0, np.inf])
    assert r[0] == 0.5 and np.isnan(r[1:]).all()
    assert or_null(r) == [0.5, None, None, None]


def test_predict_at_a_depth_below_the_mesh_resolution_writes_no_nan(tmp_path, capsys):
    out = tmp_path / "p.json"
    rc, text, _ = _run(["predict", "paper", "--depth-m", "1e-6", "--waypoints", "5", "--force-only", "--json",
                        str(out)], capsys)
    assert rc == 0
    body = out.read_text()
    assert "NaN" not in body and "Infinity" not in body
    assert "null" in body and "no ratio (null) at" in text


def test_the_ratio_peak_stays_on_one_hump_of_two():
    """Two stones: the ratio has two humps and a valley between them; a parabola through both put the 'peak' in the
    valley."""
    x = np.linspace(0.0, 70.0, 50)
    y = 1 + 0.1 * np.exp(-((x - 29.6) / 6) ** 2) + 0.1 * np.exp(-((x - 40.4) / 6) ** 2)
    i = int(np.argmax(y))
    lo, hi = upper_window(y, i)
    xp, _ = parabola_peak(x, y, lo, hi)
    top = x[np.argsort(y)[-2:]]                              # the humps' tops (each moved in by the other's tail)
    assert min(abs(xp - top[0]), abs(xp - top[1])) < 1.5 and abs(xp - 35.0) > 3.0
    span = y[i] - y.min()                                    # the valley lies within the upper quarter: the plain
    plain_lo, plain_hi = i, i                                # window runs through it, and its parabola peaks there
    while plain_lo > 0 and y[plain_lo - 1] >= y[i] - 0.25 * span:
        plain_lo -= 1
    while plain_hi < len(y) - 1 and y[plain_hi + 1] >= y[i] - 0.25 * span:
        plain_hi += 1
    assert abs(parabola_peak(x, y, plain_lo, plain_hi)[0] - 35.0) < 1.0


def test_a_noisy_single_hump_keeps_its_whole_upper_window():
    """A stress ratio on two meshes zig-zags by a few 1e-3; that is no valley."""
    x = np.linspace(0.0, 70.0, 50)
    y = 1 + 0.15 * np.exp(-((x - 35.0) / 10) ** 2) + 0.004 * (-1.0) ** np.arange(50)
    i = int(np.argmax(y))
    span = y[i] - y.min()
    lo, hi = upper_window(y, i)
    plain_lo, plain_hi = i, i
    while plain_lo > 0 and y[plain_lo - 1] >= y[i] - 0.25 * span:
        plain_lo -= 1
    while plain_hi < len(y) - 1 and y[plain_hi + 1] >= y[i] - 0.25 * span:
        plain_hi += 1
    assert (lo, hi) == (plain_lo, plain_hi)


def test_compare_refuses_a_reference_of_another_size_or_dimension(tmp_path, capsys):
    narrow = tmp_path / "narrow.toml"
    narrow.write_text(SCENE.replace("width_m = 0.07", "width_m = 0.03"))
    rc, _, err = _run(["predict", "paper", "--compare", str(narrow), "--waypoints", "5"], capsys)
    assert rc == 2 and "--compare" in err and "tissue.width_m is 0.03 m" in err
    block = tmp_path / "block.toml"
    block.write_text(SCENE.replace("height_m = 0.05", "height_m = 0.05\nlength_m = 0.07")
                     + '[indenter]\nshape = "sphere"\nradius_m = 0.005\n')
    rc, _, err = _run(["predict", "paper", "--compare", str(block), "--waypoints", "5"], capsys)
    assert rc == 2 and "--compare" in err and "3D block" in err


# ---- what the run prints -----------------------------------------------------------------------------------------

def _stone(**kw) -> Localization:
    d = dict(detected=True, lr=500.0, lr_threshold=20.0, x_m=0.01, depth_m=0.016, diameter_m=0.009,
             sigma_x_m=3e-4, sigma_depth_m=8e-4, sigma_diameter_m=8e-4, chi2_1=80.0, dof_1=85)
    d.update(kw)
    return Localization(**d)


def test_a_doubtful_estimate_says_so_on_its_line():
    assert caveats(_stone()) == "" and "warning" not in describe(_stone())
    edge = describe(_stone(at_bound=["x"]))
    assert "; warning: at the fit's bound: x" in edge
    limit = 85 + 4 * math.sqrt(2 * 85)
    assert "poor fit: chi2 367 on 85" in describe(_stone(chi2_1=367.0))
    assert caveats(_stone(chi2_1=limit - 1)) == "" and "poor fit" in caveats(_stone(chi2_1=limit + 1))


def test_warnings_print_as_one_line_and_the_old_format_returns(capsys):
    def work():
        warnings.warn("the tip\n   touched   nothing", UserWarning, stacklevel=1)
        return 0
    before = warnings.showwarning
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = before
        assert guarded("palpate", work) == 0
        assert warnings.showwarning is before
    err = capsys.readouterr().err
    assert err == "palpate: warning: the tip touched nothing\n"


def test_ctrl_c_while_the_modules_load_is_one_line_and_exit_130(monkeypatch, capsys):
    from app import entry

    def interrupted(name):
        raise KeyboardInterrupt
    monkeypatch.setattr(entry.importlib, "import_module", interrupted)
    assert entry.palpate() == 130 and entry.palpate_cell() == 130
    assert capsys.readouterr().err == "palpate: interrupted\npalpate-cell: interrupted\n"
    text = (ROOT / "pyproject.toml").read_text()
    assert 'palpate = "app.entry:palpate"' in text and 'palpate-cell = "app.entry:palpate_cell"' in text


def test_the_range_report_says_why_fem_refused_not_always_the_tip_radius():
    from robot.simforce import CachedForce

    def model(x_m, depth_m):
        if depth_m > 0.002:
            raise ValueError("depth_m=0.0021 at x_m=0.035: stone[0] under the tip lies 2 mm below the surface;\n"
                             "   the indentation must stay within 75% of that layer")
        return 100.0 * depth_m ** 1.5
    cf = CachedForce(model)
    assert cf(0.035, 0.001) > 0 and cf.range_report() is None
    cf(0.035, 0.0035)
    note = cf.range_report()["note"]
    assert "stone[0] under the tip lies 2 mm below the surface; the indentation must stay within 75%" in note
    assert "tip radius" not in note


def test_a_finite_strain_shape_with_no_neo_hookean_force_is_refused():
    """g = -1 (a neo-Hookean force of 0, the flat punch's before session 37's fix) made 1 + a g = 0 at the
    localizer's a = 1 start: a divide by zero and a crash; such a table is not a shape."""
    from planner.finite_strain_response import FiniteStrainShape
    x, dep = np.array([0.01, 0.02, 0.03]), np.array([0.0, 0.001, 0.002])
    good = {"width_m": 0.07, "x_m": x, "depth_m": dep, "g": np.array([[0.0, 0.01, 0.02]] * 3), "sweeps_s": 1.0}
    assert FiniteStrainShape.from_arrays(good).g.shape == (3, 3)
    with pytest.raises(ValueError, match="g <= -1"):
        FiniteStrainShape.from_arrays({**good, "g": np.array([[0.0, -1.0, -1.0]] * 3)})


def test_json_through_a_symlink_loop_is_refused_before_any_work(tmp_path, capsys):
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    rc, out, err = _run(["simulate", "paper", "--load", "indent", "--x-m", "0.035", "--depth-m", "0.003", "--json",
                         str(loop)], capsys)
    assert rc == 2 and "--json" in err and "symbolic links" in err and "force" not in out


def test_run_refuses_a_run_directory_another_process_holds(tmp_path, capsys):
    """The lock as `palpate run` takes it (2D; a block's run takes it in app.commands.run3d the same way): while
    OUT is held, a run there is refused and writes nothing."""
    out = tmp_path / "r"
    with holding(out):
        rc, _, err = _run(["run", "paper", "--sim", "--no-figure", "--out", str(out)], capsys)
    assert rc == 2 and "another palpate process is writing there now" in err
    assert list(out.iterdir()) == []
    src = (ROOT / "app" / "commands" / "run3d.py").read_text()
    assert "enter_context(holding(out))" in src and src.index("holding(out)") < src.index("open_out(")


def test_a_blocks_grid_too_small_to_fit_is_refused(tmp_path, capsys):
    rc, _, err = _run(["run", "block3d", "--sim", "--grid", "2x2", "--out", str(tmp_path / "r")], capsys)
    assert rc == 2 and "--grid 2x2" in err and "at least 6" in err and not (tmp_path / "r").exists()


def test_detectability_skips_stones_that_do_not_fit_in_the_tissue():
    from fem.scene import load
    from planner.detectability import detectability
    prior = load("paper").prior()                                        # 50 mm thick
    rows = detectability(prior, stones=[(0.015, 0.045), (0.008, 0.020)])["rows"]
    assert rows[0]["note"] == "does not fit in the tissue" and rows[0]["p_detect"] is None
    assert rows[1]["p_detect"] is not None
