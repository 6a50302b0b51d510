"""Session 59's independent review of 2D fem on scenes of its own: predict's ratio peak on a peak sharper than the
waypoints' spacing (it reported the largest sample, 0.5 mm from a stone the three samples around it place within
0.1 mm); near-incompressible tissue, whose nodal contact pressure oscillates without a word (+10 % at nu 0.49, +54 %
at 0.499) and whose locking warning advised, for the contact model too, a mixed formulation only load A has."""
from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import pytest

from app.commands.predict import _peak
from app.resolution import NU_PRESSURE_WARN, warn_pressure_near_incompressible2d
from fem.model import warn_if_locking
from fem.scene import load


def test_a_peak_sharper_than_the_spacing_takes_the_parabola_through_its_top_three():
    """The review's profile (a stone 6.5 mm deep at x = 42 mm, `predict --waypoints 21 --depth-m 0.001`): 1.3063,
    1.3674, 1.2448 at 40, 42.5, 45 mm; only two samples lie in the upper quarter. The vertex of the parabola through
    the top three samples (42.08 mm), not the largest sample (42.5 mm), is the peak."""
    xs = np.arange(0.030, 0.0551, 0.0025)
    ratio = np.array([1.0, 1.01, 1.03, 1.08, 1.3063, 1.3674, 1.2448, 1.06, 1.02, 1.005, 1.0])
    i = int(np.argmax(ratio))
    assert xs[i] == pytest.approx(0.0425)
    y0, y1, y2 = ratio[i - 1:i + 2]
    h = xs[1] - xs[0]
    vertex = xs[i] + h * (y0 - y2) / (2 * (y0 - 2 * y1 + y2))
    p = _peak(xs, ratio)
    assert p["x_m"] == pytest.approx(vertex, abs=1e-12)
    assert abs(p["x_m"] - 0.042) < 0.1e-3 < 0.4e-3 < abs(xs[i] - 0.042)      # 0.08 mm off the stone, the sample 0.5
    assert p["x_max_sample_m"] == xs[i] and p["ratio"] >= ratio[i]


def test_a_broad_peak_keeps_its_window():
    """The fallback is for a window of fewer than three samples only: a broad bump keeps its upper-quarter window
    (the same vertex as the least-squares parabola through it)."""
    xs = np.linspace(0.0, 0.06, 25)
    ratio = 1.0 + 0.4 * np.exp(-((xs - 0.031) / 0.012) ** 2)
    p = _peak(xs, ratio)
    assert abs(p["x_m"] - 0.031) < 0.3e-3


def _with_poisson(nu: float, name: str = "paper"):
    sc = load(name).prior()
    return dataclasses.replace(sc, tissue=dataclasses.replace(sc.tissue, poisson=nu))


@pytest.mark.parametrize("nu", [0.49, 0.499])
def test_near_incompressible_tissue_says_its_contact_pressure_oscillates(nu, capsys):
    sc = _with_poisson(nu)
    warn_pressure_near_incompressible2d(sc, "simulate", [0.0, 1.0e-3])
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"poisson = {nu:g}" in err and "surface_refine" in err
    k = 1.0e-3 / (sc.analysis.mesh_size_m / sc.analysis.surface_refine)
    assert f"here {k:.2g}" in err


def test_a_compressible_tissue_or_no_contact_says_nothing(capsys):
    warn_pressure_near_incompressible2d(_with_poisson(NU_PRESSURE_WARN - 0.01), "simulate", [1.0e-3])
    warn_pressure_near_incompressible2d(_with_poisson(0.499), "simulate", [0.0])
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("name, mixed", [("paper", True), ("block3d", False)])
def test_the_locking_warning_advises_what_the_scene_can_do(name, mixed):
    """2D: the mixed formulation for load A, and for the contact model (which has none) a finer surface; 3D (no
    mixed formulation at all): refine and compare."""
    sc = _with_poisson(0.499, name)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        warn_if_locking(sc)
    assert len(w) == 1
    msg = str(w[0].message)
    assert ('formulation = "mixed"' in msg) is mixed
    assert ("load B" in msg) is mixed and "refine" in msg
    assert math.isclose(float(msg.split("bulk modulus ")[1].split(" ")[0]), 2 * 1.499 / (3 * 0.002), rel_tol=1e-2)
