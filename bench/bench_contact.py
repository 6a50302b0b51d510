"""Benchmark of the contact fast path (fem.contact.SurfaceModel) on one scene: setup, per-waypoint cost, the
speedup over a plain full re-solve per waypoint at equal answer, and the force error against a converged mesh.

    python bench/bench_contact.py --out bench-out [--scene paper] [--quick] [--repeats 5] [--fresh-reference]

What is timed (wall clock, ``time.perf_counter``; CPU time of the process alongside, steadier on a shared machine):
- setup, cold: gmsh meshing, assembly (build_model on a freshly made mesh: no disk or memory cache), then the
  Schur factorization and condensation (SurfaceModel on that model), then the influence operators that give the
  stresses and the inversion check per waypoint (fem.influence).
- 100 waypoints (x from 5 to 65 mm, depth 4 mm) force only (one small LCP each) and with stresses
  (``indent_many``: LCPs, then per waypoint the band stresses, max von Mises and the no-inversion check from the
  influence operators).
- end to end: mesh + assembly + factor + condense + 100 predictions with stresses, one stopwatch.
- full re-solve: ``indent_full`` (refactorizes K at every active-set iteration; the model, i.e. mesh and K, is
  reused) on a subset of the waypoints; its per-waypoint median times 100 is labelled *extrapolated*.
Each timing is repeated ``--repeats`` times (fresh models for the setup); medians and minima are reported.

Equal answer: the fast and full paths' forces and max von Mises on the subset are compared (max relative
difference). Accuracy: the forces at all 100 waypoints against a converged mesh (default: P2, h = 1 mm, top-edge
size 0.125 mm; --quick: h = 1.5 mm, top 0.25 mm); the references are expensive, so their forces are cached in
OUT/contact_reference.json and OUT/contact_reference_mid.json (the h = 1.5 mm mesh, also the converged-ness check
of the finer one) keyed by the scene's content, the reference analysis and the waypoints (--fresh-reference
recomputes them; the report says when cached forces were used and when they were computed).

``run(out_dir, quick=False) -> dict`` is the entry point for ``palpate bench``; it writes OUT/contact.json and
OUT/contact.md (markdown, ready for docs/fem.md).
"""
from __future__ import annotations

import os

# Single-threaded BLAS (before numpy loads; an explicit setting in the environment wins). On 2 shared cores,
# OpenBLAS's threads spin against the other processes: measured 3-4x more CPU time for the 100 waypoints with
# stresses (SuperLU's multi-right-hand-side solve calls BLAS per supernode). Imported by `palpate bench` after
# numpy, this has no effect there: that process's setting applies (recorded in the output as blas_threads).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from fem import scene as S  # noqa: E402
from fem.contact import SurfaceModel, indent_full  # noqa: E402
from fem.mesh import mesh_scene  # noqa: E402
from fem.model import build_model  # noqa: E402
from fem.stress import components, nodal_poisson, recovery_operator  # noqa: E402

TARGETS = {"after_setup_100_s": 0.3, "end_to_end_100_s": 1.0, "force_rel_error": 0.005}
N_WAYPOINTS = 100
DEPTH_M = 0.004
MARGIN_M = 0.005
REFERENCE = {"order": 2, "mesh_size_m": 0.001, "surface_refine": 8.0}
REFERENCE_QUICK = {"order": 2, "mesh_size_m": 0.0015, "surface_refine": 6.0}


class Clock:
    """Wall and process-CPU stopwatch."""

    def __enter__(self):
        self.w, self.c = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall, self.cpu = time.perf_counter() - self.w, time.process_time() - self.c


def _stats(values: list[float]) -> dict:
    return {"median": statistics.median(values), "min": min(values), "max": max(values), "n": len(values)}


def cold_setup(sc):
    """(SurfaceModel, {mesh_s, assemble_s, factor_condense_s}) without any cache."""
    with Clock() as a:
        mesh = mesh_scene(sc)
    with Clock() as b:
        model = build_model(sc, mesh=mesh)
        model.K                                   # assembled on first use: time it here
    with Clock() as c:
        m = SurfaceModel(sc, model=model)
    with Clock() as d:
        m.influence()
    return m, {"mesh_s": a.wall, "assemble_s": b.wall, "factor_condense_s": c.wall, "influence_s": d.wall,
               "setup_s": a.wall + b.wall + c.wall + d.wall, "setup_cpu_s": a.cpu + b.cpu + c.cpu + d.cpu}


def band_max_von_mises(m: SurfaceModel, u: np.ndarray) -> float:
    """Max von Mises over the same band of nodes the fast path searches, from a full displacement vector."""
    mesh = m.model.mesh
    nodes = np.flatnonzero(mesh.nodes[:, 1] >= mesh.height_m - m.band_m - 1e-12)
    s = (recovery_operator(m.model, nodes) @ u).reshape(-1, 3)
    return float(components(s, nodal_poisson(m.model, nodes), m.model.plane)["von_mises_pa"].max())


