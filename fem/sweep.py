"""The random-scene stress sweep: valid scenes drawn from everything the validator allows, each solved under load A
and load B on a coarse mesh and checked (``check_scene``); ``palpate study sweep`` and bench/sweep.py run it.

Scenes draw tissue size, modulus and Poisson ratio (up to 0.4999, with the mixed formulation on some), 0 to 3 stones
anywhere (also touching-close to an edge) with stiffness ratios 0.1 to 1e12, rigid or elastic tips of 2 to 8 mm
radius, P1/P2, plane strain/stress, mesh sizes 3 to 10 mm. Each scene is checked: load A finite with a relative
residual below 1e-6 (else a warning must have been given), load B forces finite and >= 0 at five waypoints,
complementarity, and the fast contact path against the plain full solve at one waypoint (rigid tip). A SceneError or
ValueError (a clear refusal, e.g. a surface mesh coarser than the tip, an elastic flat punch) is counted, not a
failure; NaN, an unexplained exception or a failed check is a failure. The disk cache is off.

Scene i draws from its own generator, ``default_rng([seed, i])`` (``sweep_piece``): the same scenes whether they run
serially or on dask workers (planner.tasks), in any order.
"""
from __future__ import annotations

import csv
import math
import os
import re
import time
import traceback
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

from fem import scene as S
from fem.contact import SurfaceModel, indent_full
from fem.uniform import solve_uniform


def random_scene(rng: np.random.Generator, i: int) -> S.Scene:
    for _ in range(1000):
        W, H = rng.uniform(0.04, 0.10), rng.uniform(0.03, 0.07)
        Et = 10 ** rng.uniform(3, 5)
        nu = rng.choice([rng.uniform(0.0, 0.49), rng.uniform(0.49, 0.4999), rng.uniform(-0.5, 0.0)], p=[.8, .1, .1])
        stones = []
        for _k in range(rng.integers(0, 4)):
            d = rng.uniform(0.004, min(0.025, 0.6 * H))
            near = rng.random() < 0.25          # a quarter of the stones hug an edge (gap 1 um .. 0.5 mm)
            gap = 10 ** rng.uniform(-6, -3.3) if near else None
            edge = rng.integers(0, 3)
            x = rng.uniform(d / 2 + 1e-3, W - d / 2 - 1e-3)
            dep = rng.uniform(d / 2 + 1e-3, H - d / 2 - 1e-3)
            if near:
                if edge == 0:
                    dep = d / 2 + gap
                elif edge == 1:
                    x = d / 2 + gap
                else:
                    dep = H - d / 2 - gap
            ratio = 10 ** rng.uniform(-1, 12)
            stones.append(S.Stone(x_m=x, depth_m=dep, diameter_m=d, youngs_pa=Et * ratio,
                                  poisson=rng.uniform(0.0, 0.45)))
        R = rng.uniform(0.002, 0.008)
        Ei = None if rng.random() < 0.5 else Et * 10 ** rng.uniform(1, 5)
        order = int(rng.integers(1, 3))
        plane = "strain" if rng.random() < 0.8 else "stress"
        form = "mixed" if (order == 2 and plane == "strain" and nu > 0.45 and rng.random() < 0.7) else "displacement"
        h = rng.uniform(0.003, 0.010)
        try:
            return S.Scene(name=f"sweep-{i}", tissue=S.Tissue(width_m=W, height_m=H, youngs_pa=Et, poisson=float(nu)),
                           stones=tuple(stones),
                           indenter=S.Indenter(shape="cylinder" if rng.random() < 0.85 else "flat", radius_m=R,
                                               youngs_pa=Ei if Ei is None else float(Ei)),
                           analysis=S.Analysis(plane=plane, order=order, mesh_size_m=h,
                                               surface_refine=float(rng.uniform(2, 8)), formulation=form,
                                               top_displacement_m=float(rng.uniform(0, 0.2 * H))))
        except S.SceneError:
            continue   # overlapping stones etc.: draw again (the validator's refusals are tested elsewhere)
    raise RuntimeError("could not draw a valid scene")


