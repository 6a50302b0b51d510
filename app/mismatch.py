"""The mismatch study (issue 14) as independent pieces for planner.tasks: the truth is not the belief.

Every trial is a whole ``palpate run TRUTH --plan plan.json --sim`` (planner, driver on the in-memory simulated arm,
localizer, refinement) where the planner and the localizer know only the prior (``paper``'s: E = 2500 Pa, nu = 0.4,
50 mm thick, the surface on the nominal tissue pose) and the simulated truth is drawn from ``RANGES``:

    tissue modulus       x 0.5 - x 2 of the prior (log-uniform)
    Poisson ratio        0.35 - 0.49 (uniform)
    thickness            prior +- 10 % (uniform)
    surface offset       +- 2 mm against the nominal tissue pose (uniform; positive: above it)
    surface tilt         +- 3 deg about the tissue's y axis (uniform)
    viscoelastic         on in half the trials: relaxation 20-30 %, tau 1-4 s (standard linear solid)
    hyperelastic         with ``--hyperelastic`` only: a finite-strain neo-Hookean tissue (fem.hypertruth) in half
                         the trials, drawn from its own generator (the other draws stay those of the study without
                         it); off by default: each such trial costs a sweep in depth per probe (about 1.5-2.5 s each
                         since session 58, 2-3 s before, when a run took some 60 s against 15 s)
    stone                a random rigid stone inside the true tissue (planner.surrogate.random_stones), or none

with the nano17 sensor (its own random bias and drift). The plan, made once on the prior, indents 3 mm (not 4 mm: a
surface up to 2 mm above the nominal one makes the true indentation reach the tip radius, where fem's contact model
ends) with an 8 mN contact threshold (20 mN is never reached when the surface lies 2 mm below the nominal one).
Each trial's records are also localized with the tissue taken as known (``nuisance=False``, the localizer before
issue 14) and without the finite-strain term (``finite_strain=False``: the tissue's unknowns fitted, a linear
tissue assumed) for comparison; a stone is inside the detectability envelope when planner.detectability.p_detect (the
coarse raster, nuisance projected out) is at least 0.9: ``p_detect`` on the prior as the planner sees it, and
``p_detect_in_truth`` with the truth's modulus and surface (the judge's: a stone in tissue half as stiff gives half
the contrast; the belief's envelope counts it as detectable all the same). Trials are drawn in the parent from one generator (the same
study whoever runs it) and each run keeps its files in ``runs/trial-NNNN/``.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.cli import main as palpate
from core.contracts import MEASURED, Limits, Motion, Plan, sensor_spec
from fem.contact import cached_keys, forget_except
from fem.scene import Stone, dump_toml
from planner.detectability import p_detect, probe_sigma_n, probe_tau_s
from planner.localize import Measurements, localize
from planner.plan import plan_raster
from planner.surrogate import random_stones
from planner.tissue_response import PriorResponse, prior_and_thickness_slope
from robot.records import read_records

PLAN_DEPTH_M = 0.003
CONTACT_THRESHOLD_N = 0.008
PLAN_WAYPOINTS = 15
DEPTH_CAP_TIP_RADII = 0.9         # the judge's true indentation is capped below the tip radius (p_detect_in_truth)
RANGES = {"youngs_scale": (0.5, 2.0), "poisson": (0.35, 0.49), "thickness_scale": (0.9, 1.1),
          "surface_offset_m": (-0.002, 0.002), "surface_tilt_deg": (-3.0, 3.0), "relaxation_fraction": (0.2, 0.3),
          "relaxation_tau_s": (1.0, 4.0)}


@dataclass(frozen=True)
class MismatchTrial:
    index: int
    seed: int
    budget: int
    mismatch: dict
    stone: tuple | None           # (x_m, depth_m, diameter_m) in the true tissue, or None (healthy)

    @property
    def name(self) -> str:
        return f"trial-{self.index:04d}"


@dataclass(frozen=True)
class Shared:
    """What every trial reads (scattered once to the workers)."""
    prior: object                 # fem.scene.Scene: the prior
    sur: object                   # planner.surrogate.Surrogate of the prior
    plan_path: str
    runs_dir: str
    coarse_x_m: tuple


def draw_mismatch(rng) -> dict:
    r = RANGES
    return {"youngs_scale": float(math.exp(rng.uniform(math.log(r["youngs_scale"][0]), math.log(r["youngs_scale"][1])))),
            "poisson": float(rng.uniform(*r["poisson"])), "thickness_scale": float(rng.uniform(*r["thickness_scale"])),
            "surface_offset_m": float(rng.uniform(*r["surface_offset_m"])),
            "surface_tilt_deg": float(rng.uniform(*r["surface_tilt_deg"])),
            "viscoelastic": bool(rng.uniform() < 0.5),
            "relaxation_fraction": float(rng.uniform(*r["relaxation_fraction"])),
            "relaxation_tau_s": float(rng.uniform(*r["relaxation_tau_s"]))}


def study_trials(prior, sur, stones: int, healthy: int, budget: int, seed: int,
                 hyperelastic: bool = False) -> list[MismatchTrial]:
    """``stones`` trials with a random stone then ``healthy`` without, from one generator seeded by ``seed``;
    ``hyperelastic``: a neo-Hookean truth in half the trials, drawn from a second generator (seeded by ``seed``
    and 14) so that every other draw is the study's without it."""
    rng = np.random.default_rng(seed)
    rng_hyper = np.random.default_rng([seed, 14])
    out = []
    for i in range(stones + healthy):
        mm = draw_mismatch(rng)
        mm["hyperelastic"] = bool(rng_hyper.uniform() < 0.5) and hyperelastic
        stone = None
        if i < stones:
            H = prior.tissue.height_m * mm["thickness_scale"]
            xs, s, D = random_stones(sur.bounds, prior.tissue.width_m, H, 1, rng)[0]
            stone = (float(xs), float(s + D / 2), float(D))
        out.append(MismatchTrial(index=i, seed=seed * 100000 + i, budget=budget, mismatch=mm, stone=stone))
    return out


