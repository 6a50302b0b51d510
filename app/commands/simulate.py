"""`palpate simulate SCENE --load uniform|indent`: one FEM analysis of a scene, with JSON, figures and VTU.

Load ``uniform`` is the study's load A (the whole top edge moved down by ``analysis.top_displacement_m``).
Load ``indent`` (load B: a probe tip pressed ``--depth-m`` into the top surface at ``--x-m``) uses fem.contact's
condensed surface model: force, contact pressure, maximum von Mises under the tip, Fig 10-like contours.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from app.commands.output import warn_strain, write_json
from app.errors import UsageError
from app.figure_names import FIG_INDENT_2D, FIG_INDENT_3D, FIG_UNIFORM_3D
from app.options import (
    analysis_changes,
    check_depth_floor,
    check_output_dir,
    check_output_file,
    finite_float,
    load_scene,
    positive_float,
    refuse_figures,
)
from app.resolution import warn_pressure_near_incompressible2d, warn_unresolved2d
from fem.contact import surface_model
from fem.rigid_stress import nodal_fields
from fem.scene import SceneError, check_load_a
from fem.stress import components, nodal_poisson, recovery_operator
from fem.uniform import Profile, solve_uniform

PAPER_FAMILY = ("paper", "paper-left", "paper-right", "paper-deep")
COMPARE_DEFAULT = PAPER_FAMILY + ("healthy",)

FIGURES = {
    "stress": "fig3_stress.png",          # sxx, syy, sxy, von Mises contours (study Fig 3)
    "strain": "fig4_strain.png",          # exx, eyy, gxy, u_y contours (study Fig 4)
    "surface": "fig5_surface.png",        # stresses along the top surface (study Fig 5)
    "compare": "fig6_7_9_compare.png",    # von Mises along the top for several scenes (study Figs 6, 7, 9)
}
SIMULATE_FIGURES = (*FIGURES.values(), FIG_INDENT_2D, *FIG_UNIFORM_3D, *FIG_INDENT_3D)

HELP = """Solve one scene under a load and report the top-surface stress.

figures (--plots DIR):
  fig3_stress.png       contours of sigma_xx, sigma_yy, sigma_xy and von Mises over the section (study Fig 3)
  fig4_strain.png       contours of eps_xx, eps_yy, gamma_xy and u_y (study Fig 4)
  fig5_surface.png      the stresses along the top surface, peak marked (study Fig 5)
  fig6_7_9_compare.png  von Mises along the top for the centred, left, right and small deep stone and healthy
                        tissue on one axes (study Figs 6, 7, 9). Made automatically for the built-in scenes
                        paper, paper-left, paper-right, paper-deep; for other scenes ask with --compare.
The compared scenes are solved with the same analysis options (order, mesh size, plane) as SCENE.
  fig10_indent.png      --load indent: von Mises over the deformed section, and von Mises, sigma_xx, sigma_yy
                        under the tip, tip and stone outlines drawn (study Fig 10)

--load indent (load B): a probe tip pressed --depth-m into the top surface at --x-m (frictionless contact,
bottom u_y = 0, one bottom corner u_x = 0). Reports the tip force (N, and N/m of section), the contact half-width
and pressure, and the maximum von Mises stress within 2 R below the surface and where it lies. The JSON has
x_m, depth_m, force_n_per_m, force_n, max_von_mises_pa, contact {x_m, pressure_pa, gap_m, nodal_force_n_per_m}
and the top-surface stress profile (surface, peak)."""

EXAMPLES = """examples:
  palpate simulate paper --load uniform --plots out/ --json out/paper.json --vtu out/paper.vtu
  palpate simulate my_kidney.toml --order 1 --mesh-size-m 0.001 --compare paper paper-deep --plots out/
  palpate simulate paper --load indent --x-m 0.035 --depth-m 0.004 --plots out/ --json out/indent.json
  palpate simulate healthy --load indent --x-m 0.02 --depth-m 0.003 --indenter-radius-m 0.0025
  palpate simulate block3d --load indent --x-m 0.035 --y-m 0.035 --depth-m 0.003 --plots out/ --vtu out/b.vtu
  palpate simulate block3d --load uniform --plots out/ --json out/block3d.json