def check_scene(sc: S.Scene, rng) -> dict:
    row = {"name": sc.name, "stones": len(sc.stones), "order": sc.analysis.order, "plane": sc.analysis.plane,
           "formulation": sc.analysis.formulation, "poisson": sc.tissue.poisson,
           "max_ratio": max([s.youngs_pa / sc.tissue.youngs_pa for s in sc.stones], default=0.0),
           "min_gap_m": min([min(s.depth_m - s.radius_m, sc.tissue.height_m - s.depth_m - s.radius_m,
                                 s.x_m - s.radius_m, sc.tissue.width_m - s.x_m - s.radius_m) for s in sc.stones],
                            default=None),          # (no stone: no gap; None, never NaN, in the files)
           "status": "ok", "detail": "", "warnings": ""}
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            r = solve_uniform(sc, full_field=False)
            row["dofs"] = r.model.n_dofs
            row["residual"] = r.residual
            vals = np.concatenate([r.u] + list(r.surface.fields.values()))
            if not np.all(np.isfinite(vals)):
                raise AssertionError("load A: non-finite values")
            if r.residual > 1e-6 and not caught:
                raise AssertionError(f"load A: residual {r.residual:.1e} without a warning")
            if sc.analysis.formulation == "displacement":
                sm = SurfaceModel(sc, model=r.model)
                R = sc.indenter.radius_m
                xs = rng.uniform(0, sc.tissue.width_m, 5)
                ds = rng.uniform(0, 0.9 * R, 5) * np.array([1, 1, 1, 1e-6, 1])
                res = sm.indent_many(xs, ds)
                F = np.array([q.force_n_per_m for q in res])
                if not (np.all(np.isfinite(F)) and np.all(F >= 0)):
                    raise AssertionError(f"load B: forces {F}")
                for q in res:
                    if np.any(q.gap_m < -1e-9 * R) or np.any(q.nodal_force_n_per_m < 0) or \
                            abs(q.gap_m @ q.nodal_force_n_per_m) > 1e-9 * R * max(q.force_n_per_m, 1e-30) + 1e-30:
                        raise AssertionError("load B: complementarity violated")
                    if not np.isfinite(q.max_von_mises_pa):
                        raise AssertionError("load B: non-finite stress")
                row["max_force_n_per_m"] = float(F.max())
                if sm.rigid_tip and sc.indenter.youngs_pa is None:
                    k = int(np.argmax(F))
                    full = indent_full(sc, float(xs[k]), float(ds[k]), model=r.model)["force_n_per_m"]
                    row["fast_vs_full"] = abs(F[k] - full) / max(abs(full), 1e-300) if full > 0 else abs(F[k])
                    if row["fast_vs_full"] > 1e-6:
                        raise AssertionError(f"load B: fast {F[k]} vs full {full}")
        except (S.SceneError, ValueError) as e:   # a clear refusal: the message says what to change
            row["status"], row["detail"] = "refused", f"{type(e).__name__}: {e}"[:200]
        except Exception as e:  # noqa: BLE001
            row["status"] = "FAIL"
            row["detail"] = f"{type(e).__name__}: {e}"[:300]
            traceback.print_exc()
        row["warnings"] = "; ".join(sorted({re.sub(r"'[^']*'|[-+]?\d[\d.e+-]*", "#", str(w.message))[:60]
                                            for w in caught}))
    row["time_s"] = time.perf_counter() - t0
    return row


def summarize(rows) -> str:
    st = Counter(r["status"] for r in rows)
    ok = [r for r in rows if r["status"] == "ok"]
    res = [r["residual"] for r in ok if "residual" in r]
    ffull = [r["fast_vs_full"] for r in ok if "fast_vs_full" in r]
    warned = Counter()
    for r in rows:
        for w in filter(None, r["warnings"].split("; ")):
            warned[re.sub(r"'[^']*'|[-+]?\d[\d.e+-]*", "#", w)[:45]] += 1
    errs = Counter(re.sub(r"'[^']*'|[-+]?\d[\d.e+-]*", "#", r["detail"])[:70] if r["status"] == "refused" else ""
                   for r in rows)
    L = [f"### Random-scene sweep ({len(rows)} scenes)", "",
         f"- ok: {st.get('ok', 0)}, clear refusals (SceneError/ValueError with a message): {st.get('refused', 0)}, "
         f"**failures (NaN, unexplained exception, failed check): {st.get('FAIL', 0)}**",
         f"- stones per scene 0-3 (total {sum(r['stones'] for r in rows)}), stiffness ratios up to "
         f"{max(r['max_ratio'] for r in rows):.1e}, stones as close as "
         f"{min((r['min_gap_m'] for r in rows if r['min_gap_m'] is not None), default=math.nan) * 1e6:.1f} um to an "
         f"edge, Poisson up to "
         f"{max(r['poisson'] for r in rows):.4f} ({sum(r['formulation'] == 'mixed' for r in rows)} mixed)",
         f"- load A relative residual: median {np.median(res):.1e}, max {np.max(res):.1e}" if res else "",
         f"- load B fast vs full solve (rigid tips, {len(ffull)} scenes): max {np.max(ffull):.1e}" if ffull else "",
         f"- time: {sum(r['time_s'] for r in rows):.0f} s total, median {np.median([r['time_s'] for r in rows]):.2f} s "
         "per scene"]
    if warned:
        L.append("- warnings given: " + ", ".join(f"{k} ({v})" for k, v in warned.most_common()))
    refusals = {k: v for k, v in errs.items() if k}
    if refusals:
        L.append("- refusals: " + ", ".join(f"{k} ({v})" for k, v in refusals.items()))
    return "\n".join(x for x in L if x) + "\n"


def sweep_piece(seed: int, i: int) -> dict:
    """Scene i of the sweep seeded ``seed``, drawn and checked with the disk cache off (a module-level function: dask
    workers import it)."""
    old = os.environ.get("PALPATE_CACHE")
    os.environ["PALPATE_CACHE"] = "0"
    try:
        rng = np.random.default_rng([seed, i])
        return check_scene(random_scene(rng, i), rng)
    finally:
        if old is None:
            os.environ.pop("PALPATE_CACHE", None)
        else:
            os.environ["PALPATE_CACHE"] = old


def write_results(rows: list[dict], out: Path) -> str:
    """sweep.csv (one row per scene) and sweep.md (the summary) in ``out``; returns the markdown."""
    out.mkdir(parents=True, exist_ok=True)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(out / "sweep.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    md = summarize(rows)
    (out / "sweep.md").write_text(md)
    return md
