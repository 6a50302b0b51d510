"""Run time against error for the paper scene, what each skip saves and costs, locking, and scaling.

    python bench/bench_runtime_error.py --out bench-out [--quick] [--repeat 3]

Load A: the top-surface von Mises profile (top moved down 5 mm). Load B: the contact force over a raster of 41
waypoints at 4 mm depth. Errors are against a converged reference (P2, h = 0.5 mm for load A and h = 1 mm with
surface refinement 8 for load B; --quick: P2, h = 1 mm for both): load A as the largest difference of the profile
(interpolated at the reference's nodes) over the reference peak, load B as the largest force difference over the
largest reference force. Times are wall-clock medians of --repeat runs (the machine is shared: ~2x noise), cold:
meshing, assembly, factorization, and the query, with the disk cache off unless a row says otherwise.

Writes OUT/runtime_error.csv (mesh/order grid and skip variants), OUT/skips.csv, OUT/locking.csv,
OUT/scaling.csv, OUT/runtime_error.md (markdown tables for docs/speed.md), OUT/pareto.png, OUT/scaling.png.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import os
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fem import contact  # noqa: E402
from fem import scene as S  # noqa: E402
from fem.contact import SurfaceModel  # noqa: E402
from fem.uniform import solve_uniform  # noqa: E402

RASTER = np.linspace(0.005, 0.065, 41)
DEPTH = 0.004


def _timed(fn, repeat):
    """(result of the last run, median wall time)."""
    ts, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return out, statistics.median(ts)


class _NoCache:
    def __enter__(self):
        self.old = os.environ.get("PALPATE_CACHE")
        os.environ["PALPATE_CACHE"] = "0"

    def __exit__(self, *a):
        if self.old is None:
            os.environ.pop("PALPATE_CACHE", None)
        else:
            os.environ["PALPATE_CACHE"] = self.old


def load_a(sc, **kw):
    return solve_uniform(sc, full_field=kw.pop("full_field", False), **kw)


def load_b(sc, stresses=False, **kw):
    sm = SurfaceModel(sc, **kw)
    if stresses:
        return sm, np.array([r.force_n_per_m for r in sm.indent_many(RASTER, DEPTH)])
    return sm, np.array([sm.force_n_per_m(x, DEPTH) for x in RASTER])


def err_a(r, ref) -> float:
    xr, vr = ref.surface.x_m, ref.surface.fields["von_mises_pa"]
    v = np.interp(xr, r.surface.x_m, r.surface.fields["von_mises_pa"])
    return float(np.max(np.abs(v - vr)) / vr.max())


def err_b(f, fref) -> float:
    return float(np.max(np.abs(f - fref)) / np.max(fref))


def references(base, quick):
    with _NoCache():
        ra = load_a(base.with_analysis(mesh_size_m=0.001 if quick else 0.0005))
        rb = load_b(base.with_analysis(mesh_size_m=0.001, surface_refine=4.0 if quick else 8.0))[1]
    return ra, rb


def grid(base, ref_a, ref_b, sizes, repeat):
    rows = []
    with _NoCache():
        for order in (1, 2):
            for h in sizes:
                sc = base.with_analysis(order=order, mesh_size_m=h)
                ra, ta = _timed(lambda: load_a(sc), repeat)
                (sm, f), tb = _timed(lambda: load_b(sc), repeat)
                d = sc.analysis == base.analysis
                rows.append({"variant": f"P{order} h={h * 1e3:g}mm", "order": order, "mesh_size_m": h,
                             "dofs": ra.model.n_dofs, "a_time_s": ta, "a_error": err_a(ra, ref_a),
                             "b_time_s": tb, "b_error": err_b(f, ref_b), "default": d, "kind": "mesh"})
                print(f"  P{order} h={h * 1e3:g} mm: {ra.model.n_dofs} DOFs  A {ta:.3f} s err {rows[-1]['a_error']:.2e}"
                      f"  B {tb:.3f} s err {rows[-1]['b_error']:.2e}", flush=True)
    return rows


def skips(base, ref_a, ref_b, repeat):
    """Each skip at the default settings: time with and without it, and the difference it makes."""
    out, pareto = [], []
    healthy_like = base.with_stones([dataclasses.replace(base.stones[0], youngs_pa=base.tissue.youngs_pa,
                                                         poisson=base.tissue.poisson)])
    with _NoCache(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # rigid stone
        ra, ta = _timed(lambda: load_a(base), repeat)
        re, te = _timed(lambda: load_a(base, rigid_stones=False), repeat)
        (smr, fr), tbr = _timed(lambda: load_b(base), repeat)
        (sme, fe), tbe = _timed(lambda: load_b(base, rigid_stones=False), repeat)
        out.append({"skip": "rigid stone (load A)", "time_with_s": ta, "time_without_s": te,
                    "dofs_with": ra.model.n_dofs, "dofs_without": re.model.n_dofs,
                    "measured_error": err_a(ra, re), "stated_bound": base.tissue.youngs_pa / base.stones[0].youngs_pa})
        out.append({"skip": "rigid stone (load B raster)", "time_with_s": tbr, "time_without_s": tbe,
                    "dofs_with": smr.model.n_dofs, "dofs_without": sme.model.n_dofs,
                    "measured_error": err_b(fr, fe), "stated_bound": base.tissue.youngs_pa / base.stones[0].youngs_pa})
        pareto += [{"variant": "elastic stone", "a_time_s": te, "a_error": err_a(re, ref_a), "b_time_s": tbe,
                    "b_error": err_b(fe, ref_b), "kind": "skip off"}]
        # rigid tip
        (smt, ft), tbt = _timed(lambda: load_b(base, rigid_tip=False), repeat)
        out.append({"skip": "rigid tip (load B raster)", "time_with_s": tbr, "time_without_s": tbt,
                    "dofs_with": smr.model.n_dofs, "dofs_without": smt.model.n_dofs,
                    "measured_error": err_b(fr, ft), "stated_bound": smr.tip_bound})
        pareto += [{"variant": "elastic tip", "a_time_s": np.nan, "a_error": np.nan, "b_time_s": tbt,
                    "b_error": err_b(ft, ref_b), "kind": "skip off"}]
        # no inclusion: the healthy scene vs a stone with the tissue's own modulus (the same physics)
        healthy = base.prior()
        rh, th = _timed(lambda: load_a(healthy), repeat)
        rs, ts = _timed(lambda: load_a(healthy_like), repeat)
        (smh, fh), tbh = _timed(lambda: load_b(healthy), repeat)
        (sms, fs), tbs = _timed(lambda: load_b(healthy_like), repeat)
        out.append({"skip": "no inclusion (load A, healthy)", "time_with_s": th, "time_without_s": ts,
                    "dofs_with": rh.model.n_dofs, "dofs_without": rs.model.n_dofs,
                    "measured_error": err_a(rh, rs), "stated_bound": 0.0})
        out.append({"skip": "no inclusion (load B, healthy)", "time_with_s": tbh, "time_without_s": tbs,
                    "dofs_with": smh.model.n_dofs, "dofs_without": sms.model.n_dofs,
                    "measured_error": err_b(fh, fs), "stated_bound": 0.0})
        # surface only
        rf, tf = _timed(lambda: load_a(base, full_field=True), repeat)
        out.append({"skip": "surface-only output (load A)", "time_with_s": ta, "time_without_s": tf,
                    "dofs_with": ra.model.n_dofs, "dofs_without": rf.model.n_dofs,
                    "measured_error": err_a(ra, rf), "stated_bound": 0.0})
        pareto += [{"variant": "full field", "a_time_s": tf, "a_error": err_a(rf, ref_a), "b_time_s": np.nan,
                    "b_error": np.nan, "kind": "skip off"}]
        (sms2, fst), tbst = _timed(lambda: load_b(base, stresses=True), repeat)
        out.append({"skip": "force-only queries (load B raster)", "time_with_s": tbr, "time_without_s": tbst,
                    "dofs_with": smr.model.n_dofs, "dofs_without": sms2.model.n_dofs,
                    "measured_error": err_b(fr, fst), "stated_bound": 0.0})
    # the cache: cold, from disk (a new process), from memory
    with tempfile.TemporaryDirectory() as tmp:
        old = {k: os.environ.get(k) for k in ("PALPATE_CACHE", "PALPATE_CACHE_DIR")}
        os.environ["PALPATE_CACHE_DIR"], os.environ["PALPATE_CACHE"] = tmp, "1"
        try:
            cold, disk, mem, disk_a = [], [], [], []
            for _ in range(repeat):
                for f in Path(tmp).iterdir():
                    f.unlink()
                contact._CACHE.clear()
                t0 = time.perf_counter()
                c = contact.surface_model(base)
                fc = np.array([c.force_n_per_m(x, DEPTH) for x in RASTER])
                cold.append(time.perf_counter() - t0)
                contact._CACHE.clear()
                t0 = time.perf_counter()
                d = contact.surface_model(base)
                fd = np.array([d.force_n_per_m(x, DEPTH) for x in RASTER])
                disk.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                m = contact.surface_model(base)
                np.array([m.force_n_per_m(x, DEPTH) for x in RASTER])
                mem.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                rda = load_a(base)          # load A: the mesh comes from the disk cache
                disk_a.append(time.perf_counter() - t0)
            assert np.array_equal(c.C, d.C) and np.array_equal(fc, fd)
            out.append({"skip": "disk cache (load B raster, new process)", "time_with_s": statistics.median(disk),
                        "time_without_s": statistics.median(cold), "dofs_with": d.model.n_dofs,
                        "dofs_without": c.model.n_dofs, "measured_error": float(np.max(np.abs(fc - fd))),
                        "stated_bound": 0.0})
            out.append({"skip": "memory cache (load B raster, same process)", "time_with_s": statistics.median(mem),
                        "time_without_s": statistics.median(cold), "dofs_with": m.model.n_dofs,
                        "dofs_without": c.model.n_dofs, "measured_error": 0.0, "stated_bound": 0.0})
            out.append({"skip": "disk cache (load A: mesh)", "time_with_s": statistics.median(disk_a),
                        "time_without_s": ta, "dofs_with": rda.model.n_dofs, "dofs_without": ra.model.n_dofs,
                        "measured_error": err_a(rda, ra), "stated_bound": 0.0})
            pareto += [{"variant": "disk cache", "a_time_s": statistics.median(disk_a), "a_error": err_a(rda, ref_a),
                        "b_time_s": statistics.median(disk), "b_error": err_b(fd, ref_b), "kind": "cache"}]
        finally:
            for k, v in old.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
            contact._CACHE.clear()
    for r in out:
        r["saving"] = r["time_without_s"] / r["time_with_s"]
        print(f"  {r['skip']}: {r['time_with_s']:.3f} s vs {r['time_without_s']:.3f} s "
              f"(x{r['saving']:.2f}), error {r['measured_error']:.1e} (bound {r['stated_bound']:.1e})", flush=True)
    return out, pareto


def locking(base, quick, nus=(0.4, 0.49, 0.499, 0.4999)):
    rows = []
    with _NoCache(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for nu in ((0.4, 0.4999) if quick else nus):
            sc = dataclasses.replace(base, tissue=dataclasses.replace(base.tissue, poisson=nu))
            ref = load_a(sc.with_analysis(formulation="mixed", mesh_size_m=0.001))
            for lab, kw in (("P1 displacement", dict(order=1)), ("P2 displacement", {}),
                            ("P2/P1 mixed", dict(formulation="mixed"))):
                t0 = time.perf_counter()
                r = load_a(sc.with_analysis(**kw))
                t = time.perf_counter() - t0
                rows.append({"poisson": nu, "formulation": lab, "time_s": t,
                             "peak_error": r.surface.peak()[1] / ref.surface.peak()[1] - 1,
                             "profile_error": err_a(r, ref),
                             "reaction_error": r.reaction_n_per_m / ref.reaction_n_per_m - 1})
                print(f"  nu {nu}: {lab}: peak {100 * rows[-1]['peak_error']:+.3f} %, profile "
                      f"{100 * rows[-1]['profile_error']:.3f} %, {t:.2f} s", flush=True)
    return rows


def scaling(base, quick, repeat):
    rows = []
    with _NoCache():
        sm = SurfaceModel(base)
        sm.indent_many(RASTER[:2], DEPTH)            # stress operators and factorization built once
        for n in ((1, 10, 100) if quick else (1, 10, 100, 1000)):
            xs = np.linspace(0.005, 0.065, n)
            _, tf = _timed(lambda: [sm.force_n_per_m(x, DEPTH) for x in xs], repeat)
            _, ts = _timed(lambda: sm.indent_many(xs, DEPTH), repeat)
            rows.append({"study": "waypoints", "n": n, "dofs": sm.model.n_dofs, "force_s": tf, "stress_s": ts,
                         "per_waypoint_force_ms": 1e3 * tf / n, "per_waypoint_stress_ms": 1e3 * ts / n})
            print(f"  {n} waypoints: forces {tf:.4f} s, with stresses {ts:.4f} s", flush=True)
        for h in ((0.008, 0.004, 0.002, 0.001) if quick else (0.008, 0.004, 0.002, 0.001, 0.0005)):
            sc = base.with_analysis(mesh_size_m=h)
            t0 = time.perf_counter()
            s = SurfaceModel(sc)
            setup = time.perf_counter() - t0
            _, tf = _timed(lambda: [s.force_n_per_m(x, DEPTH) for x in RASTER], repeat)
            t0 = time.perf_counter()
            load_a(sc)
            ta = time.perf_counter() - t0
            rows.append({"study": "dofs", "n": len(RASTER), "dofs": s.model.n_dofs, "h_m": h,
                         "mesh_assemble_s": s.timings_s["mesh_assemble_s"],
                         "factor_condense_s": s.timings_s["factor_condense_s"], "setup_s": setup,
                         "per_waypoint_force_ms": 1e3 * tf / len(RASTER), "load_a_s": ta, "n_top": len(s.top)})
            print(f"  h {h * 1e3:g} mm: {s.model.n_dofs} DOFs, setup {setup:.2f} s, load A {ta:.2f} s, "
                  f"{1e3 * tf / len(RASTER):.3f} ms/waypoint", flush=True)
    d = [r for r in rows if r["study"] == "dofs"]
    for key in ("setup_s", "load_a_s", "per_waypoint_force_ms"):
        x, y = np.log([r["dofs"] for r in d]), np.log([r[key] for r in d])
        slope = np.polyfit(x[1:], y[1:], 1)[0] if len(d) > 2 else np.nan
        for r in d:
            r[f"slope_{key}"] = slope
    return rows


def figures(out: Path, rows, pareto, scal):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    for ax, load, title in ((axes[0], "a", "load A: surface von Mises profile"),
                            (axes[1], "b", "load B: contact force, 41-waypoint raster")):
        for order, mk, col in ((1, "o", "tab:blue"), (2, "s", "tab:orange")):
            rr = [r for r in rows if r["order"] == order]
            t = [r[f"{load}_time_s"] for r in rr]
            e = [max(r[f"{load}_error"], 1e-16) for r in rr]
            ax.plot(t, e, mk + "-", color=col, label=f"P{order}, h = {rr[0]['mesh_size_m'] * 1e3:g} .. "
                                                    f"{rr[-1]['mesh_size_m'] * 1e3:g} mm")
            for r, ti, ei in zip(rr, t, e):
                ax.annotate(f"{r['mesh_size_m'] * 1e3:g}", (ti, ei), textcoords="offset points", xytext=(4, 4),
                            fontsize=7)
        style = {"elastic stone": ("^", "tab:red"), "elastic tip": ("v", "tab:purple"),
                 "full field": ("<", "tab:brown"), "disk cache": ("D", "tab:green")}
        for p in pareto:
            if np.isfinite(p[f"{load}_time_s"]):
                mk, col = style.get(p["variant"], ("x", "k"))
                ax.plot(p[f"{load}_time_s"], max(p[f"{load}_error"], 1e-16), mk, color=col, ms=8,
                        label=p["variant"] + (" (skip off)" if p["kind"] == "skip off" else " (warm, default)"))
        d = next(r for r in rows if r["default"])
        ax.plot(d[f"{load}_time_s"], d[f"{load}_error"], "*", ms=18, mfc="none", mec="k", mew=1.5,
                label="default (P2, h = 2 mm, all skips on)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("wall time, cold (s)")
        ax.set_ylabel("error vs converged reference (relative)")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.legend(fontsize=7)
    fig.suptitle("paper scene: run time against error (labels: mesh size at depth, mm)")
    fig.tight_layout()
    fig.savefig(out / "pareto.png", dpi=130)
    plt.close(fig)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    w = [r for r in scal if r["study"] == "waypoints"]
    axes[0].loglog([r["n"] for r in w], [r["force_s"] for r in w], "o-", label="forces (LCP per waypoint)")
    axes[0].loglog([r["n"] for r in w], [r["stress_s"] for r in w], "s-", label="forces + stresses (batched)")
    axes[0].set_xlabel("waypoints")
    axes[0].set_ylabel("wall time (s), surface model built")
    axes[0].set_title("cost against waypoints (paper, default mesh)")
    d = [r for r in scal if r["study"] == "dofs"]
    for key, lab in (("setup_s", "contact setup (mesh, assemble, Schur)"), ("load_a_s", "load A solve"),
                     ("mesh_assemble_s", "mesh + assemble")):
        axes[1].loglog([r["dofs"] for r in d], [r[key] for r in d], "o-",
                       label=lab + (f", slope {d[0]['slope_' + key]:.2f}" if "slope_" + key in d[0] else ""))
    ax2 = axes[1].twinx()
    ax2.loglog([r["dofs"] for r in d], [r["per_waypoint_force_ms"] for r in d], "k^--", label="ms per waypoint")
    ax2.set_ylabel("force query (ms per waypoint)")
    axes[1].set_xlabel("DOFs (P2)")
    axes[1].set_ylabel("wall time (s)")
    axes[1].set_title("cost against DOFs")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax2.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    axes[0].legend(fontsize=8)
    h1, l1 = axes[1].get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    axes[1].legend(h1 + h2, l1 + l2, fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(out / "scaling.png", dpi=130)
    plt.close(fig)


def markdown(rows, skip_rows, lock_rows, scal, quick) -> str:
    L = ["### Run time against error (paper scene)", "",
         f"Reference: P2, h = {'1' if quick else '0.5'} mm (load A) and P2, h = 1 mm, surface refinement "
         f"{'4' if quick else '8'} (load B). Times: cold (mesh + assemble + factor + query, cache off), median "
         "of repeats, 2 shared cores.", "",
         "| elements | h (mm) | DOFs | load A time (s) | load A error | load B time (s) | load B error |",
         "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        tag = " **(default)**" if r["default"] else ""
        L.append(f"| P{r['order']}{tag} | {r['mesh_size_m'] * 1e3:g} | {r['dofs']:,} | {r['a_time_s']:.3f} | "
                 f"{r['a_error']:.1e} | {r['b_time_s']:.3f} | {r['b_error']:.1e} |")
    L += ["", "### What each skip saves (default settings) and the error it introduces", "",
          "| skip | time with (s) | time without (s) | saving | DOFs with / without | measured error | stated bound |",
          "|---|---:|---:|---:|---:|---:|---:|"]
    for r in skip_rows:
        L.append(f"| {r['skip']} | {r['time_with_s']:.3f} | {r['time_without_s']:.3f} | x{r['saving']:.1f} | "
                 f"{r['dofs_with']:,} / {r['dofs_without']:,} | {r['measured_error']:.1e} | "
                 f"{r['stated_bound']:.1e} |")
    L += ["", "### Near-incompressible tissue (load A, default mesh vs mixed P2/P1 at h = 1 mm)", "",
          "| Poisson | formulation | peak error | profile error | reaction error | time (s) |",
          "|---:|---|---:|---:|---:|---:|"]
    for r in lock_rows:
        L.append(f"| {r['poisson']} | {r['formulation']} | {100 * r['peak_error']:+.3f} % | "
                 f"{100 * r['profile_error']:.3f} % | {100 * r['reaction_error']:+.3f} % | {r['time_s']:.2f} |")
    L += ["", "### Scaling", "", "| waypoints | forces (s) | ms / waypoint | forces + stresses (s) |",
          "|---:|---:|---:|---:|"]
    for r in scal:
        if r["study"] == "waypoints":
            L.append(f"| {r['n']} | {r['force_s']:.4f} | {r['per_waypoint_force_ms']:.3f} | {r['stress_s']:.4f} |")
    L += ["", "| h (mm) | DOFs | top nodes | mesh + assemble (s) | factor + condense (s) | load A (s) | ms / waypoint |",
          "|---:|---:|---:|---:|---:|---:|---:|"]
    d = [r for r in scal if r["study"] == "dofs"]
    for r in d:
        L.append(f"| {r['h_m'] * 1e3:g} | {r['dofs']:,} | {r['n_top']} | {r['mesh_assemble_s']:.3f} | "
                 f"{r['factor_condense_s']:.3f} | {r['load_a_s']:.3f} | {r['per_waypoint_force_ms']:.3f} |")
    if d:
        L.append(f"\nFitted exponents (time ~ DOFs^k, above the coarsest mesh): contact setup "
                 f"{d[0]['slope_setup_s']:.2f}, load A {d[0]['slope_load_a_s']:.2f}, per-waypoint force "
                 f"{d[0]['slope_per_waypoint_force_ms']:.2f}.")
    return "\n".join(L) + "\n"


def _csv(path, rows):
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)


def run(out_dir, quick: bool = False, repeat: int | None = None) -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    repeat = repeat or (1 if quick else 3)
    base = S.load("paper")
    sizes = (0.008, 0.004, 0.002) if quick else (0.008, 0.004, 0.002, 0.001)
    print("references ...", flush=True)
    ref_a, ref_b = references(base, quick)
    print("mesh size x order grid:", flush=True)
    rows = grid(base, ref_a, ref_b, sizes, repeat)
    print("skips:", flush=True)
    skip_rows, pareto = skips(base, ref_a, ref_b, repeat)
    print("locking:", flush=True)
    lock_rows = locking(base, quick)
    print("scaling:", flush=True)
    scal = scaling(base, quick, repeat)
    _csv(out / "runtime_error.csv", rows + pareto)
    _csv(out / "skips.csv", skip_rows)
    _csv(out / "locking.csv", lock_rows)
    _csv(out / "scaling.csv", scal)
    figures(out, rows, pareto, scal)
    md = markdown(rows, skip_rows, lock_rows, scal, quick)
    (out / "runtime_error.md").write_text(md)
    print(md)
    print(f"wrote {out}/runtime_error.csv, skips.csv, locking.csv, scaling.csv, runtime_error.md, pareto.png, "
          f"scaling.png")
    return {"grid": rows, "skips": skip_rows, "locking": lock_rows, "scaling": scal}


def _read_csv(path):
    def conv(v):
        if v in ("True", "False"):
            return v == "True"
        try:
            return int(v)
        except ValueError:
            try:
                return float(v) if v != "" else float("nan")
            except ValueError:
                return v
    with open(path) as f:
        return [{k: conv(v) for k, v in r.items()} for r in csv.DictReader(f)]


def replot(out_dir) -> None:
    """Redraw the figures from the CSVs of an earlier run."""
    out = Path(out_dir)
    both = _read_csv(out / "runtime_error.csv")
    rows = [r for r in both if r.get("kind") == "mesh"]
    figures(out, rows, [r for r in both if r.get("kind") != "mesh"], _read_csv(out / "scaling.csv"))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="bench-out")
    p.add_argument("--replot", action="store_true", help="only redraw the figures from OUT's CSVs")
    p.add_argument("--quick", action="store_true", help="coarser reference, fewer sizes, one repeat (~1 min)")
    p.add_argument("--repeat", type=int, help="timing repeats (median); default 3, --quick 1")
    a = p.parse_args(argv)
    if a.replot:
        replot(a.out)
        return 0
    run(a.out, a.quick, a.repeat)
    return 0


if __name__ == "__main__":
    sys.exit(main())