def reference_forces(sc, xs, out_dir: Path, analysis: dict, fresh: bool,
                     name: str = "contact_reference.json") -> dict:
    """Forces at xs on a fine mesh; cached in out_dir/name."""
    ref_sc = sc.with_analysis(**analysis)
    key = {"scene_key": sc.key(), "analysis": analysis, "depth_m": DEPTH_M, "x_m": [float(x) for x in xs]}
    path = out_dir / name
    if not fresh and path.exists():
        try:
            d = json.loads(path.read_text())
            if d.get("key") == key:
                d["cached"] = True
                return d
        except (OSError, ValueError):
            pass
    print(f"  reference mesh P{analysis['order']}, h = {analysis['mesh_size_m'] * 1e3:g} mm, top "
          f"{analysis['mesh_size_m'] / analysis['surface_refine'] * 1e3:g} mm: building ...", flush=True)
    m, t = cold_setup(ref_sc)
    f = [m.force_n(float(x), DEPTH_M) for x in xs]
    d = {"key": key, "force_n": f, "dofs": int(m.model.n_dofs), "setup_s": t["setup_s"],
         "computed": time.strftime("%Y-%m-%d %H:%M:%S")}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(d, indent=1) + "\n")
    d["cached"] = False
    print(f"  reference: {d['dofs']} DOFs, setup {t['setup_s']:.1f} s (cached in {path})", flush=True)
    return d


