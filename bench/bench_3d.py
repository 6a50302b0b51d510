"""Benchmarks of fem in 3D (issue 15): numbers printed and written, not timed tests.

    python bench/bench_3d.py convergence [--out bench-out] [--levels p2-2.0 p2-1.5 ...]
                                     # or the uniform family s1.00 s0.90 ... s0.60 (FAMILY_BASE times S)
    python bench/bench_3d.py waypoints   [--out bench-out]       # block3d, 100 waypoints, set-up, cache, memory
    python bench/bench_3d.py hertz       [--out bench-out]       # rigid sphere on a block 20 R wide
    python bench/bench_3d.py solvers [LEVEL [METHOD ...]] [--out bench-out]   # Schur condensation: CHOLMOD with
                                     # METIS or AMD, SuperLU; the full solve against the backward sweep
    python bench/bench_3d.py table       [--out bench-out]       # markdown from the JSON lines written above

Every configuration runs in its own process (``one``), so its peak resident memory (ru_maxrss) is its own; each
appends one JSON line to OUT/bench_3d_<kind>.jsonl. Wall times on this shared 2-core machine vary with the other
sessions' load: the load average at the start of each run is recorded next to its times.

convergence: block3d (stone 15 mm at 25 mm depth under (35, 35) mm; spherical tip R = 5 mm) at several meshes (P1,
P2; top-patch size h_top = mesh_size_m / surface_refine), the forces at the benchmark's 100 waypoints (a 10 x 10
grid over the central 40 x 40 mm, depth 3 mm) and the load A peak; errors against the finest mesh run.
waypoints: the default block3d mesh: set-up (mesh, assemble, factor + condense, with CHOLMOD's parts), the disk
cache's store and reload (a fresh process), per-waypoint force-only and with-stresses times, peak memory; then a
third process whose stresses come from the factor the reload stored (fem.interior_factor): its first stress query
and the same 100 batched maxima, compared bitwise.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
LEVELS = {   # name: (order, mesh_size_m, surface_refine)
    "p1-1.25": (1, 0.010, 8.0), "p1-0.83": (1, 0.010, 12.0),
    "p2-2.0": (2, 0.012, 6.0), "p2-1.5": (2, 0.012, 8.0), "p2-1.25": (2, 0.010, 8.0), "p2-1.0": (2, 0.010, 10.0),
    "p2-0.83": (2, 0.010, 12.0),
    "p2-2.0-10": (2, 0.010, 5.0), "p2-1.5-10": (2, 0.010, 20.0 / 3.0),   # the 10 mm bulk cap of p2-1.25, p2-1.0
}
GRADES = {"g25": 0.25, "g35": 0.35, "g18": 0.18}   # a level name with a suffix -g25 uses analysis.grade = 0.25
DEPTH_M = 0.003
# The uniformly refined family "sS": block3d's first default mesh (bulk 12 mm, surface_refine 8: 1.5 mm on the patch,
# grade 0.25) with every size and the grading slope times S. block3d's default since 2026-11-26 is s0.80.
FAMILY_BASE = (0.012, 8.0, 0.25)


def _rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6


def _grid():
    xs = np.linspace(0.015, 0.055, 10)
    return [(float(x), float(y)) for y in xs for x in xs]


def _level_scene(level: str):
    """(block3d at LEVELS[level], order, mesh_size_m, surface_refine); a suffix -g25 sets analysis.grade. A level
    "sS" (e.g. s0.80) is block3d's default mesh scaled uniformly by S: every size (top patch, stones' surfaces,
    bulk cap) and the grading slope times S, so the meshes of the family differ only in resolution."""
    from fem.scene import load
    if level.startswith("s"):
        s = float(level[1:])
        sc = load("block3d").with_analysis(order=2, mesh_size_m=FAMILY_BASE[0] * s, surface_refine=FAMILY_BASE[1],
                                            grade=FAMILY_BASE[2] * s)
        return sc, 2, sc.analysis.mesh_size_m, sc.analysis.surface_refine
    base, _, g = level.partition("-g")
    order, size, refine = LEVELS[base]
    sc = load("block3d").with_analysis(order=order, mesh_size_m=size, surface_refine=refine,
                                        grade=GRADES[f"g{g}"] if g else None)
    return sc, order, size, refine


def one_convergence(level: str) -> dict:
    from fem.contact3d import SurfaceModel3D
    from fem.model3d import build_model3d
    from fem.scene_mesh3d import mesh_for3d
    from fem.uniform3d import solve_uniform3d
    sc, order, size, refine = _level_scene(level)
    t0 = time.perf_counter()
    mesh = mesh_for3d(sc, use=False)
    t1 = time.perf_counter()
    model = build_model3d(sc, mesh=mesh)
    model.K                                     # assembled here (Model3D assembles on first use)
    t2 = time.perf_counter()
    sm = SurfaceModel3D(sc, model=model)
    t3 = time.perf_counter()
    forces, ts = [], []
    for x, y in _grid():
        s = time.perf_counter()
        forces.append(sm.force_n(x, y, DEPTH_M))
        ts.append(time.perf_counter() - s)
    la = solve_uniform3d(sc, model=model, full_field=False)
    xp, yp, vp = la.surface.peak()
    return {"level": level, "order": order, "mesh_size_m": size, "surface_refine": refine,
            "grade": sc.analysis.grade or 0.5,
            "h_top_m": size / refine, "nodes": int(mesh.n_nodes), "tets": int(len(mesh.tets)),
            "dofs": int(model.n_dofs), "patch_nodes": int(len(sm.patch)), "forces_n": forces,
            "force_centre_n": sm.force_n(0.035, 0.035, DEPTH_M), "load_a_peak": [xp, yp, vp],
            "mesh_s": t1 - t0, "assemble_s": t2 - t1, "condense_s": t3 - t2,
            "condense_parts_s": sm.timings_s.get("condense_parts_s", {}),
            "per_waypoint_median_s": float(np.median(ts)), "peak_rss_gb": _rss_gb(), "load_avg": os.getloadavg()[0]}


def one_waypoints(cache_dir: str, phase: str) -> dict:
    """phase "build": cold set-up and store; "reload": a fresh process restoring from the disk cache (its first
    stress query factorizes once and stores the factor's interior columns); "refactor-free": another fresh process,
    whose stresses come from that stored factor (fem.interior_factor)."""
    os.environ["PALPATE_CACHE_DIR"] = cache_dir
    from fem.contact3d import surface_model3d
    from fem.scene import load
    sc = load("block3d")
    t0 = time.perf_counter()
    sm = surface_model3d(sc, cache=True)
    t1 = time.perf_counter()
    out = {"phase": phase, "setup_or_reload_s": t1 - t0, "timings_s": sm.timings_s, "patch_nodes": int(len(sm.patch)),
           "load_avg": os.getloadavg()[0]}
    if phase == "build":
        return {**out, "peak_rss_gb": _rss_gb()}
    grid = _grid()
    forces, tf = [], []
    for x, y in grid:
        s = time.perf_counter()
        forces.append(sm.force_n(x, y, DEPTH_M))
        tf.append(time.perf_counter() - s)
    s = time.perf_counter()
    sm.indent(0.035, 0.035, DEPTH_M)
    first_stress_s = time.perf_counter() - s        # "reload": assembles the model and factorizes K once
    tsx, fast = [], []
    for x, y in grid:
        s = time.perf_counter()
        fast.append(sm.indent(x, y, DEPTH_M, stresses=True))
        tsx.append(time.perf_counter() - s)
    s = time.perf_counter()
    batch = sm.indent_many([(x, y, DEPTH_M) for x, y in grid], stresses=True)
    batched = time.perf_counter() - s
    out.update({"forces_n": forces, "force_only_ms": {"median": 1e3 * float(np.median(tf)),
                                                       "max": 1e3 * float(np.max(tf))},
                "with_stresses_ms": {"median": 1e3 * float(np.median(tsx)), "max": 1e3 * float(np.max(tsx))},
                "with_stresses_batched_100_ms_each": 1e3 * batched / len(grid),
                "batched_max_von_mises_pa": [r.max_von_mises_pa for r in batch],
                "first_stress_query_s": first_stress_s, "factor_from_cache": "K" not in vars(sm.model)})
    if phase != "reload":
        return {**out, "peak_rss_gb": _rss_gb()}
    fac = sm.fac                               # the same waypoints by the full back-substitution (forward + back)
    interior = sm.interior
    sm.interior, sm._fac = (lambda: None), _FullSolveOnly(fac)
    tfull, dvm = [], []
    for (x, y), r in zip(grid[::5], fast[::5]):
        s = time.perf_counter()
        rf = sm.indent(x, y, DEPTH_M, stresses=True)
        tfull.append(time.perf_counter() - s)
        dvm.append(abs(r.max_von_mises_pa / rf.max_von_mises_pa - 1))
    sm.interior, sm._fac = interior, fac
    return {**out, "full_solve_path_ms": {"median": 1e3 * float(np.median(tfull)), "max": 1e3 * float(np.max(tfull)),
                                          "n": len(tfull), "max_rel_diff_von_mises": float(max(dvm))},
            "ordering": getattr(fac, "ordering", "superlu"), "peak_rss_gb": _rss_gb()}


class _FullSolveOnly:
    """A condensing factorization seen without ``solve_contact``: stresses by the full back-substitution."""

    def __init__(self, fac):
        self.free, self.c, self.compliance, self.solve = fac.free, fac.c, fac.compliance, fac.solve


def one_hertz(fine_over_R: float, W_over_R: float = 20.0, d_over_R: float = 0.05, H_over_W: float = 0.5,
              grade: float = 0.5) -> dict:
    from scipy.optimize import brentq

    from fem.contact3d import SurfaceModel3D
    from fem.mesh3d import mesh_block
    from fem.scene import Analysis, Indenter, Scene, Tissue
    R, E, nu = 0.005, 2500.0, 0.4
    W, H, d = W_over_R * R, H_over_W * W_over_R * R, d_over_R * R
    a = np.sqrt(R * d)
    fine = R * fine_over_R
    sc = Scene(name="hertz", tissue=Tissue(width_m=W, length_m=W, height_m=H, youngs_pa=E, poisson=nu),
               indenter=Indenter(shape="sphere", radius_m=R),
               analysis=Analysis(order=2, mesh_size_m=H / 4, surface_refine=H / 4 / (4 * fine), patch_m=2.2 * R,
                                 top_displacement_m=0.0))
    t0 = time.perf_counter()
    mesh = mesh_block(W, W, H, [], H / 4, H / 4 / (4 * fine), 2, patch_m=2.2 * R, focus=(W / 2, W / 2, fine, 1.5 * a),
                      grade=grade)
    sm = SurfaceModel3D(sc, mesh=mesh)
    r = sm.indent(W / 2, W / 2, d, stresses=False)
    Es = E / (1 - nu ** 2)
    F_hertz = 4 / 3 * Es * np.sqrt(R) * d ** 1.5
    a_s = brentq(lambda x: x / 2 * np.log((R + x) / (R - x)) - d, 1e-12, 0.999 * R)
    F_sneddon = Es / 2 * ((a_s ** 2 + R ** 2) * np.log((R + a_s) / (R - a_s)) - 2 * a_s * R)
    return {"fine_over_R": fine_over_R, "W_over_R": W_over_R, "H_over_R": H_over_W * W_over_R, "d_over_R": d_over_R,
            "grade": grade,
            "nodes": int(mesh.n_nodes), "dofs": int(sm.model.n_dofs), "patch_nodes": int(len(sm.patch)),
            "force_n": r.force_n, "hertz_n": F_hertz, "sneddon_sphere_n": F_sneddon,
            "err_hertz": r.force_n / F_hertz - 1, "err_sneddon": r.force_n / F_sneddon - 1,
            "contact_radius_m": r.contact_radius_m, "hertz_radius_m": a, "sneddon_radius_m": a_s,
            "time_s": time.perf_counter() - t0, "peak_rss_gb": _rss_gb(), "load_avg": os.getloadavg()[0]}


def one_solver(method: str, level: str) -> dict:
    """method: superlu, cholmod (the default ordering), cholmod-amd or cholmod-metis."""
    from fem.condense import schur
    from fem.contact3d import patch_nodes
    from fem.model3d import build_model3d, fixed_bottom
    from fem.scene_mesh3d import mesh_for3d
    sc = _level_scene(level)[0]
    model = build_model3d(sc, mesh=mesh_for3d(sc, use=False))
    model.K                                     # assembled before the memory baseline and the timer
    fixed = np.unique(fixed_bottom(model))
    free = np.setdiff1d(np.arange(model.n_dofs), fixed)
    contact = model.reduced_index(3 * patch_nodes(model.mesh, sc.analysis.patch_m) + 2)
    r0 = _rss_gb()
    kind, _, ordering = method.partition("-")
    t0 = time.perf_counter()
    f = schur(model.K, free, contact, kind, ordering or "auto")
    t = time.perf_counter() - t0
    C = f.compliance
    row = {"method": method, "level": level, "dofs": int(model.n_dofs), "patch_nodes": int(len(contact)),
           "condense_s": t, "peak_rss_gb": _rss_gb(), "rss_before_gb": r0, "trace_C": float(np.trace(C)),
           "parts_s": getattr(f, "timings_s", {}), "load_avg": os.getloadavg()[0]}
    if hasattr(f, "solve_contact"):            # one waypoint's displacements: full solve against backward sweep
        rng = np.random.default_rng(0)
        F = np.zeros((len(contact), 1))
        F[rng.choice(len(contact), 300, replace=False)] = rng.random((300, 1))
        rhs = np.zeros((len(free), 1))
        rhs[f.c] = F
        s = time.perf_counter()
        f.solve(rhs[:, 0])
        row["solve_factor_s"] = time.perf_counter() - s
        full, back = [], []
        for _ in range(9):
            s = time.perf_counter()
            u = f.solve(rhs)
            full.append(time.perf_counter() - s)
            s = time.perf_counter()
            v = f.solve_contact(F)
            back.append(time.perf_counter() - s)
        row.update(full_solve_ms=1e3 * float(np.median(full)), backward_sweep_ms=1e3 * float(np.median(back)),
                   max_rel_diff=float(np.abs(u - v).max() / np.abs(u).max()))
    return row


def _spawn(out: Path, kind: str, *args: str) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "one", kind, *args]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if p.returncode != 0:
        print(p.stderr[-3000:], file=sys.stderr)
        raise SystemExit(f"{kind} {args} failed")
    row = json.loads(p.stdout.strip().splitlines()[-1])
    out.mkdir(parents=True, exist_ok=True)
    with open(out / f"bench_3d_{kind}.jsonl", "a") as f:
        f.write(json.dumps(row) + "\n")
    brief = {k: v for k, v in row.items() if not isinstance(v, list)}
    print(json.dumps(brief), flush=True)
    return row


def _read(out: Path, kind: str) -> list[dict]:
    p = out / f"bench_3d_{kind}.jsonl"
    return [json.loads(line) for line in p.read_text().splitlines() if line.strip()] if p.exists() else []


def richardson(rows: list[dict], bulk_m: float = 0.010, grade: float = 0.25) -> list[str]:
    """Markdown lines: the P2 runs at one bulk cap and grade, refined in h_top only; the observed order p from the
    three finest (h1 > h2 > h3: (F1 - F2) / (F2 - F3) = (h1^p - h2^p) / (h2^p - h3^p), per waypoint, median),
    the extrapolated forces F_inf = F3 + (F3 - F2) h3^p / (h2^p - h3^p), and every run's error against them."""
    from scipy.optimize import brentq
    seq = sorted((r for r in rows if r["order"] == 2 and r["mesh_size_m"] == bulk_m and r.get("grade") == grade),
                 key=lambda r: -r["h_top_m"])
    if len(seq) < 3:
        return []
    (h1, h2, h3), (F1, F2, F3) = ([r["h_top_m"] for r in seq[-3:]],
                                  [np.asarray(r["forces_n"]) for r in seq[-3:]])
    ratio = (F1 - F2) / (F2 - F3)

    def order(q):
        g = lambda p: (h1 ** p - h2 ** p) / (h2 ** p - h3 ** p) - q   # noqa: E731  (increasing in p)
        return brentq(g, 0.05, 12.0) if g(0.05) < 0 < g(12.0) else np.nan
    ps = np.array([order(q) for q in ratio])
    monotone = np.isfinite(ps)
    p = float(np.median(ps[monotone]))
    F_inf = F3 + (F3 - F2) * h3 ** p / (h2 ** p - h3 ** p)
    hs = ", ".join(f"{r['h_top_m'] * 1e3:g}" for r in seq)
    c2, c3 = seq[-2]["force_centre_n"], seq[-1]["force_centre_n"]
    centre = c3 + (c3 - c2) * h3 ** p / (h2 ** p - h3 ** p)
    out = [f"Richardson, P2, grade {grade:g}, bulk cap {bulk_m * 1e3:g} mm, h_top {hs} mm: forces converge "
           f"monotonically at "
           f"{monotone.sum()} of {len(ps)} waypoints; observed order p = {p:.2f} (median; 10-90 %: "
           f"{np.percentile(ps[monotone], 10):.2f}-{np.percentile(ps[monotone], 90):.2f}); "
           f"extrapolated force at (35, 35) mm {centre:.6g} N", "",
           "| mesh | h_top (mm) | bulk cap (mm) | DOFs | max error against F_inf (100 waypoints) | mean error | error at (35, 35) mm |",
           "|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["order"], -r["h_top_m"], r["mesh_size_m"])):
        if r["order"] == 2 and r.get("grade") == grade:
            e = np.asarray(r["forces_n"]) / F_inf - 1
            out.append(f"| {r['level']} | {r['h_top_m'] * 1e3:.3g} | {r['mesh_size_m'] * 1e3:g} | {r['dofs']} | "
                       f"{np.abs(e).max():.2%} | {e.mean():+.2%} | {r['force_centre_n'] / centre - 1:+.2%} |")
    return out + [""] + grading_effect(rows, seq[-1], bulk_m, grade)


def family_limit(rows: list[dict]) -> dict | None:
    """The converged forces from the uniformly refined family (levels "sS", at least four): per waypoint w,
    F_w(S) = F_inf,w (1 + c S^p) with c and p shared by all waypoints (the discretization error's shape) and
    F_inf,w free, by least squares on the relative residuals; p's standard error from the fit of the mean force
    over the waypoints, M(S) = M_inf + C S^p (whose mesh ripple averages out over 100 waypoints)."""
    from scipy.optimize import least_squares
    fam = sorted((r for r in rows if str(r["level"]).startswith("s")), key=lambda r: -float(r["level"][1:]))
    if len(fam) < 4:
        return None
    s = np.array([float(r["level"][1:]) for r in fam])
    F = np.array([r["forces_n"] for r in fam])

    def inf_of(c, p):
        shape = 1 + c * s[:, None] ** p
        return (F * shape).sum(0) / (shape ** 2).sum(0), shape

    def res(t):
        Finf, shape = inf_of(*t)
        return ((F - Finf * shape) / F).ravel()
    fit = min((least_squares(res, [0.01, p0], bounds=([-1, 0.3], [1, 8])) for p0 in (1.0, 2.0, 3.0)),
              key=lambda r: r.cost)
    c, p = fit.x
    F_inf, shape = inf_of(c, p)
    m = F.mean(axis=1)
    mf = least_squares(lambda t: (t[0] + t[1] * s ** t[2] - m) / m, [m[-1], m[0] - m[-1], p],
                       bounds=([0, -1, 0.3], [1, 1, 8]))
    dof = max(1, len(s) - 3)
    cov = np.linalg.pinv(mf.jac.T @ mf.jac) * (2 * mf.cost / dof)
    return {"rows": fam, "s": s, "F": F, "F_inf": F_inf, "c": float(c), "p": float(p),
            "ripple": (F / (F_inf * shape) - 1), "mean_fit": mf.x, "p_mean": float(mf.x[2]),
            "p_mean_sigma": float(np.sqrt(cov[2, 2]))}


def uniform_family(rows: list[dict]) -> list[str]:
    """Markdown lines: every run of the uniform family (and any other run) against the family's limit."""
    fam = family_limit(rows)
    if fam is None:
        return []
    rip = fam["ripple"]
    out = [f"Uniform refinement (levels sS: every size of the first default mesh times S, {len(fam['s'])} levels, "
           f"{fam['rows'][0]['dofs']}-{fam['rows'][-1]['dofs']} DOFs): F_w(S) = F_inf,w (1 + c S^p) with c = "
           f"{fam['c']:.4f}, p = {fam['p']:.2f} shared; the mean force alone gives p = {fam['p_mean']:.2f} +- "
           f"{fam['p_mean_sigma']:.2f}; the mesh ripple left (residual) rms {rip.std():.3%}, max "
           f"{np.abs(rip).max():.3%}.", "",
           "| mesh | S | h_top (mm) | grade | DOFs | max error against F_inf (100 waypoints) | mean error | "
           "set-up (s) | ms / waypoint (force) | peak memory (GB) |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: r["dofs"]):
        if r["order"] != 2:
            continue
        e = np.asarray(r["forces_n"]) / fam["F_inf"] - 1
        S = r["level"][1:] if str(r["level"]).startswith("s") else ""
        out.append(f"| {r['level']} | {S} | {r['h_top_m'] * 1e3:.3g} | {r.get('grade', 0.5):g} | {r['dofs']} | "
                   f"{np.abs(e).max():.2%} | {e.mean():+.2%} | "
                   f"{r['mesh_s'] + r['assemble_s'] + r['condense_s']:.1f} | "
                   f"{r['per_waypoint_median_s'] * 1e3:.2f} | {r['peak_rss_gb']:.2f} |")
    return out + [""]


def grading_effect(rows: list[dict], finest: dict, bulk_m: float, grade: float) -> list[str]:
    """Markdown lines: the force change from a finer bulk grading at equal h_top and cap, and the finest run
    corrected by it (additive: F(h_min, g_fine) ~ F(h_min, g) + F(h, g_fine) - F(h, g) at the finest h run with
    both); the default mesh's (p2-1.5-g25) error against that estimate."""
    key = {(r["h_top_m"], r["mesh_size_m"], r.get("grade")): r for r in rows if r["order"] == 2}
    pairs = sorted(((r, key[(r["h_top_m"], r["mesh_size_m"], grade)]) for r in rows
                    if r["order"] == 2 and r["mesh_size_m"] == bulk_m and r.get("grade", 0.5) < grade
                    and (r["h_top_m"], r["mesh_size_m"], grade) in key), key=lambda p: p[0]["h_top_m"])
    default = next((r for r in rows if r["level"] == "p2-1.5-g25"), None)
    if not pairs or default is None:
        return []
    out = ["| h_top (mm) | grade | DOFs | change from grade " f"{grade:g}: centre | mean over the 100 | max |",
           "|---|---|---|---|---|---|"]
    for fine, coarse in pairs:
        d = np.asarray(fine["forces_n"]) / np.asarray(coarse["forces_n"]) - 1
        out.append(f"| {fine['h_top_m'] * 1e3:.3g} | {fine['grade']:g} | {fine['dofs']} | "
                   f"{fine['force_centre_n'] / coarse['force_centre_n'] - 1:+.2%} | {d.mean():+.2%} | "
                   f"{d[np.argmax(np.abs(d))]:+.2%} |")
    fine, coarse = pairs[0]
    est = np.asarray(finest["forces_n"]) + np.asarray(fine["forces_n"]) - np.asarray(coarse["forces_n"])
    est_c = finest["force_centre_n"] + fine["force_centre_n"] - coarse["force_centre_n"]
    e = np.asarray(default["forces_n"]) / est - 1
    return out + ["", f"Estimate of a finer answer: {finest['level']} plus the grading change at h_top = "
                  f"{fine['h_top_m'] * 1e3:g} mm ({fine['level']} - {coarse['level']}): the default mesh "
                  f"(p2-1.5-g25) is above it by {e.mean():+.2%} on average, {np.abs(e).max():.2%} at worst, "
                  f"{default['force_centre_n'] / est_c - 1:+.2%} at (35, 35) mm.", ""]


def table(out: Path) -> str:
    """Markdown tables from the JSON lines (the last run of each configuration)."""
    lines = []
    conv = {r["level"]: r for r in _read(out, "convergence")}
    if conv:
        ref = min(conv.values(), key=lambda r: (-r["order"], r.get("grade", 0.5), r["h_top_m"]))   # finest bulk first
        F_ref = np.asarray(ref["forces_n"])
        lines += [f"block3d, 100 waypoints (10 x 10 over the central 40 x 40 mm, depth 3 mm); reference: "
                  f"{ref['level']} (P{ref['order']}, h_top = {ref['h_top_m'] * 1e3:g} mm)", "",
                  "| mesh | h_top (mm) | grade | DOFs | patch nodes | max force error | centre force (N) | load A peak (Pa) "
                  "| set-up (s): mesh + assemble + condense | ms / waypoint | peak memory (GB) | load avg |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in sorted(conv.values(), key=lambda r: (r["order"], -r["h_top_m"], -r.get("grade", 0.5))):
            err = np.max(np.abs(np.asarray(r["forces_n"]) / F_ref - 1))
            lines.append(f"| P{r['order']} {r['level']} | {r['h_top_m'] * 1e3:.3g} | {r.get('grade', 0.5):g} | {r['dofs']} | {r['patch_nodes']} | "
                         f"{err:.2%} | {r['force_centre_n']:.5g} | {r['load_a_peak'][2]:.4g} | "
                         f"{r['mesh_s']:.1f} + {r['assemble_s']:.1f} + {r['condense_s']:.1f} | "
                         f"{r['per_waypoint_median_s'] * 1e3:.2f} | {r['peak_rss_gb']:.2f} | {r['load_avg']:.1f} |")
        lines.append("")
        lines += richardson(list(conv.values()))
        lines += uniform_family(list(conv.values()))
    way = _read(out, "waypoints")
    if way:
        b = [r for r in way if r["phase"] == "build"][-1]
        rl = [r for r in way if r["phase"] == "reload"][-1]
        rf = ([r for r in way if r["phase"] == "refactor-free"] or [None])[-1]
        lines += ["block3d default mesh, benchmark:", "",
                  f"- set-up (cold, no cache): {b['setup_or_reload_s']:.1f} s: {json.dumps(b['timings_s'])}; peak "
                  f"memory {b['peak_rss_gb']:.2f} GB (load avg {b['load_avg']:.1f})",
                  f"- reload from the disk cache (fresh process): {rl['setup_or_reload_s']:.3f} s",
                  f"- per waypoint, force only: median {rl['force_only_ms']['median']:.2f} ms, max "
                  f"{rl['force_only_ms']['max']:.2f} ms",
                  f"- per waypoint with stresses: median {rl['with_stresses_ms']['median']:.1f} ms, max "
                  f"{rl['with_stresses_ms']['max']:.1f} ms (after a one-time {rl['first_stress_query_s']:.1f} s: "
                  f"assembly + factorization for the fields); batched (100 waypoints, one solve): "
                  f"{rl.get('with_stresses_batched_100_ms_each', float('nan')):.1f} ms each"
                  + (f"; the full back-substitution path on {rl['full_solve_path_ms']['n']} of them, same process: "
                     f"median {rl['full_solve_path_ms']['median']:.1f} ms, max {rl['full_solve_path_ms']['max']:.1f} "
                     f"ms, largest relative difference of the maximum von Mises "
                     f"{rl['full_solve_path_ms']['max_rel_diff_von_mises']:.1e} (ordering: {rl['ordering']})"
                     if "full_solve_path_ms" in rl else ""),
                  f"- peak memory of the reload + 320 queries process: {rl['peak_rss_gb']:.2f} GB"]
        if rf is not None:
            same = rf.get("batched_max_von_mises_pa") == rl.get("batched_max_von_mises_pa")
            lines.append(f"- a later process, the factor's interior columns from the disk cache (no assembly: "
                         f"{rf['factor_from_cache']}): first stress query {rf['first_stress_query_s']:.2f} s, per "
                         f"waypoint with stresses median {rf['with_stresses_ms']['median']:.1f} ms, batched "
                         f"{rf['with_stresses_batched_100_ms_each']:.1f} ms each; the 100 batched maxima "
                         f"{'bitwise equal to' if same else 'DIFFERENT from'} the reload's; peak memory "
                         f"{rf['peak_rss_gb']:.2f} GB")
        if conv:
            err = np.max(np.abs(np.asarray(rl["forces_n"]) / F_ref - 1))
            lines.append(f"- force error against {ref['level']}: max over the 100 waypoints {err:.2%}")
            fam = family_limit(list(conv.values()))
            if fam is not None:
                e = np.asarray(rl["forces_n"]) / fam["F_inf"] - 1
                lines.append(f"- force error against the uniform family's limit (p = {fam['p']:.2f}): max over the "
                             f"100 waypoints {np.abs(e).max():.2%}, mean {e.mean():+.2%}")
        lines.append("")
    hz = _read(out, "hertz")
    if hz:
        lines += ["Hertz, rigid sphere R = 5 mm on a block W wide and H deep (P2, focused refinement):", "",
                  "| W / R | H / R | grade | h under the tip / R | d / R | DOFs | F / F_Hertz - 1 | "
                  "F / F_sphere(Sneddon) - 1 | a / sqrt(R d) | time (s) |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for r in hz:
            lines.append(f"| {r['W_over_R']:g} | {r['H_over_R']:g} | {r.get('grade', 0.5):g} | "
                         f"{r['fine_over_R']:g} | {r['d_over_R']:g} | {r['dofs']} | {r['err_hertz']:+.2%} | "
                         f"{r['err_sneddon']:+.2%} | {r['contact_radius_m'] / r['hertz_radius_m']:.3f} | {r['time_s']:.1f} |")
        lines.append("")
    sol = _read(out, "solver")
    if sol:
        lines += ["Condensation onto the probed patch, same model:", "",
                  "| method | mesh | DOFs | patch nodes | time (s) | peak memory (GB) | parts | one waypoint's "
                  "displacements: full solve / backward sweep (ms) | load avg |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in sol:
            sweep = (f"{r['full_solve_ms']:.1f} / {r['backward_sweep_ms']:.1f}" if "full_solve_ms" in r else "")
            lines.append(f"| {r['method']} | {r['level']} | {r['dofs']} | {r['patch_nodes']} | {r['condense_s']:.1f} | "
                         f"{r['peak_rss_gb']:.2f} | {json.dumps({k: round(v, 1) for k, v in r['parts_s'].items()})} | "
                         f"{sweep} | {r['load_avg']:.1f} |")
    text = "\n".join(lines) + "\n"
    (out / "bench_3d.md").write_text(text)
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=("convergence", "waypoints", "hertz", "solvers", "table", "one"))
    ap.add_argument("rest", nargs="*")
    ap.add_argument("--out", default=str(ROOT / "bench-out"))
    ap.add_argument("--levels", nargs="*", default=list(LEVELS), help="LEVELS names, optionally with -g25 / -g35")
    a = ap.parse_args(argv)
    out = Path(a.out)
    if a.what == "one":
        kind, *args = a.rest
        fn = {"convergence": lambda: one_convergence(args[0]),
              "waypoints": lambda: one_waypoints(args[0], args[1]),
              "hertz": lambda: one_hertz(*map(float, args)),
              "solver": lambda: one_solver(args[0], args[1])}[kind]
        print(json.dumps(fn()))
        return 0
    if a.what == "convergence":
        for level in a.levels:
            _spawn(out, "convergence", level)
    elif a.what == "waypoints":
        with tempfile.TemporaryDirectory() as d:
            _spawn(out, "waypoints", d, "build")
            _spawn(out, "waypoints", d, "reload")
            _spawn(out, "waypoints", d, "refactor-free")
    elif a.what == "hertz":
        _spawn(out, "hertz", *(a.rest or ["0.05"]))
    elif a.what == "solvers":
        level, *methods = a.rest or ["p2-2.0"]
        for method in methods or ("cholmod-metis", "cholmod-amd", "superlu"):
            _spawn(out, "solver", method, level)
    print(table(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
