"""`palpate simulate` and `palpate predict` for 3D scenes (a tissue with length_m: fem.uniform3d, fem.contact3d).

simulate --load uniform: the top face moved down; the von Mises map over the top face and its peak (x_m, y_m).
simulate --load indent: the spherical (or flat) tip pressed --depth-m in at (--x-m, --y-m): force, contact radius,
maximum von Mises under the tip. predict --grid NXxNY: force and maximum stress over a grid of waypoints spanning the
probed patch (less the tip radius), against the reference scene (default: the prior), and their ratio (contrast).
JSON keys as in 2D plus y_m. Figures: maps over the top face, a section through the stone; VTU export.
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from app.commands.output import warn_strain, write_json
from app.errors import UsageError
from app.figure_names import FIG_INDENT_3D, FIG_PREDICT_3D, FIG_UNIFORM_3D
from core.peak import or_null, ratio_of
from fem.contact3d import (
    STRESS_RESOLVED,
    check_waypoint3d,
    factor3d_cached,
    patch_element_m,
    surface3d_cached,
    surface_model3d,
)
from fem.mesh3d import estimate_nodes3d, patch_bounds
from fem.results3d import SurfaceMap, quadratic_peak
from fem.stress3d import components3d, recover3d
from fem.uniform3d import nodal_fields3d, solve_uniform3d

BATCH = 100            # waypoints per batched sweep (memory: a few n_dofs x BATCH doubles; one read of the factor each)


def _mesh_dict(mesh, model) -> dict:
    return {"nodes": int(mesh.n_nodes), "elements": int(len(mesh.tets)), "order": int(mesh.order),
            "dofs": int(model.n_dofs), "dofs_full": int(mesh.n_dofs)}




def _section_y(sc, default_y: float) -> float:
    return sc.stones[0].y_m if sc.stones else default_y


def run_simulate(args, sc, rigid) -> int:
    if args.compare is not None:
        raise UsageError("--compare is for 2D scenes; for a 3D scene use `palpate predict SCENE --grid NXxNY`")
    warn_order(sc, "simulate")
    if args.load == "indent":
        return _indent(args, sc, rigid)
    t0 = time.perf_counter()
    res = solve_uniform3d(sc, full_field=bool(args.plots or args.vtu), rigid_stones=rigid)
    mesh = res.model.mesh
    xp, yp, vp = res.surface.peak()
    out = {"scene": sc.name, "load": "uniform", "analysis": dataclasses.asdict(sc.analysis),
           "rigid_stones": [bool(r) for r in res.model.rigid], **res.surface.to_dict(),
           "reaction_n": res.reaction_n, "force_n": res.reaction_n, "mesh": _mesh_dict(mesh, res.model),
           "timings_s": dict(res.timings_s), "files": {}}
    if args.vtu:
        from fem.export3d import write_vtu3d
        out["files"]["vtu"] = str(write_vtu3d(args.vtu, mesh, res.u, point_data=res.nodal))
    if args.plots:
        from fem import plots3d
        a = sc.analysis
        tag = (f"{sc.name}: top moved down {a.top_displacement_m * 1e3:g} mm, P{a.order} tetrahedra, "
               f"h = {a.mesh_size_m * 1e3:g} mm")
        d = Path(args.plots)
        out["files"]["surface"] = str(plots3d.surface_maps(
            d / FIG_UNIFORM_3D[0], sc, res.surface.x_m, res.surface.y_m,
            {"von_mises_pa": res.surface.fields["von_mises_pa"], "szz_pa": res.surface.fields["szz_pa"]},
            f"Top-face stress - {tag}", peak=(xp, yp)))
        ys = _section_y(sc, sc.tissue.length_m / 2)
        out["files"]["section"] = str(plots3d.section(d / FIG_UNIFORM_3D[1], sc, mesh, res.nodal["von_mises_pa"], ys,
                                                      "von Mises (Pa)", f"Section y = {ys * 1e3:g} mm - {tag}"))
    out["timings_s"]["total_s"] = time.perf_counter() - t0
    write_json(args.json, out)        # (first: a reader that closes the pipe early does not lose the file)
    stream = sys.stderr if args.json == "-" else sys.stdout
    print(f"scene {sc.name} (3D): load uniform (top down {sc.analysis.top_displacement_m * 1e3:g} mm), "
          f"P{sc.analysis.order}; {out['mesh']['nodes']} nodes, {out['mesh']['elements']} tetrahedra, "
          f"{out['mesh']['dofs']} DOFs\n  peak von Mises on the top face: {vp:.2f} Pa at x = {xp * 1e3:.2f} mm, "
          f"y = {yp * 1e3:.2f} mm\n  reaction: {res.reaction_n:.5g} N\n  time: {out['timings_s']['total_s']:.2f} s"
          + "".join(f"\n  wrote {k}: {f}" for k, f in out["files"].items()), file=stream)
    return 0


def _indent(args, sc, rigid) -> int:
    if args.x_m is None or args.y_m is None or args.depth_m is None:
        print("palpate simulate: --load indent on a 3D scene needs --x-m X, --y-m Y and --depth-m D (tip position "
              "on the top face and indentation depth, m)", file=sys.stderr)
        return 2
    try:
        check_waypoint3d(sc, args.x_m, args.y_m, args.depth_m)
    except ValueError as e:
        print(f"palpate simulate: --x-m {args.x_m:g} / --y-m {args.y_m:g} / --depth-m {args.depth_m:g}: {e}",
              file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    if not args.quiet:
        announce(sc, "simulate", stresses=True, rigid_stones=rigid)
    m = surface_model3d(sc, stresses=True, rigid_stones=rigid)
    t1 = time.perf_counter()
    r, u = m.indent_with_field(args.x_m, args.y_m, args.depth_m)
    t2 = time.perf_counter()
    model, mesh = m.model, m.mesh
    top = mesh.top
    surf = SurfaceMap(mesh.nodes[top, 0], mesh.nodes[top, 1],
                      components3d(recover3d(model, u, top)))
    out = {"scene": sc.name, "load": "indent", **r.to_dict(), "indenter": dataclasses.asdict(sc.indenter),
           "analysis": dataclasses.asdict(sc.analysis), "rigid_stones": [bool(x) for x in model.rigid],
           **surf.to_dict(), "mesh": {**_mesh_dict(mesh, model), "contact_candidates": int(len(m.patch))},
           "timings_s": {**m.timings_s, "model_s": t1 - t0, "indent_s": t2 - t1}, "files": {}}
    nodal = nodal_fields3d(model, u) if (args.plots or args.vtu) else None
    if args.vtu:
        from fem.export3d import write_vtu3d
        out["files"]["vtu"] = str(write_vtu3d(args.vtu, mesh, u, point_data=nodal))
    if args.plots:
        from fem import plots3d
        d = Path(args.plots)
        R = sc.indenter.radius_m
        tag = (f"{sc.name}: {sc.indenter.shape} tip R = {R * 1e3:g} mm at ({r.x_m * 1e3:g}, {r.y_m * 1e3:g}) mm, "
               f"depth {r.depth_m * 1e3:g} mm, F = {r.force_n:.4g} N")
        out["files"]["surface"] = str(plots3d.surface_maps(
            d / FIG_INDENT_3D[0], sc, surf.x_m, surf.y_m,
            {"von_mises_pa": surf.fields["von_mises_pa"], "uz_m": u[2::3][top]}, tag))
        out["files"]["section"] = str(plots3d.section(d / FIG_INDENT_3D[1], sc, mesh, nodal["von_mises_pa"], r.y_m,
                                                      "von Mises (Pa)", f"Section y = {r.y_m * 1e3:g} mm - {tag}"))
    out["timings_s"]["total_s"] = time.perf_counter() - t0
    write_json(args.json, out)
    stream = sys.stderr if args.json == "-" else sys.stdout
    print(f"scene {sc.name} (3D): load indent ({sc.indenter.shape} tip, R = {sc.indenter.radius_m * 1e3:g} mm) at "
          f"x = {r.x_m * 1e3:g} mm, y = {r.y_m * 1e3:g} mm, depth {r.depth_m * 1e3:g} mm; P{sc.analysis.order}, "
          f"{out['mesh']['dofs']} DOFs, {len(m.patch)} patch nodes\n  force: {r.force_n:.5g} N\n"
          f"  contact radius {r.contact_radius_m * 1e3:.3f} mm, {int((r.nodal_force_n > 0).sum())} nodes in contact\n"
          f"  max von Mises {r.max_von_mises_pa:.4g} Pa at ({r.max_von_mises_at_m[0] * 1e3:.2f}, "
          f"{r.max_von_mises_at_m[1] * 1e3:.2f}) mm, {r.max_von_mises_at_m[2] * 1e3:.2f} mm deep\n  tip: {r.tip_note}\n"
          "  time: " + ", ".join(f"{k[:-2]} {v:.3f} s" for k, v in out["timings_s"].items() if isinstance(v, float))
          + "".join(f"\n  wrote {k}: {f}" for k, f in out["files"].items()), file=stream)
    warn_unresolved(sc, "simulate", [r])
    warn_strain("simulate", sc, args.depth_m)
    return 0


def warn_order(sc, command: str) -> None:
    """One line on stderr, before the work, for a block meshed with linear tetrahedra (analysis.order = 1): they are
    stiff in 3D where P1 triangles are not in 2D (session 56's physics review: a sphere of R 10 mm 0.4 mm into a
    160 x 160 x 80 mm block, the contact spanning 6.4 elements: +10.6 % against Hertz where P2 gives +1.7 %, and +16
    to +21 % below 3 elements; the contact-resolution warning's numbers are P2's; 2D P1 within 0.7 % of P2)."""
    if sc.analysis.order == 1:
        print(f"palpate {command}: {sc.name}: warning: analysis.order = 1 (linear tetrahedra) is stiff in 3D: a "
              f"review measured the force +10.6 % above Hertz with the contact spanning 6.4 elements (P2: +1.7 %), "
              f"+16 to +21 % below 3, and the stress further off; use order = 2 (the default)", file=sys.stderr)


def warn_unresolved(sc, command: str, rows) -> None:
    """One line on stderr when any of ``rows`` in contact had a contact radius spanning fewer than STRESS_RESOLVED
    of the patch's elements: the stress peak is not resolved there, and the force is not within 1 % either (session
    45's review: a spanning 2.25 elements, +1.1 to +1.7 % against its mesh family's limit; block3d's 3.2, 0.72 %;
    session 47's, a 30 x 40 x 20 mm block, grade 0.5, against converged focused meshes: +4.0 to +7.7 % at 0.9-1.5
    elements, +2.7 % at 2.2, +1.7 % at 3.1)."""
    k = [r.contact_radius_over_element for r in rows if r.force_n > 0]
    if k and min(k) < STRESS_RESOLVED:
        h = patch_element_m(sc)
        stress = ("the maximum von Mises is not resolved there (up to about 20 % off, false peaks near the contact's "
                  "edge below 2) and " if any(r.max_von_mises_pa > 0 for r in rows) else "")
        force = ("the force is not resolved either: within one element a few nodes carry the whole contact (a "
                 "review's 1 um indentations: 2.4 and 0.5 times Hertz on two meshes)" if min(k) < 1.0 else
                 "the force may be stiff")
        print(f"palpate {command}: {sc.name}: warning: the contact radius spans {min(k):.2g} of the patch's elements "
              f"({h * 1e3:.3g} mm) at its smallest, under {STRESS_RESOLVED:g}: {stress}{force} "
              f"(measured: +1.1 to +1.7 % at 2.25 elements on block3d's mesh; on a review's block with grade 0.5, "
              f"+2.7 % at 2.2 and +4 to +8 % at 0.9-1.5, +1.7 % still at 3.1); raise "
              f"analysis.surface_refine (now {sc.analysis.surface_refine:g}) or indent deeper (the force converges "
              f"faster than the stress peak, but a 3D force ratio within about 1 % of 1 is mesh noise: a scene and its "
              f"prior are meshed apart)", file=sys.stderr)


# ------------------------------------------------------------------------------------------------- predict

def parse_grid(text: str) -> tuple[int, int]:
    """'NXxNY' -> (nx, ny), each 1..200; UsageError naming --grid otherwise."""
    parts = str(text).lower().split("x")
    try:
        nx, ny = (int(p) for p in parts)
    except ValueError:
        raise UsageError(f"--grid {text!r}: give NXxNY, e.g. 10x10") from None
    if not (1 <= nx <= 200 and 1 <= ny <= 200):
        raise UsageError(f"--grid {text!r}: NX and NY must lie in 1..200")
    return nx, ny


def grid(sc, nx: int, ny: int) -> tuple[np.ndarray, np.ndarray]:
    """Waypoint coordinates spanning the probed patch less the tip radius (the centre for a count of 1)."""
    x0, x1, y0, y1 = patch_bounds(sc.tissue.width_m, sc.tissue.length_m, sc.analysis.patch_m)
    R = sc.indenter.radius_m

    def axis(lo, hi, n):
        return np.array([0.5 * (lo + hi)]) if n == 1 else np.linspace(lo + R, hi - R, n)
    return axis(x0, x1, nx), axis(y0, y1, ny)


# docs/fem.md, "In 3D"; measured 2026-11-26 (the estimate before meshing, fem.mesh3d.estimate_nodes3d, said 156,587 there)
REFERENCE_BUILD = "for comparison block3d's prior, 137,445 DOFs once meshed, takes about 35 s on 2 cores"


def announce(sc, command: str, stresses: bool, **options) -> None:
    """One progress line on stderr before a 3D model's long work: its build when it is not cached, and the
    factorization stresses need once when the factor they use is not cached (fem.contact3d.factor3d_cached)."""
    dofs = estimate_nodes3d(sc)["dofs"]
    if not surface3d_cached(sc, **options):
        print(f"palpate {command}: {sc.name}: building its 3D model (about {dofs:,.0f} DOFs estimated before "
              f"meshing, which ran 14 % high on block3d's prior: mesh, assembly, sparse factorization; "
              f"{REFERENCE_BUILD}), kept in the disk cache for the next run", file=sys.stderr, flush=True)
    elif stresses and not factor3d_cached(sc, **options):
        print(f"palpate {command}: {sc.name}: the stresses under the tip need the model's factorization once "
              f"(about {dofs:,.0f} DOFs estimated before meshing; {REFERENCE_BUILD}; kept in the disk cache for the "
              f"next run; predict --force-only does without)", file=sys.stderr, flush=True)


def _predict(sc, xs, ys, depth_m, stresses: bool, quiet: bool = False) -> dict:
    t0 = time.perf_counter()
    if not quiet:
        announce(sc, "predict", stresses)
    m = surface_model3d(sc, stresses=stresses)
    t1 = time.perf_counter()
    pts = [(float(x), float(y), depth_m) for y in ys for x in xs]
    rows = []
    for k in range(0, len(pts), BATCH):          # one batched solve per BATCH waypoints (their stress fields)
        rows += m.indent_many(pts[k:k + BATCH], stresses=stresses)
    t2 = time.perf_counter()
    n = len(rows)
    warn_unresolved(sc, "predict", rows)
    return {"x_m": [r.x_m for r in rows], "y_m": [r.y_m for r in rows], "force_n": [r.force_n for r in rows],
            "max_von_mises_pa": [r.max_von_mises_pa for r in rows] if stresses else None,
            "max_von_mises_at_x_m": [r.max_von_mises_at_m[0] for r in rows] if stresses else None,
            "max_von_mises_at_y_m": [r.max_von_mises_at_m[1] for r in rows] if stresses else None,
            "max_von_mises_at_depth_m": [r.max_von_mises_at_m[2] for r in rows] if stresses else None,
            "contact_radius_m": [r.contact_radius_m for r in rows],
            "contact_radius_over_element": [r.contact_radius_over_element for r in rows], "tip_note": m.tip_note,
            "mesh": {"nodes": int(m.mesh.n_nodes), "elements": int(len(m.mesh.tets)),
                     "contact_candidates": int(len(m.patch))},
            "timings_s": {"setup_s": t1 - t0, "predict_s": t2 - t1, "per_waypoint_s": (t2 - t1) / n}}


def _peak(w: dict, ratio: np.ndarray) -> dict | None:
    """The ratio's peak over the grid (a quadratic through the samples around the largest); undefined ratios (NaN:
    the reference felt no force) skipped, and None when there is none."""
    x, y = np.asarray(w["x_m"]), np.asarray(w["y_m"])
    if not np.isfinite(ratio).any():
        return None
    i = int(np.nanargmax(ratio))
    if len(ratio) >= 13 and np.isfinite(ratio).all():
        xp, yp, rp = quadratic_peak(x, y, ratio)
    else:
        xp, yp, rp = float(x[i]), float(y[i]), float(ratio[i])
    return {"x_m": xp, "y_m": yp, "ratio": rp, "index": i, "x_max_sample_m": float(x[i]),
            "y_max_sample_m": float(y[i])}


def run_predict(args, sc, ref) -> int:
    t0 = time.perf_counter()
    warn_order(sc, "predict")
    nx, ny = parse_grid(args.grid or "10x10")
    xs, ys = grid(sc, nx, ny)
    try:
        if not args.depth_m > 0:
            raise ValueError(f"--depth-m must be positive, got {args.depth_m}")
        for x in (xs[0], xs[-1]):
            for y in (ys[0], ys[-1]):
                check_waypoint3d(sc, float(x), float(y), args.depth_m)
    except ValueError as e:
        name = getattr(args, "depth_name", None) or f"--depth-m {args.depth_m:g}"
        named = f"{name} on scene {sc.name}: " if str(e).startswith("depth_m") else ""
        print(f"palpate predict: {named}{e}", file=sys.stderr)
        return 2
    if getattr(args, "depth_note", None):       # (the default depth on a small tip: app.commands.predict)
        print(args.depth_note, file=sys.stderr)
    stresses = not args.force_only
    main = _predict(sc, xs, ys, args.depth_m, stresses, args.quiet)
    out = {"scene": sc.name, "load": "indent", "depth_m": args.depth_m, "grid": [nx, ny],
           "indenter": dataclasses.asdict(sc.indenter), "analysis": dataclasses.asdict(sc.analysis),
           "stones": [dataclasses.asdict(s) for s in sc.stones], "waypoints": main, "files": {}}
    maps = {"force_n": np.reshape(main["force_n"], (ny, nx))}
    if stresses:
        maps["max_von_mises_pa"] = np.reshape(main["max_von_mises_pa"], (ny, nx))
    if ref is not None:
        try:
            rd = _predict(ref, xs, ys, args.depth_m, stresses, args.quiet)
        except ValueError as e:          # fem refuses the press on the reference (a shallow stone there)
            name = getattr(args, "depth_name", None) or f"--depth-m {args.depth_m:g}"
            raise UsageError(f"{name} on the reference (--compare {args.compare}): {e}") from None
        out["reference_scene"], out["reference"] = ref.name, rd
        ratio = ratio_of(main["force_n"], rd["force_n"])
        out["ratio"] = or_null(ratio)
        out["peak_ratio"] = _peak(main, ratio)
        maps["force ratio (contrast)"] = ratio.reshape(ny, nx)
        if stresses:
            rs = ratio_of(main["max_von_mises_pa"], rd["max_von_mises_pa"])
            out["ratio_von_mises"] = or_null(rs)
            out["peak_ratio_von_mises"] = _peak(main, rs)
    if args.plots:
        from fem import plots3d
        title = (f"{sc.name}: {sc.indenter.shape} tip R = {sc.indenter.radius_m * 1e3:g} mm pressed "
                 f"{args.depth_m * 1e3:g} mm on a {nx} x {ny} grid" + (f", against {ref.name}" if ref else ""))
        out["files"]["predict"] = str(plots3d.grid_maps(Path(args.plots) / FIG_PREDICT_3D, sc, xs, ys, maps, title))
    t = dict(main["timings_s"])
    if ref is not None:
        t.update({"reference_setup_s": out["reference"]["timings_s"]["setup_s"],
                  "reference_predict_s": out["reference"]["timings_s"]["predict_s"]})
    t["total_s"] = time.perf_counter() - t0
    out["timings_s"] = t
    f = np.asarray(main["force_n"])
    lines = [f"scene {sc.name} (3D): {nx} x {ny} waypoints over x {xs[0] * 1e3:g}..{xs[-1] * 1e3:g} mm, y "
             f"{ys[0] * 1e3:g}..{ys[-1] * 1e3:g} mm, depth {args.depth_m * 1e3:g} mm ({sc.indenter.shape} tip R = "
             f"{sc.indenter.radius_m * 1e3:g} mm)",
             f"  force: {f.min():.4g} .. {f.max():.4g} N"]
    if "peak_ratio" in out:
        p = out["peak_ratio"]
        undefined = max(sum(v is None for v in out[k]) for k in ("ratio", "ratio_von_mises") if k in out)
        if p is None:
            lines.append(f"  vs {out['reference_scene']}: no force ratio: the reference feels no force at any "
                         f"waypoint (the tip touches no surface node: a depth below the mesh's resolution)")
        else:
            lines.append(f"  vs {out['reference_scene']}: force ratio peaks at {p['ratio']:.4f} at x = "
                         f"{p['x_m'] * 1e3:.1f} mm, y = {p['y_m'] * 1e3:.1f} mm")
        if undefined and p is not None:
            lines.append(f"  warning: no ratio (null) at {undefined} of {len(out['ratio'])} waypoints: the reference "
                         f"feels no force there (the tip touches no surface node: a depth below the mesh's "
                         f"resolution)")
    if sc.stones:
        lines.append("  stones at " + ", ".join(f"({s.x_m * 1e3:g}, {s.y_m * 1e3:g}) mm" for s in sc.stones))
    lines.append(f"  time: setup {t['setup_s']:.2f} s, {nx * ny} waypoints {t['predict_s']:.3f} s "
                 f"({t['per_waypoint_s'] * 1e3:.2f} ms each); total {t['total_s']:.2f} s")
    lines += [f"  wrote {k}: {v}" for k, v in out["files"].items()]
    write_json(args.json, out)
    print("\n".join(lines), file=sys.stderr if args.json == "-" else sys.stdout)
    warn_strain("predict", sc, args.depth_m)
    return 0
