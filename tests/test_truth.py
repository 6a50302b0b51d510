"""The simulated truth's conditions beyond its scene (robot/truth.py): validation, the [truth] table, the standard
linear solid, the registration error on the arm, and the CLI's refusals (one line, exit 2)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from robot_fixtures import make_sim

from app.cli import main
from robot.truth import Relaxation, TruthConditions, TruthError, conditions_of


def test_conditions_are_checked_and_read_from_the_truth_table(tmp_path):
    with pytest.raises(TruthError, match="surface_offset_m = 0.01 is outside"):
        TruthConditions(surface_offset_m=0.01)
    with pytest.raises(TruthError, match="finite"):
        TruthConditions(relaxation_fraction=float("nan"))
    f = tmp_path / "t.toml"
    f.write_text('[tissue]\nwidth_m = 0.07\nheight_m = 0.05\nyoungs_pa = 3000.0\npoisson = 0.45\n'
                 '[truth]\nsurface_offset_m = -0.0015\nrelaxation_fraction = 0.25\n')
    c = conditions_of(str(f))
    assert c.surface_offset_m == -0.0015 and c.relaxation_fraction == 0.25 and not c.ideal
    assert conditions_of("paper").ideal
    f.write_text('[tissue]\nwidth_m = 0.07\nheight_m = 0.05\nyoungs_pa = 3000.0\npoisson = 0.45\n[truth]\nofset = 1\n')
    with pytest.raises(TruthError, match="unknown key.*ofset"):
        conditions_of(str(f))
    from fem.scene import load
    assert load(str(f)).tissue.youngs_pa == 3000.0          # fem reads the scene and skips [truth]


def test_standard_linear_solid_relaxes_to_its_long_term_fraction():
    """Ramp to a force in 2 s, hold: the force right after the ramp is below the elastic one (relaxation during the
    ramp), then decays with tau to (1 - g) of it; out of contact it is reset."""
    g, tau, dt = 0.25, 2.0, 0.002
    r = Relaxation(g, tau)
    t = np.arange(0, 30, dt)
    fe = np.minimum(t / 2.0, 1.0) * 0.1
    out = []
    for v in fe:
        r.step(v, dt)
        out.append(r.force(v))
    out = np.array(out)
    k_ramp = int(2.0 / dt)
    # closed form at the end of a linear ramp: F = F_e [1 - g + g tau / T (1 - exp(-T / tau))]
    ramp = 0.1 * (1 - g + g * tau / 2.0 * (1 - math.exp(-2.0 / tau)))
    assert out[k_ramp - 1] == pytest.approx(ramp, rel=1e-3)
    assert out[-1] == pytest.approx(0.1 * (1 - g), rel=1e-4)
    k = k_ramp + int(tau / dt)        # one tau into the hold: the excess over (1 - g) has fallen by e
    assert (out[k] - 0.075) / (out[k_ramp] - 0.075) == pytest.approx(math.exp(-1), rel=2e-3)
    r.step(0.0, dt)
    assert r.force(0.0) == 0.0 and r.h == 0.0


def test_registration_error_moves_the_contact(tmp_path):
    """A surface 1 mm above the nominal one: the tip at nominal depth d feels the force of d + 1 mm."""
    f = lambda x, d: 100.0 * d ** 1.5          # noqa: E731
    arm, c, r = make_sim(f, surface_height_m=lambda x: 1e-3, cache=False)
    x, d = arm.tip_in_tissue()
    shift = -d + 0.002                           # put the tip 2 mm below the nominal surface
    arm.T_tcp[:3, 3] -= shift * arm.n_base
    x, d = arm.tip_in_tissue()
    assert d == pytest.approx(0.002, abs=1e-9)
    assert arm.contact_force_n() == pytest.approx(f(x, 0.003), rel=1e-9)


@pytest.mark.parametrize("argv, needle", [
    (["--sim", "--truth-surface-offset-m", "0.01"], "surface_offset_m = 0.01 is outside"),
    (["--host", "192.0.2.1", "--truth-relaxation"], "--truth-relaxation"),
    (["--sim", "controller", "--truth-sensor-drift-n-per-s", "1e-4"], "[truth] table"),
    (["--sim", "--prior", "nonesuch"], "--prior nonesuch"),
])
def test_truth_options_refused_in_one_line(tmp_path, capsys, argv, needle):
    rc = main(["run", "paper", *argv, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and needle in err[0], err
    assert not (tmp_path / "o").exists()