3D scenes (tissue.length_m given: block3d, ...): --load uniform reports the von Mises map over the top face and its
peak (x_m, y_m); --load indent needs --x-m, --y-m and --depth-m and reports the maximum von Mises over the stress
points of the tissue's elements (4 per element, where a quadratic element's stress is most accurate: +1 to +12 %
above Hertz for a sphere once the contact radius spans 3 or more of the patch's elements, with a warning below
that; the figures' and the VTU's nodal fields average each element's values at the nodes and peak higher); figures fig3d_*.png (top-face maps and a section through the stone or the tip),
VTU with tetrahedra."""


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("simulate", help="one FEM analysis of a scene (load A: uniform top displacement; load B: --load indent)",
                       description=HELP, epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", metavar="SCENE", help="built-in name (paper, paper-left, paper-right, paper-deep, "
                                                  "healthy; 3D: block3d, block3d-healthy, block3d-left, "
                                                  "block3d-front, block3d-deep) or a TOML file")
    p.add_argument("--load", choices=("uniform", "indent"), default="uniform",
                   help="uniform: the whole top edge moved down by analysis.top_displacement_m (default); "
                        "indent: a probe tip pressed in at --x-m")
    p.add_argument("--json", metavar="PATH", help="write the machine-readable result here ('-': stdout)")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr (3D: before a model's build)")
    p.add_argument("--plots", metavar="DIR", help="write the figures (listed above) into DIR")
    p.add_argument("--vtu", metavar="PATH", help="write displacement, stress and strain fields as VTU (ParaView)")
    p.add_argument("--compare", nargs="*", metavar="SCENE",
                   help="scenes whose von Mises profiles go on the comparison figure with SCENE's (no names: "
                        f"{' '.join(COMPARE_DEFAULT)}); needs --plots; put it after SCENE")
    g = p.add_argument_group("analysis overrides (default: the scene's [analysis] table)")
    g.add_argument("--order", type=int, choices=(1, 2), help="1: P1 triangles, 2: P2 triangles")
    g.add_argument("--mesh-size-m", type=positive_float, metavar="H", help="element size at depth (m)")
    g.add_argument("--surface-refine", type=positive_float, metavar="F", help="top-surface size = H / F")
    g.add_argument("--plane", choices=("strain", "stress"), help="plane strain or plane stress")
    g.add_argument("--stones", choices=("auto", "rigid", "elastic"), default="auto",
                   help="auto: stones >= 1e4 times stiffer than tissue are rigid bodies (default)")
    i = p.add_argument_group("indentation (--load indent)")
    i.add_argument("--x-m", "--x0-m", dest="x_m", type=finite_float,
                   help="tip position along the top surface, from the left edge (m); --x0-m is its former name")
    i.add_argument("--y-m", "--y0-m", dest="y_m", type=finite_float,
                   help="3D scenes: tip position across the top face, from the front face (m)")
    i.add_argument("--depth-m", type=finite_float, help="indentation depth below the undeformed surface (m)")
    i.add_argument("--indenter-radius-m", type=positive_float, help="tip radius (m; default: the scene's [indenter])")
    p.set_defaults(func=run)
    return p


def _inputs(args) -> dict:
    """The files the command reads (an output must not be one of them)."""
    return {"SCENE": args.scene, **{f"--compare {c}": c for c in (args.compare or [])}}


def run(args) -> int:
    check_output_file(args.json, "--json", inputs=_inputs(args))
    check_output_dir(args.plots, "--plots")
    check_output_file(args.vtu, "--vtu", inputs=_inputs(args))
    refuse_figures(args.plots, SIMULATE_FIGURES, {"--json": args.json, "--vtu": args.vtu})
    if args.vtu and not args.vtu.lower().endswith(".vtu"):
        raise UsageError(f"--vtu {args.vtu}: give a file path ending in .vtu")
    if args.load == "uniform":       # the indentation's options have no meaning for load A: refused, not ignored
        given = [o for o, v in (("--x-m", args.x_m), ("--y-m", args.y_m), ("--depth-m", args.depth_m),
                                ("--indenter-radius-m", args.indenter_radius_m)) if v is not None]
        if given:
            raise UsageError(f"{given[0]}: an option of --load indent; --load uniform (the default) moves the whole top "
                             f"surface down by the scene's analysis.top_displacement_m")
    check_depth_floor(args.depth_m)
    sc = _scene(args)
    if sc.is_3d:                     # a block (tissue.length_m): fem's 3D path
        if args.indenter_radius_m is not None:
            sc = dataclasses.replace(sc, indenter=dataclasses.replace(sc.indenter, radius_m=args.indenter_radius_m))
        from app.commands import sim3d  # the 3D path (scipy.linalg, CHOLMOD): loaded for a 3D scene only
        return sim3d.run_simulate(args, sc, _rigid(args))
    if args.y_m is not None:
        raise UsageError(f"--y-m {args.y_m:g}: scene {sc.name!r} is a 2D section (no tissue.length_m); --y-m "
                         f"places the tip on a 3D block's top face")
    if args.load == "indent":
        return _run_indent(args)
    return _run_uniform(args)


def _run_indent(args) -> int:
    """Load B: the probe tip pressed ``--depth-m`` into the top surface at ``--x-m`` (fem.contact's fast path)."""
    if args.x_m is None or args.depth_m is None:
        print("palpate simulate: --load indent needs --x-m X and --depth-m D (tip position along the top surface "
              "and indentation depth, m)", file=sys.stderr)
        return 2
    if args.compare is not None:
        print("palpate simulate: --compare applies to --load uniform; for the stone/healthy comparison under "
              "the tip use `palpate predict`", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    sc = _scene(args)
    if args.indenter_radius_m is not None:
        sc = dataclasses.replace(sc, indenter=dataclasses.replace(sc.indenter, radius_m=args.indenter_radius_m))
    m = surface_model(sc, rigid_stones=_rigid(args))
    t1 = time.perf_counter()
    try:
        r = m.indent(args.x_m, args.depth_m)
    except ValueError as e:
        print(f"palpate simulate: --x-m (--x0-m) {args.x_m:g} / --depth-m {args.depth_m:g}: {e}", file=sys.stderr)
        return 2
    t2 = time.perf_counter()
    model, mesh = m.model, m.model.mesh
    u = m.full_field(args.x_m, args.depth_m)
    top = mesh.top
    surf = components((recovery_operator(model, top) @ u).reshape(-1, 3), nodal_poisson(model, top), model.plane)
    profile = Profile(mesh.nodes[top, 0], surf)
    nodal = None
    if args.plots or args.vtu:
        allnodes = np.arange(mesh.n_nodes)
        s3, eps = nodal_fields(model, u)
        nodal = components(s3, nodal_poisson(model, allnodes), model.plane)
        nodal.update({"exx": eps[:, 0], "eyy": eps[:, 1], "gxy": eps[:, 2]})
    t3 = time.perf_counter()
    res = r.to_dict()
    res["contact"]["nodal_force_n_per_m"] = r.nodal_force_n_per_m.tolist()
    out = {"scene": sc.name, "load": "indent", **res,
           "indenter": dataclasses.asdict(sc.indenter), "analysis": dataclasses.asdict(sc.analysis),
           "rigid_stones": [bool(x) for x in model.rigid],
           **profile.to_dict(),
           "mesh": {"nodes": int(mesh.n_nodes), "elements": int(len(mesh.tris)), "order": int(mesh.order),
                    "dofs": int(model.n_dofs), "dofs_full": int(mesh.n_dofs), "contact_candidates": int(len(top))},
           "timings_s": {**m.timings_s, "model_s": t1 - t0, "indent_s": t2 - t1, "fields_s": t3 - t2},
           "files": {}}
    if args.vtu:
        from fem.export import write_vtu
        out["files"]["vtu"] = str(write_vtu(args.vtu, mesh, u, point_data=nodal))
    if args.plots:
        out["files"].update(_indent_figures(Path(args.plots), sc, m, r, u, nodal))
    out["timings_s"]["total_s"] = time.perf_counter() - t0
    write_json(args.json, out)        # (first: a reader that closes the pipe early does not lose the file)
    _indent_summary(sc, r, out, sys.stderr if args.json == "-" else sys.stdout)
    warn_unresolved2d(sc, "simulate", [r.half_width_m], depths_m=[args.depth_m])
    warn_pressure_near_incompressible2d(sc, "simulate", [r.half_width_m])
    warn_strain("simulate", sc, args.depth_m)
    return 0


def _indent_figures(d: Path, sc, m, r, u, nodal) -> dict[str, str]:
    """fig10_indent.png: von Mises over the deformed section and von Mises, sigma_xx, sigma_yy under the tip."""
    from fem import plots  # matplotlib: loaded only when figures are asked for
    mesh = m.model.mesh
    dm = plots.deformed(mesh, u)
    U = np.asarray(u).reshape(-1, 2)
    outl = []
    for k, (x, y, rad) in enumerate(plots.outlines_of(sc)):          # stones drawn where they moved to
        nodes = np.unique(mesh.tris[mesh.region == k + 1])
        dx, dy = U[nodes].mean(axis=0) if len(nodes) else (0.0, 0.0)
        outl.append((x + dx, y + dy, rad))
    R, H, W = sc.indenter.radius_m, sc.tissue.height_m, sc.tissue.width_m
    half = max(3 * R, 2.5 * r.depth_m + 2 * R)
    zoom = (max(0.0, r.x_m - half), min(W, r.x_m + half), max(0.0, H - 1.2 * half), H + 0.5 * R)
    # the maximum's node, where it moved to (max_von_mises_at_m is (x, depth below the undeformed surface))
    j = np.argmin(np.hypot(mesh.nodes[:, 0] - r.max_von_mises_at_m[0], mesh.nodes[:, 1] - (H - r.max_von_mises_at_m[1])))
    mark = tuple(dm.nodes[j])
    a = sc.analysis
    tag = (f"{sc.name}: {sc.indenter.shape} tip R = {R * 1e3:g} mm at x = {r.x_m * 1e3:g} mm, depth "
           f"{r.depth_m * 1e3:g} mm, F = {r.force_n:.4g} N; plane {a.plane}, P{a.order}, h = {a.mesh_size_m * 1e3:g} mm"
           " (deformed, true scale)")
    f = plots.indent_panels(d / FIG_INDENT_2D, dm, {k: nodal[k] for k in ("von_mises_pa", "sxx_pa", "syy_pa")},
                            indenter=sc.indenter, x_m=r.x_m, tip_bottom_y_m=H - r.depth_m, outlines=outl,
                            zoom_m=zoom, mark_m=mark, suptitle=tag)
    return {"indent": str(f)}


def _indent_summary(sc, r, out, stream) -> None:
    a, mm, t = sc.analysis, out["mesh"], out["timings_s"]
    active = r.nodal_force_n_per_m > 0
    lines = [f"scene {sc.name}: load indent ({sc.indenter.shape} tip, R = {sc.indenter.radius_m * 1e3:g} mm, "
             f"{sc.indenter.thickness_m * 1e3:g} mm thick) at x = {r.x_m * 1e3:g} mm, depth {r.depth_m * 1e3:g} mm; "
             f"plane {a.plane}, P{a.order}, h = {a.mesh_size_m * 1e3:g} mm (top {a.mesh_size_m / a.surface_refine * 1e3:g} mm)",
             f"  mesh: {mm['nodes']} nodes, {mm['elements']} elements, {mm['dofs']} DOFs",
             f"  force: {r.force_n:.5g} N ({r.force_n_per_m:.5g} N/m)",
             f"  contact: half-width {r.half_width_m * 1e3:.3f} mm, {int(active.sum())} nodes in contact, "
             f"peak pressure {r.pressure_pa.max():.4g} Pa",
             f"  max von Mises {r.max_von_mises_pa:.4g} Pa at x = {r.max_von_mises_at_m[0] * 1e3:.2f} mm, "
             f"{r.max_von_mises_at_m[1] * 1e3:.2f} mm below the surface",
             f"  tip: {r.tip_note}",
             "  time: " + ", ".join(f"{k[:-2]} {v:.3f} s" for k, v in t.items())]
    lines += [f"  wrote {k}: {f}" for k, f in out["files"].items()]
    print("\n".join(lines), file=stream)


# ------------------------------------------------------------------------------------------------- load A

def _scene(args):
    sc = load_scene(args.scene)
    changes = analysis_changes(args, sc)
    return sc.with_analysis(**changes) if changes else sc


def _rigid(args):
    return {"auto": "auto", "rigid": True, "elastic": False}[args.stones]


def _compare_names(args, sc) -> list[str]:
    if args.compare is not None:
        names = list(args.compare) or list(COMPARE_DEFAULT)
    elif args.plots and args.scene in PAPER_FAMILY:
        names = list(COMPARE_DEFAULT)
    else:
        return []
    return [n for n in dict.fromkeys([args.scene] + names)]


def _run_uniform(args) -> int:
    t0 = time.perf_counter()
    sc = _scene(args)
    names = _compare_names(args, sc)
    if names and not args.plots:
        raise UsageError("--compare needs --plots DIR (where the comparison figure goes)")
    others = {}
    for name in names:                          # checked before anything is solved
        if name != args.scene:
            others[name] = load_scene(name, "--compare")
            if others[name].is_3d:
                raise UsageError(f"--compare {name}: a 3D block (tissue.length_m); {args.scene} is a 2D section "
                                 f"and --compare takes 2D sections (for blocks: palpate predict SCENE --compare)")
    want_field = bool(args.plots or args.vtu)
    for name, scene in ((args.scene, sc), *others.items()):     # load A's own limit, named with its scene
        try:
            check_load_a(scene)
        except SceneError as e:
            raise UsageError(f"scene {name}: {e}") from None
    res = solve_uniform(sc, full_field=want_field, rigid_stones=_rigid(args))
    mesh = res.model.mesh
    out = {"scene": sc.name, "load": "uniform", "analysis": dataclasses.asdict(sc.analysis),
           "rigid_stones": [bool(r) for r in res.model.rigid],
           **res.surface.to_dict(),
           "reaction_n_per_m": res.reaction_n_per_m,
           "force_n": res.reaction_n_per_m * sc.indenter.thickness_m,
           "mesh": {"nodes": int(mesh.n_nodes), "elements": int(len(mesh.tris)), "order": int(mesh.order),
                    "dofs": int(res.model.n_dofs), "dofs_full": int(mesh.n_dofs)},
           "timings_s": dict(res.timings_s), "files": {}}

    if args.vtu:
        from fem.export import write_result_vtu
        out["files"]["vtu"] = str(write_result_vtu(args.vtu, res))

    compare = []
    if names:
        for name in names:
            if name == args.scene:
                other, r = sc, res
            else:
                other = dataclasses.replace(others[name], analysis=sc.analysis)
                r = solve_uniform(other, full_field=False, rigid_stones=_rigid(args))
            compare.append((other, r.surface))
        out["compare"] = [{"scene": o.name, "peak": prof.to_dict()["peak"]} for o, prof in compare]

    if args.plots:
        out["files"].update(_figures(Path(args.plots), sc, res, compare))
    out["timings_s"]["total_s"] = time.perf_counter() - t0

    write_json(args.json, out)
    _summary(sc, res, out, sys.stderr if args.json == "-" else sys.stdout)
    return 0


def _figures(d: Path, sc, res, compare) -> dict[str, str]:
    from fem import plots  # matplotlib: loaded only when figures are asked for
    mesh, n = res.model.mesh, res.nodal
    outl = plots.outlines_of(sc)
    a = sc.analysis
    tag = (f"{sc.name}: top moved down {a.top_displacement_m * 1e3:g} mm, plane {a.plane}, "
           f"P{a.order}, h = {a.mesh_size_m * 1e3:g} mm")
    files = {}
    files["stress"] = plots.field_panels(d / FIGURES["stress"], mesh,
                                         {k: n[k] for k in ("sxx_pa", "syy_pa", "sxy_pa", "von_mises_pa")},
                                         outlines=outl, suptitle=f"Stress - {tag}")
    fields = {k: n[k] for k in ("exx", "eyy", "gxy")}
    fields["uy_m"] = res.u[1::2]
    files["strain"] = plots.field_panels(d / FIGURES["strain"], mesh, fields, outlines=outl,
                                         suptitle=f"Strain and displacement - {tag}", scales={"uy_m": 1e3})
    files["surface"] = plots.surface_graph(d / FIGURES["surface"], res.surface, stones_x=[s.x_m for s in sc.stones],
                                           title=f"Top-surface stress - {tag}")
    if compare:
        curves = [(o.name, prof, [s.x_m for s in o.stones]) for o, prof in compare]
        files["compare"] = plots.compare_profiles(d / FIGURES["compare"], curves,
                                                  title=f"Top-surface von Mises, P{a.order}, plane {a.plane}")
    return {k: str(v) for k, v in files.items()}


def _summary(sc, res, out, stream) -> None:
    """The human summary (on stderr when the JSON goes to stdout)."""
    xp, vp = res.surface.peak()
    vm = res.surface.fields["von_mises_pa"]
    a, m, t = sc.analysis, out["mesh"], out["timings_s"]
    rig = sum(out["rigid_stones"])
    lines = [f"scene {sc.name}: load uniform (top down {a.top_displacement_m * 1e3:g} mm), plane {a.plane}, "
             f"P{a.order}, h = {a.mesh_size_m * 1e3:g} mm (top {a.mesh_size_m / a.surface_refine * 1e3:g} mm)",
             f"  mesh: {m['nodes']} nodes, {m['elements']} elements, {m['dofs']} DOFs solved"
             + (f" ({m['dofs_full']} before {rig} rigid stone(s))" if rig else ""),
             f"  peak von Mises on the top surface: {vp:.2f} Pa at x = {xp * 1e3:.2f} mm"
             + (" (uniform along the surface)" if np.ptp(vm) < 1e-6 * vm.max() else ""),
             f"  reaction: {res.reaction_n_per_m:.3f} N/m ({out['force_n']:.4f} N over "
             f"{sc.indenter.thickness_m * 1e3:g} mm thickness)",
             "  time: " + ", ".join(f"{k[:-2]} {v:.2f} s" for k, v in t.items())]
    lines += [f"  compare {c['scene']}: peak {c['peak']['von_mises_pa']:.2f} Pa at x = {c['peak']['x_m'] * 1e3:.2f} mm"
              for c in out.get("compare", [])[1:]]
    lines += [f"  wrote {k}: {f}" for k, f in out["files"].items()]
    print("\n".join(lines), file=stream)
