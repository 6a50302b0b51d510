"""`palpate simulate SCENE --load uniform|indent`: one FEM analysis of a scene, with JSON, figures and VTU.

Load ``uniform`` is the study's load A (the whole top edge moved down by ``analysis.top_displacement_m``).
Load ``indent`` (a probe tip pressed in at x0) arrives with fem.contact: ``_run_indent`` is its hook.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

PAPER_FAMILY = ("paper", "paper-left", "paper-right", "paper-deep")
COMPARE_DEFAULT = PAPER_FAMILY + ("healthy",)

FIGURES = {
    "stress": "fig3_stress.png",          # sxx, syy, sxy, von Mises contours (study Fig 3)
    "strain": "fig4_strain.png",          # exx, eyy, gxy, u_y contours (study Fig 4)
    "surface": "fig5_surface.png",        # stresses along the top surface (study Fig 5)
    "compare": "fig6_7_9_compare.png",    # von Mises along the top for several scenes (study Figs 6, 7, 9)
}

HELP = """Solve one scene under a load and report the top-surface stress.

figures (--plots DIR):
  fig3_stress.png       contours of sigma_xx, sigma_yy, sigma_xy and von Mises over the section (study Fig 3)
  fig4_strain.png       contours of eps_xx, eps_yy, gamma_xy and u_y (study Fig 4)
  fig5_surface.png      the stresses along the top surface, peak marked (study Fig 5)
  fig6_7_9_compare.png  von Mises along the top for the centred, left, right and small deep stone and healthy
                        tissue on one axes (study Figs 6, 7, 9). Made automatically for the built-in scenes
                        paper, paper-left, paper-right, paper-deep; for other scenes ask with --compare.
The compared scenes are solved with the same analysis options (order, mesh size, plane) as SCENE."""

EXAMPLES = """examples:
  palpate simulate paper --load uniform --plots out/ --json out/paper.json --vtu out/paper.vtu
  palpate simulate my_kidney.toml --order 1 --mesh-size-m 0.001 --compare paper paper-deep --plots out/"""


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("simulate", help="one FEM analysis of a scene (load A: uniform top displacement)",
                       description=HELP, epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", metavar="SCENE", help="built-in name (paper, paper-left, paper-right, paper-deep, "
                                                  "healthy) or a TOML file")
    p.add_argument("--load", choices=("uniform", "indent"), default="uniform",
                   help="uniform: the whole top edge moved down by analysis.top_displacement_m (default); "
                        "indent: a probe tip pressed in at --x0-m")
    p.add_argument("--json", metavar="PATH", help="write the machine-readable result here ('-': stdout)")
    p.add_argument("--plots", metavar="DIR", help="write the figures (listed above) into DIR")
    p.add_argument("--vtu", metavar="PATH", help="write displacement, stress and strain fields as VTU (ParaView)")
    p.add_argument("--compare", nargs="*", metavar="SCENE",
                   help="scenes whose von Mises profiles go on the comparison figure with SCENE's (no names: "
                        f"{' '.join(COMPARE_DEFAULT)}); needs --plots; put it after SCENE")
    g = p.add_argument_group("analysis overrides (default: the scene's [analysis] table)")
    g.add_argument("--order", type=int, choices=(1, 2), help="1: P1 triangles, 2: P2 triangles")
    g.add_argument("--mesh-size-m", type=float, metavar="H", help="element size at depth (m)")
    g.add_argument("--surface-refine", type=float, metavar="F", help="top-surface size = H / F")
    g.add_argument("--plane", choices=("strain", "stress"), help="plane strain or plane stress")
    g.add_argument("--stones", choices=("auto", "rigid", "elastic"), default="auto",
                   help="auto: stones >= 1e4 times stiffer than tissue are rigid bodies (default)")
    i = p.add_argument_group("indentation (--load indent)")
    i.add_argument("--x0-m", type=float, help="tip position along the top surface (m)")
    i.add_argument("--depth-m", type=float, help="indentation depth (m)")
    i.add_argument("--indenter-radius-m", type=float, help="tip radius (m)")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    if args.load == "indent":
        return _run_indent(args)
    return _run_uniform(args)


def _run_indent(args) -> int:
    print("palpate simulate: the indent load arrives with fem.contact (not built yet); use --load uniform",
          file=sys.stderr)
    return 2


# ------------------------------------------------------------------------------------------------- load A

def _scene(args):
    from fem import scene as S
    sc = S.load(args.scene)
    changes = {k: v for k, v in (("order", args.order), ("mesh_size_m", args.mesh_size_m),
                                 ("surface_refine", args.surface_refine), ("plane", args.plane))
               if v is not None}
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
    from fem import scene as S
    from fem.uniform import solve_uniform
    t0 = time.perf_counter()
    sc = _scene(args)
    want_field = bool(args.plots or args.vtu)
    res = solve_uniform(sc, full_field=want_field, rigid_stones=_rigid(args))
    mesh = res.model.mesh
    out = {"scene": sc.name, "load": "uniform", "analysis": dataclasses.asdict(sc.analysis),
           "rigid_stones": [bool(r) for r in res.model.rigid],
           **res.surface.to_json(),
           "reaction_n_per_m": res.reaction_n_per_m,
           "force_n": res.reaction_n_per_m * sc.indenter.thickness_m,
           "mesh": {"nodes": int(mesh.n_nodes), "elements": int(len(mesh.tris)), "order": int(mesh.order),
                    "dofs": int(res.model.n_dofs), "dofs_full": int(mesh.n_dofs)},
           "timings_s": dict(res.timings_s), "files": {}}

    if args.vtu:
        from fem.export import write_result_vtu
        out["files"]["vtu"] = str(write_result_vtu(args.vtu, res))

    compare = []
    names = _compare_names(args, sc)
    if names and not args.plots:
        print("palpate simulate: --compare needs --plots DIR (where the figure goes)", file=sys.stderr)
        return 2
    if names:
        for name in names:
            if name == args.scene:
                other, r = sc, res
            else:
                other = dataclasses.replace(S.load(name), analysis=sc.analysis)
                r = solve_uniform(other, full_field=False, rigid_stones=_rigid(args))
            compare.append((other, r.surface))
        out["compare"] = [{"scene": o.name, "peak": prof.to_json()["peak"]} for o, prof in compare]

    if args.plots:
        out["files"].update(_figures(Path(args.plots), sc, res, compare))
    out["timings_s"]["total_s"] = time.perf_counter() - t0

    _summary(sc, res, out, sys.stderr if args.json == "-" else sys.stdout)
    if args.json:
        text = json.dumps(out, indent=1)
        if args.json == "-":
            print(text)
        else:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
            Path(args.json).write_text(text + "\n")
    return 0


def _figures(d: Path, sc, res, compare) -> dict[str, str]:
    from fem import plots
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
    import numpy as np
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