def make_plan(prior, path: Path) -> tuple:
    """The study's plan on the prior (written once to ``path``; kept if there), its coarse raster's x."""
    if not path.exists():
        plan = plan_raster(prior, n_waypoints=PLAN_WAYPOINTS, limits=Limits(depth_limit_m=PLAN_DEPTH_M),
                           motion=Motion(contact_threshold_n=CONTACT_THRESHOLD_N))
        plan.save(path)
    return tuple(float(q.x_m) for q in Plan.load(path).probes)


def truth_toml(prior, mm: dict, stone) -> str:
    t = prior.tissue
    sc = dataclasses.replace(prior, name="truth", stones=(stone,) if stone is not None else (),
                             tissue=dataclasses.replace(t, youngs_pa=t.youngs_pa * mm["youngs_scale"],
                                                        poisson=mm["poisson"],
                                                        height_m=t.height_m * mm["thickness_scale"]))
    truth = {"surface_offset_m": mm["surface_offset_m"], "surface_tilt_rad": math.radians(mm["surface_tilt_deg"]),
             "relaxation_fraction": mm["relaxation_fraction"] if mm["viscoelastic"] else 0.0,
             "relaxation_tau_s": mm["relaxation_tau_s"]}
    if mm.get("hyperelastic"):
        truth["hyperelastic"] = True
    value = lambda v: ("true" if v else "false") if isinstance(v, bool) else repr(v)     # noqa: E731 (TOML)
    return dump_toml(sc) + "\n[truth]\n" + "".join(f"{k} = {value(v)}\n" for k, v in truth.items())


class _Scaled:
    """A surrogate whose contrast is ``k`` times another's (a rigid stone's contrast is proportional to E)."""

    def __init__(self, sur, k: float):
        self.sur, self.k = sur, k

    def contrast(self, *a, **kw):
        return self.k * np.asarray(self.sur.contrast(*a, **kw))


def p_detect_in_truth(prior, sur, stone, mm: dict, coarse_x) -> float:
    """The study's judge (it knows the truth; the localizer never calls this): the coarse raster's detection
    probability for ``stone`` in the TRUE tissue as far as the prior's table can say it: the contrast scaled by the
    true modulus, at the true indentation (the planned depth plus the true surface's height over the nominal one at
    each probe: offset and tilt, as robot.truth places it), capped at 0.9 tip radii (fem's contact model ends at the
    tip radius; the simulator continues the force linearly beyond it). Poisson ratio and thickness stay the prior's
    (a table per truth would cost minutes)."""
    x = np.asarray(coarse_x, float)
    W = prior.tissue.width_m
    above = mm["surface_offset_m"] + (x - 0.5 * W) * math.tan(math.radians(mm["surface_tilt_deg"]))
    dep = np.clip(PLAN_DEPTH_M + above, 0.2 * PLAN_DEPTH_M, DEPTH_CAP_TIP_RADII * prior.indenter.radius_m)
    return p_detect(prior, (stone.x_m, stone.depth_m, stone.diameter_m), x_m=x, depth_m=dep,
                    sigma_n=probe_sigma_n(sensor_spec("nano17")), surrogate=_Scaled(sur, mm["youngs_scale"]),
                    tau_s=probe_tau_s(Motion(), dep))


