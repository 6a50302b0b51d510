"""`palpate simulate --load indent` and `palpate predict`: they run, their JSON keeps the keys of docs/architecture.md, the figures
are written, and the physics shows (the force ratio peaks over the stone). Coarse meshes (h = 4 mm) keep it fast."""
import json

import numpy as np
import pytest

from app.cli import main

COARSE = ["--mesh-size-m", "0.004"]


@pytest.fixture(autouse=True)
def _no_disk_cache(monkeypatch, tmp_path):
    # hermetic: no models from (or into) the user's disk cache; the in-process cache still applies
    monkeypatch.setenv("PALPATE_CACHE", "0")
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path / "cache"))


def test_simulate_indent_json_summary_and_figure(tmp_path, capsys):
    out = tmp_path / "indent.json"
    rc = main(["simulate", "paper", "--load", "indent", "--x-m", "0.035", "--depth-m", "0.003", *COARSE,
               "--json", str(out), "--plots", str(tmp_path / "fig"), "--vtu", str(tmp_path / "i.vtu")])
    assert rc == 0
    d = json.loads(out.read_text())
    assert set(d) >= {"x_m", "depth_m", "force_n_per_m", "force_n", "max_von_mises_pa", "contact"}
    assert set(d["contact"]) >= {"x_m", "pressure_pa"}
    assert d["x_m"] == 0.035 and d["depth_m"] == 0.003 and d["load"] == "indent"
    assert d["force_n"] > 0 and d["max_von_mises_pa"] > 0
    assert d["force_n"] == pytest.approx(d["force_n_per_m"] * d["indenter"]["thickness_m"], rel=1e-12)
    p, x = np.array(d["contact"]["pressure_pa"]), np.array(d["contact"]["x_m"])
    assert len(p) == len(x) > 0 and p.min() >= 0 and p.max() > 0
    assert abs(x[np.argmax(p)] - 0.035) <= 0.0015                   # pressure peaks under the tip
    assert 0 < d["half_width_m"] < d["indenter"]["radius_m"]
    assert abs(d["max_von_mises_at"]["x_m"] - 0.035) <= d["indenter"]["radius_m"]
    assert set(d["surface"]) >= {"x_m", "sxx_pa", "syy_pa", "sxy_pa", "von_mises_pa"}
    assert (tmp_path / "fig" / "fig10_indent.png").stat().st_size > 10_000
    assert (tmp_path / "i.vtu").exists()
    text = capsys.readouterr().out
    assert "force:" in text and "N/m" in text and "max von Mises" in text and "tip:" in text


def test_simulate_indent_radius_override_and_bad_requests(tmp_path, capsys):
    forces = {}
    for r in ("0.0025", "0.005"):
        out = tmp_path / f"r{r}.json"
        assert main(["simulate", "healthy", "--load", "indent", "--x-m", "0.035", "--depth-m", "0.002", *COARSE,
                     "--indenter-radius-m", r, "--json", str(out)]) == 0
        d = json.loads(out.read_text())
        assert d["indenter"]["radius_m"] == float(r)
        forces[r] = d["force_n"]
    assert forces["0.0025"] < forces["0.005"]                     # a blunter tip pushes back harder
    capsys.readouterr()
    assert main(["simulate", "paper", "--load", "indent", "--depth-m", "0.003", *COARSE]) == 2
    assert "--x-m" in capsys.readouterr().err
    assert main(["simulate", "paper", "--load", "indent", "--x-m", "0.09", "--depth-m", "0.003", *COARSE]) == 2
    assert "x_m" in capsys.readouterr().err


def test_predict_ratio_peaks_over_the_stone(tmp_path, capsys):
    out = tmp_path / "predict.json"
    n = 13
    rc = main(["predict", "paper", "--waypoints", str(n), *COARSE, "--json", str(out),
               "--plots", str(tmp_path / "fig")])
    assert rc == 0
    d = json.loads(out.read_text())
    w, ref = d["waypoints"], d["reference"]
    for block in (w, ref):
        assert set(block) >= {"x_m", "force_n", "max_von_mises_pa"}
        assert len(block["x_m"]) == len(block["force_n"]) == len(block["max_von_mises_pa"]) == n
    x = np.array(w["x_m"])
    assert x[0] == pytest.approx(0.005) and x[-1] == pytest.approx(0.065)
    assert d["reference_scene"] == "paper-prior" and d["depth_m"] == 0.004
    ratio = np.array(d["ratio"])
    np.testing.assert_allclose(ratio, np.array(w["force_n"]) / np.array(ref["force_n"]), rtol=1e-12)
    assert np.all(ratio >= 1 - 1e-9)                                # a stiff stone never softens the response
    spacing = x[1] - x[0]
    assert abs(d["peak_ratio"]["x_m"] - 0.035) <= spacing and d["peak_ratio"]["ratio"] > 1.05
    assert abs(d["peak_ratio_von_mises"]["x_m"] - 0.035) <= 2 * spacing
    assert set(d["timings_s"]) >= {"setup_s", "predict_s", "per_waypoint_s", "total_s"}
    assert (tmp_path / "fig" / "fig11_predict.png").stat().st_size > 10_000
    assert "force ratio peaks" in capsys.readouterr().out


def test_predict_agrees_with_simulate_and_follows_the_stone(tmp_path):
    out = tmp_path / "p.json"
    assert main(["predict", "paper-left", "--waypoints", "13", "--compare", "healthy", "--force-only", *COARSE,
                 "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    assert d["reference_scene"] == "healthy" and d["waypoints"]["max_von_mises_pa"] is None
    x = np.array(d["waypoints"]["x_m"])
    assert abs(d["peak_ratio"]["x_m"] - 0.020) <= x[1] - x[0]
    # the same waypoint through `simulate --load indent` gives the same force
    i = 5
    s = tmp_path / "s.json"
    assert main(["simulate", "paper-left", "--load", "indent", "--x-m", repr(float(x[i])), "--depth-m", "0.004",
                 *COARSE, "--json", str(s)]) == 0
    assert json.loads(s.read_text())["force_n"] == pytest.approx(d["waypoints"]["force_n"][i], rel=1e-12)


def test_predict_refuses_bad_requests(capsys):
    assert main(["predict", "paper", "--waypoints", "0", *COARSE]) == 2
    assert "--waypoints" in capsys.readouterr().err
    assert main(["predict", "paper", "--waypoints", "5", "--margin-m", "0.04", *COARSE]) == 2
    assert "--margin-m" in capsys.readouterr().err
    assert main(["predict", "paper", "--waypoints", "5", "--depth-m", "-0.001", *COARSE]) == 2