def run(out_dir, quick: bool = False, scene: str = "paper", repeats: int | None = None,
        full_subset: int | None = None, fresh_reference: bool = False) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    repeats = repeats or (2 if quick else 5)
    full_subset = full_subset or (2 if quick else 5)
    sc = S.load(scene)
    xs = np.linspace(MARGIN_M, sc.tissue.width_m - MARGIN_M, N_WAYPOINTS)
    print(f"contact benchmark: scene {scene}, {N_WAYPOINTS} waypoints at depth {DEPTH_M * 1e3:g} mm, "
          f"{repeats} repeats", flush=True)

    setup, force_only, stresses, e2e, e2e_cpu, after_cpu = [], [], [], [], [], []
    for k in range(repeats):
        with Clock() as total:
            m, t = cold_setup(sc)
            with Clock() as s:
                res = m.indent_many(xs, DEPTH_M)
        with Clock() as f:
            forces = [m.force_n(float(x), DEPTH_M) for x in xs]
        setup.append(t)
        stresses.append(s.wall)
        after_cpu.append(s.cpu)
        force_only.append(f.wall)
        e2e.append(total.wall)
        e2e_cpu.append(total.cpu)
        print(f"  run {k + 1}: setup {t['setup_s']:.3f} s (mesh {t['mesh_s']:.3f}, assemble {t['assemble_s']:.3f}, "
              f"factor+condense {t['factor_condense_s']:.3f}) | 100 waypoints: force only {f.wall:.3f} s, "
              f"with stresses {s.wall:.3f} s | end to end {total.wall:.3f} s (cpu {total.cpu:.3f} s)", flush=True)
    fast_force = np.array([r.force_n for r in res])
    assert np.allclose(fast_force, forces, rtol=1e-12)
    fast_vm = np.array([r.max_von_mises_pa for r in res])

    # full re-solve per waypoint on a subset spread over the surface (over the stone and away from it)
    sub = np.unique(np.linspace(0, N_WAYPOINTS - 1, full_subset).round().astype(int))
    full_t, dF, dV, iters = [], [], [], []
    for i in sub:
        with Clock() as c:
            r = indent_full(sc, float(xs[i]), DEPTH_M, model=m.model)
        full_t.append(c.wall)
        iters.append(r["iterations"])
        dF.append(abs(r["force_n"] / fast_force[i] - 1))
        dV.append(abs(band_max_von_mises(m, r["u"]) / fast_vm[i] - 1))
        print(f"  full re-solve x = {xs[i] * 1e3:.1f} mm: {c.wall:.3f} s, {r['iterations']} active-set iterations, "
              f"force differs by {dF[-1]:.1e}, max von Mises by {dV[-1]:.1e}", flush=True)

    ref_analysis = REFERENCE_QUICK if quick else REFERENCE
    ref = reference_forces(sc, xs, out_dir, ref_analysis, fresh_reference,
                           name="contact_reference_mid.json" if quick else "contact_reference.json")
    err = np.abs(fast_force / np.asarray(ref["force_n"]) - 1)
    check = None
    if not quick:   # is the reference converged? the next coarser mesh against it
        mid = reference_forces(sc, xs, out_dir, REFERENCE_QUICK, fresh_reference, name="contact_reference_mid.json")
        d = np.abs(np.asarray(mid["force_n"]) / np.asarray(ref["force_n"]) - 1)
        check = {"analysis": REFERENCE_QUICK, "dofs": mid["dofs"], "max_rel_force_diff": float(d.max())}

    med = lambda v: statistics.median(v)  # noqa: E731
    per_wp_stress = med(stresses) / N_WAYPOINTS
    per_wp_force = med(force_only) / N_WAYPOINTS
    per_wp_full = med(full_t)
    result = {
        "scene": scene, "waypoints": N_WAYPOINTS, "depth_m": DEPTH_M, "repeats": repeats, "quick": quick,
        "analysis": {"order": sc.analysis.order, "mesh_size_m": sc.analysis.mesh_size_m,
                     "surface_refine": sc.analysis.surface_refine, "plane": sc.analysis.plane},
        "dofs": int(m.model.n_dofs), "contact_candidates": int(len(m.top)),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform(),
                    "load_avg_1m": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
                    "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS", "default")},
        "setup_s": {k: _stats([t[k] for t in setup]) for k in setup[0]},
        "force_only_100_s": _stats(force_only),
        "with_stresses_100_s": _stats(stresses),
        "with_stresses_100_cpu_s": _stats(after_cpu),
        "end_to_end_100_s": _stats(e2e),
        "end_to_end_100_cpu_s": _stats(e2e_cpu),
        "per_waypoint_s": {"force_only": per_wp_force, "with_stresses": per_wp_stress, "full_resolve": per_wp_full},
        "full_resolve": {"waypoints_timed": int(len(sub)), "x_m": xs[sub].tolist(), "per_waypoint_s": _stats(full_t),
                         "iterations": iters, "extrapolated_100_s": per_wp_full * N_WAYPOINTS,
                         "note": "timed on the subset, times 100 = extrapolated; model (mesh, K) reused"},
        "speedup": {"vs_with_stresses": per_wp_full / per_wp_stress, "vs_force_only": per_wp_full / per_wp_force,
                    "vs_with_stresses_incl_setup": per_wp_full * N_WAYPOINTS / med(e2e)},
        "equal_answer": {"max_rel_force_diff": max(dF), "max_rel_von_mises_diff": max(dV)},
        "accuracy": {"reference_analysis": ref_analysis, "reference_dofs": ref["dofs"],
                     "reference_cached": ref["cached"], "reference_computed": ref.get("computed"),
                     "max_rel_force_error": float(err.max()), "median_rel_force_error": float(np.median(err)),
                     "worst_x_m": float(xs[int(np.argmax(err))]), "reference_check": check},
    }
    result["targets"] = {
        "after_setup_100_s": {"target": TARGETS["after_setup_100_s"], "median": med(stresses),
                              "met": med(stresses) < TARGETS["after_setup_100_s"]},
        "end_to_end_100_s": {"target": TARGETS["end_to_end_100_s"], "median": med(e2e),
                             "met": med(e2e) < TARGETS["end_to_end_100_s"]},
        "force_rel_error": {"target": TARGETS["force_rel_error"], "value": float(err.max()),
                            "met": float(err.max()) < TARGETS["force_rel_error"]},
    }
    md = markdown(result)
    (out_dir / "contact.json").write_text(json.dumps(result, indent=1) + "\n")
    (out_dir / "contact.md").write_text(md)
    print(md)
    return result