def run_trial(shared: Shared, t: MismatchTrial) -> dict:
    """One trial's row (a module-level function: dask workers import it)."""
    prior, sur = shared.prior, shared.sur
    coarse_x = np.array(shared.coarse_x_m)
    PriorResponse(prior, coarse_x)                        # the prior's fields, kept in this process's memory
    prior_and_thickness_slope(prior, coarse_x, PLAN_DEPTH_M)
    keep = cached_keys()
    stone = None if t.stone is None else Stone(x_m=t.stone[0], depth_m=t.stone[1], diameter_m=t.stone[2])
    d = Path(shared.runs_dir) / t.name
    d.mkdir(parents=True, exist_ok=True)
    (d / "truth.toml").write_text(truth_toml(prior, t.mismatch, stone))
    t0 = time.perf_counter()
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            # one process per trial: the study's parallelism is its trials (no forked fits inside them)
            rc = palpate(["run", str(d / "truth.toml"), "--plan", shared.plan_path, "--sim", "--seed", str(t.seed),
                          "--budget-probes", str(t.budget), "--no-figure", "--fit-workers", "1",
                          "--out", str(d / "run")])
    except Exception as e:  # noqa: BLE001 - a run that fails is a study's finding: counted, and the study goes on
        rc = -1
        err.write(f"\n{type(e).__name__}: {e}")
    finally:
        forget_except(keep)                                 # the truth's one-off models
    row = {"trial": t.index, "seed": t.seed, "rc": rc, "wall_s": time.perf_counter() - t0, **t.mismatch,
           "stone": stone is not None}
    if rc != 0:
        row["error"] = " ".join(err.getvalue().strip().splitlines()[-1:])
        return row
    r = json.loads((d / "run" / "result.json").read_text())
    est, nu = r["estimate"], r["nuisance"]
    # a detection the fit cannot place (verdict not_localized: app.runexec.unplaced) is no found stone
    detected = bool(r["detected"]) and r.get("verdict") != "not_localized"
    row.update(detected=detected, verdict=r.get("verdict"), lr=r["evidence"]["likelihood_ratio"],
               probes=r["probes_used"],
               stiffness_scale=nu["stiffness_scale"]["value"], thickness_est=nu["thickness_scale"]["value"],
               offset_est_m=nu["surface_offset_m"]["value"], tilt_est_rad=nu["surface_tilt_rad"]["value"],
               relax_est=nu["dwell_relaxation_fraction"]["value"], onsets=nu["contact_onsets_used"],
               finite_strain_est=(nu.get("finite_strain_amplitude") or {}).get("value"),
               finite_strain_in_estimate=nu.get("finite_strain_in_estimate"))
    meas = Measurements.from_records(read_records(d / "run"), statuses=MEASURED)
    old = localize(prior, meas, sur, nuisance=False)
    row.update(detected_known_tissue=old.detected, lr_known_tissue=old.lr)
    lin = localize(prior, meas, sur, finite_strain=False)      # the same records without the finite-strain term
    row.update(detected_no_finite_strain=lin.detected, lr_no_finite_strain=lin.lr)
    if stone is not None:
        row.update(x_m=stone.x_m, depth_m=stone.depth_m, diameter_m=stone.diameter_m)
        dep = np.full(len(coarse_x), PLAN_DEPTH_M)
        row["p_detect"] = p_detect(prior, (stone.x_m, stone.depth_m, stone.diameter_m), x_m=coarse_x, depth_m=dep,
                                   sigma_n=probe_sigma_n(sensor_spec("nano17")), surrogate=sur,
                                   tau_s=probe_tau_s(Motion(), dep))
        row["p_detect_truth"] = p_detect_in_truth(prior, sur, stone, t.mismatch, coarse_x)
        if detected:
            iv = est["depth_interval_m"]
            row.update(err_x_m=est["x_m"]["value"] - stone.x_m, err_depth_m=est["depth_m"]["value"] - stone.depth_m,
                       err_diam_m=est["diameter_m"]["value"] - stone.diameter_m, sigma_x_m=est["x_m"]["sigma"],
                       sigma_depth_m=est["depth_m"]["sigma"],
                       in68=bool(iv["68"][0] <= stone.depth_m <= iv["68"][1]),
                       in95=bool(iv["95"][0] <= stone.depth_m <= iv["95"][1]),
                       x_in1s=bool(abs(est["x_m"]["value"] - stone.x_m) <= est["x_m"]["sigma"]),
                       x_in2s=bool(abs(est["x_m"]["value"] - stone.x_m) <= 2 * est["x_m"]["sigma"]))
        if old.detected:
            row.update(err_x_known_tissue_m=old.x_m - stone.x_m, err_depth_known_tissue_m=old.depth_m - stone.depth_m)
        if lin.detected:
            row.update(err_x_no_finite_strain_m=lin.x_m - stone.x_m,
                       err_depth_no_finite_strain_m=lin.depth_m - stone.depth_m)
    return row
