"""`palpate run` on a tissue without a table starts probing at once and builds the table beside the coarse raster
(planner.pending): the stand-in build here hands over a table only once a probe is on disk, so a run that waited
for the table before probing would fail."""
from __future__ import annotations

import json
import time

import pytest

import planner.finite_strain_response as fsr
from app.cli import main
from fem.scene import load
from planner import pending
from planner.surrogate import load_surrogate

TOML = """name = "other-poisson"
[tissue]
width_m = 0.070
height_m = 0.050
youngs_pa = 2500.0
poisson = 0.45
[[stone]]
x_m = 0.030
depth_m = 0.020
diameter_m = 0.012
"""


@pytest.fixture(autouse=True)
def _no_finite_strain_shape(monkeypatch):
    """This tissue has no finite-strain shape either: a run would build it before probing (11 sweeps, 20 s), not
    what these tests are about; refused here, the localizer runs without that term (with its one-line warning)."""
    def refuse(prior):
        raise ValueError("not built in this test")
    monkeypatch.setattr(fsr, "build_shape", refuse)
    monkeypatch.setattr(fsr, "_MEM", {})          # (the refusal is remembered: not for the rest of the session)


def test_run_probes_while_the_table_is_built(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    handed_over = {}

    def slow_build(prior, progress=None, **kwargs):
        assert prior.tissue.poisson == 0.45 and not prior.stones
        deadline = time.monotonic() + 120
        while not ((out / "probes.jsonl").exists() and (out / "probes.jsonl").read_text().strip()):
            if time.monotonic() > deadline:
                raise AssertionError("no probe was measured while the table was being built")
            progress(1, 384, 1.0)
            time.sleep(0.05)
        handed_over["probes"] = len((out / "probes.jsonl").read_text().splitlines())
        return load_surrogate(load("paper").prior(), build=False)     # a stand-in table (not this tissue's)

    monkeypatch.setattr(pending, "load_surrogate", slow_build)
    scene = tmp_path / "mine.toml"
    scene.write_text(TOML)
    assert main(["run", str(scene), "--sim", "--budget-probes", "15", "--no-figure", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "building it in the background" in err and "surrogate table: 1/384 stones" in err
    assert handed_over["probes"] >= 1
    r = json.loads((out / "result.json").read_text())
    assert r["time"]["probing_started_s"] < r["time"]["wall_s"]
    assert r["detectability"]["usable"] is not None


def test_a_failed_table_build_is_one_line_and_the_probes_are_kept(tmp_path, monkeypatch, capsys):
    def failing_build(prior, **kwargs):
        raise ValueError("fem refused a candidate stone")

    monkeypatch.setattr(pending, "load_surrogate", failing_build)
    scene = tmp_path / "mine.toml"
    scene.write_text(TOML)
    out = tmp_path / "run"
    assert main(["run", str(scene), "--sim", "--budget-probes", "15", "--no-figure", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "cannot be modelled" in err[-1] and "fem refused a candidate stone" in err[-1]
    assert "Traceback" not in "\n".join(err)
    assert len((out / "probes.jsonl").read_text().splitlines()) == 15
