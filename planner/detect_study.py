"""The detectability Monte Carlo: planner.detectability's predicted detection rate against simulated rasters.

For each case (a stone at x_m, depth_m, diameter_m) ``runs`` simulated 15-probe rasters at 4 mm (the accuracy
study's measurement model, planner.accuracy.FastArm, on the TRUE scene's fem forces) are localized from the prior
and the records, and the detections counted; the prediction is p_detect (noncentral chi2 from the expected contrast
and the localizer's weights). tests/test_detect_rate.py checks one marginal case; ``palpate study detect`` runs a
grid of them on planner.tasks (serial or dask). Case i's runs are seeded ``seed * 100000 + i * 1000 + k``.
"""
from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.contracts import Motion, sensor_spec
from core.jsonsafe import nulled
from fem.scene import Stone
from planner.accuracy import DEPTH_M, FastArm, continued_force
from planner.detectability import p_detect, probe_sigma_n, probe_tau_s
from planner.localize import Measurements, localize
from planner.raster import raster_positions
from planner.surrogate import stone_model
from planner.tasks import Runner, record_with, run_pieces

DIAMETERS_M = (0.004, 0.006, 0.008)
DEPTHS_M = (0.020, 0.030, 0.040)
# (diameter, depth): across the margin with the tissue's unknowns fitted (issue 14): 6 mm at 20 mm predicted 0.59
QUICK = ((0.004, 0.030), (0.006, 0.020), (0.010, 0.025), (0.012, 0.030))


@dataclass(frozen=True)
class Case:
    index: int
    x_m: float
    depth_m: float
    diameter_m: float
    runs: int
    seed: int = 1
    sensor: str = "nano17"
    n_probes: int = 15

    @property
    def name(self) -> str:
        return f"case-{self.index:03d}-seed{self.seed}"


def study_cases(quick: bool, runs: int | None = None, seed: int = 1, sensor: str = "nano17",
                x_m: float = 0.035) -> list[Case]:
    grid = QUICK if quick else [(D, d) for d in DEPTHS_M for D in DIAMETERS_M]
    n = runs or (40 if quick else 150)
    return [Case(index=i, x_m=x_m, depth_m=d, diameter_m=D, runs=n, seed=seed, sensor=sensor)
            for i, (D, d) in enumerate(grid)]


def run_case(sur, c: Case) -> dict:
    """Predicted and Monte-Carlo detection rate of one case (a module-level function: dask workers import it)."""
    prior = sur.prior
    x = raster_positions(prior.tissue.width_m, n=c.n_probes, margin_m=0.005)
    truth = stone_model(prior.with_stones([Stone(x_m=c.x_m, depth_m=c.depth_m, diameter_m=c.diameter_m)]))
    pred = p_detect(prior, (c.x_m, c.depth_m, c.diameter_m), x_m=x, depth_m=np.full(len(x), DEPTH_M),
                    sigma_n=probe_sigma_n(sensor_spec(c.sensor)), surrogate=sur,
                    tau_s=np.full(len(x), float(probe_tau_s(Motion(), DEPTH_M))))
    hits = 0
    for k in range(c.runs):
        arm = FastArm(continued_force(truth), c.sensor, np.random.default_rng(c.seed * 100000 + c.index * 1000 + k))
        hits += bool(localize(prior, Measurements.from_records(arm.execute(x), Motion()), sur).detected)
    rate = hits / c.runs
    return {"index": c.index, "x_m": c.x_m, "depth_m": c.depth_m, "diameter_m": c.diameter_m, "runs": c.runs,
            "sensor": c.sensor, "n_probes": c.n_probes, "predicted": float(pred), "detected": hits, "rate": rate,
            "se": math.sqrt(max(pred * (1 - pred), 1e-12) / c.runs)}


def run_detect(sur, cases: list[Case], runner: Runner = Runner(), store: Path | None = None) -> list[dict]:
    return run_pieces(run_case, sur, cases, [c.name for c in cases], runner=runner, store=store,
                      desc="detectability cases",
                      shape=record_with("index", "x_m", "depth_m", "diameter_m", "runs", "sensor", "n_probes",
                                        "predicted", "detected", "rate", "se"))


def write_report(out: Path, rows: list[dict], elapsed_s: float, where: str = "") -> list[str]:
    """detect.json, detect.csv, detect.md (returned as lines) and detect.png in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "detect.json").write_text(json.dumps(nulled(rows), indent=1, allow_nan=False))
    with open(out / "detect.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    lines = [f"Detectability Monte Carlo: {len(rows)} stones, {rows[0]['runs']} simulated {rows[0]['n_probes']}-probe "
             f"rasters each, sensor {rows[0]['sensor']} ({elapsed_s:.0f} s{'; ' + where if where else ''})", "",
             "| diameter (mm) | depth (mm) | predicted | Monte Carlo | difference / standard error |",
             "|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['diameter_m'] * 1e3:g} | {r['depth_m'] * 1e3:g} | {r['predicted']:.2f} | {r['rate']:.2f} "
                     f"| {(r['rate'] - r['predicted']) / r['se']:+.1f} |")
    (out / "detect.md").write_text("\n".join(lines) + "\n")
    from planner.plots_accuracy import detect_figure
    detect_figure(rows, out / "detect.png")
    return lines