def markdown(r: dict) -> str:
    s, T = r["setup_s"], r["targets"]
    ms = lambda v: f"{v * 1e3:.1f} ms"  # noqa: E731

    def row(label, st, unit=1.0, fmt="{:.3f} s"):
        return f"| {label} | {fmt.format(st['median'] * unit)} | {fmt.format(st['min'] * unit)} |"

    acc, fr, eq, sp = r["accuracy"], r["full_resolve"], r["equal_answer"], r["speedup"]
    ra = acc["reference_analysis"]
    ok = lambda b: "met" if b else "**MISSED**"  # noqa: E731
    lines = [
        f"Scene `{r['scene']}` (P{r['analysis']['order']}, h = {r['analysis']['mesh_size_m'] * 1e3:g} mm, top "
        f"{r['analysis']['mesh_size_m'] / r['analysis']['surface_refine'] * 1e3:g} mm, plane {r['analysis']['plane']}: "
        f"{r['dofs']:,} DOFs, {r['contact_candidates']} candidate contact nodes), {r['waypoints']} waypoints from 5 to "
        f"65 mm at depth {r['depth_m'] * 1e3:g} mm, rigid cylinder R = 5 mm. Wall clock on {r['machine']['cpus']} "
        f"shared cores (load average {r['machine']['load_avg_1m']:.1f} at the end; BLAS threads "
        f"{r['machine']['blas_threads']}), {r['repeats']} runs: median and minimum; process CPU time alongside (what "
        "an unloaded machine's wall clock would show: the code is single-threaded). Cold setup: no mesh or factor "
        "cache.", "",
        "| step | median | min |", "|---|---:|---:|",
        row("mesh (gmsh)", s["mesh_s"]), row("assemble", s["assemble_s"]),
        row("factor + Schur condensation", s["factor_condense_s"]),
        row("influence operators (stresses, inversion check)", s["influence_s"]), row("**setup total**", s["setup_s"]),
        row(f"{r['waypoints']} waypoints, force only", r["force_only_100_s"]),
        row(f"**{r['waypoints']} waypoints, force + max von Mises**", r["with_stresses_100_s"]),
        row("  (same, process CPU time)", r["with_stresses_100_cpu_s"]),
        row(f"**end to end** (setup + {r['waypoints']} waypoints with stresses)", r["end_to_end_100_s"]),
        row("  (same, process CPU time)", r["end_to_end_100_cpu_s"]),
        f"| per waypoint: force only / with stresses | {ms(r['per_waypoint_s']['force_only'])} / "
        f"{ms(r['per_waypoint_s']['with_stresses'])} | |",
        row(f"full re-solve, per waypoint ({fr['waypoints_timed']} timed)", fr["per_waypoint_s"]),
        f"| full re-solve, {r['waypoints']} waypoints (*extrapolated*) | {fr['extrapolated_100_s']:.1f} s | |", "",
        f"Speedup of the fast path over a full re-solve per waypoint (which refactorizes K in each of its "
        f"{min(fr['iterations'])}-{max(fr['iterations'])} active-set iterations): **{sp['vs_with_stresses']:.0f}x** "
        f"with stresses, {sp['vs_force_only']:.0f}x force only, {sp['vs_with_stresses_incl_setup']:.0f}x counting "
        f"the fast path's setup. Equal answer: forces agree to {eq['max_rel_force_diff']:.1e} and max von Mises to "
        f"{eq['max_rel_von_mises_diff']:.1e} (relative, max over the timed waypoints).", "",
        f"Force error against a converged mesh (P{ra['order']}, h = {ra['mesh_size_m'] * 1e3:g} mm, top "
        f"{ra['mesh_size_m'] / ra['surface_refine'] * 1e3:g} mm, {acc['reference_dofs']:,} DOFs"
        f"{', forces cached from ' + str(acc['reference_computed']) if acc['reference_cached'] else ''}): "
        f"max {100 * acc['max_rel_force_error']:.3f} % (at x = {acc['worst_x_m'] * 1e3:.1f} mm), median "
        f"{100 * acc['median_rel_force_error']:.3f} % over the {r['waypoints']} waypoints."
        + (f" The reference is converged: the next coarser mesh (h = "
           f"{acc['reference_check']['analysis']['mesh_size_m'] * 1e3:g} mm, {acc['reference_check']['dofs']:,} DOFs) "
           f"differs from it by at most {100 * acc['reference_check']['max_rel_force_diff']:.3f} %."
           if acc.get("reference_check") else ""), "",
        "| target | value | |", "|---|---:|---|",
        f"| {r['waypoints']} waypoints after setup < {T['after_setup_100_s']['target']} s | "
        f"{T['after_setup_100_s']['median']:.3f} s | {ok(T['after_setup_100_s']['met'])} |",
        f"| end to end < {T['end_to_end_100_s']['target']} s | {T['end_to_end_100_s']['median']:.3f} s | "
        f"{ok(T['end_to_end_100_s']['met'])} |",
        f"| force within {100 * T['force_rel_error']['target']:g} % of a converged mesh | "
        f"{100 * T['force_rel_error']['value']:.3f} % | {ok(T['force_rel_error']['met'])} |",
    ]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="bench-out", help="output directory (contact.json, contact.md)")
    ap.add_argument("--scene", default="paper")
    ap.add_argument("--quick", action="store_true", help="2 repeats, 2 full re-solves, a cheaper reference mesh")
    ap.add_argument("--repeats", type=int, help="timing repeats (default 5, quick 2)")
    ap.add_argument("--full-subset", type=int, help="waypoints timed with the full re-solve (default 5, quick 2)")
    ap.add_argument("--fresh-reference", action="store_true", help="recompute the converged-mesh forces")
    a = ap.parse_args(argv)
    run(a.out, quick=a.quick, scene=a.scene, repeats=a.repeats, full_subset=a.full_subset,
        fresh_reference=a.fresh_reference)
    return 0


if __name__ == "__main__":
    sys.exit(main())
