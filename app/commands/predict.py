"""`palpate predict SCENE --waypoints N [--depth-m D]`: what the probe would feel across the surface (load B).

The tip force and the maximum von Mises stress under the tip at N evenly spaced waypoints, for SCENE and for a
reference (by default SCENE's prior: the same tissue without stones), and their ratio. One mesh and one
factorization per scene; each waypoint is a small contact problem on the condensed surface (fem.contact), and the
stresses of all waypoints come from one batched back-substitution.
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
from app.figure_names import FIG_PREDICT_2D, FIG_PREDICT_3D
from app.options import (
    MAX_WAYPOINTS,
    analysis_changes,
    check_depth_floor,
    check_output_dir,
    check_output_file,
    finite_float,
    int_range,
    load_scene,
    positive_float,
    refuse_figures,
)
from app.resolution import warn_unresolved2d
from core.contracts import TIP_DEPTH_FRACTION, Limits, default_depth_limit_m, default_depth_said
from core.peak import or_null, parabola_peak, ratio_of, upper_window
from fem.contact import check_waypoint, surface_model
from fem.scene import SceneError, tip_taken_as_rigid

DEFAULT_DEPTH_M = Limits().depth_limit_m      # (core.contracts.default_depth_limit_m: less on a small tip)
DEFAULT_MARGIN_M = 0.005
BATCH = 100            # waypoints per batched back-substitution (memory: n_dofs x BATCH doubles)

DESCRIPTION = """Predict the probe's tip force and the maximum von Mises stress under the tip at N waypoints across
the top surface (load B: a tip pressed --depth-m into the surface at each waypoint, frictionless contact), for
SCENE and for a reference scene, and report their ratio (SCENE / reference).

The reference defaults to SCENE's prior: the same tissue, tip and analysis without the stones (what a surgeon
knows before probing). --compare NAME uses another scene as the reference (its tissue and stones, SCENE's tip and
analysis options); --compare none skips it.

The maximum von Mises stress is searched within 2 R (R: tip radius) below the surface: over the nodes in 2D, over
the stress points of the tissue's elements on a 3D block (4 per element, where a quadratic element's stress is most
accurate; against Hertz for a sphere +1 to +12 % high once the contact radius spans 3 or more of the patch's
elements, and a warning below that, where it can be 20 % off; JSON contact_radius_over_element). Waypoints run from
--margin-m to width - --margin-m, ends included.

figures (--plots DIR):
  fig11_predict.png   force (left axis) and max von Mises (right axis) against tip position for SCENE (solid) and
                      the reference (dashed), and below their ratios; the stones' extent shaded (study Fig 11)"""

EPILOG = """examples:
  palpate predict paper --waypoints 100 --plots out/ --json out/predict.json
  palpate predict paper-left --waypoints 50 --depth-m 0.003 --compare healthy
  palpate predict my_kidney.toml --waypoints 200 --margin-m 0.008 --mesh-size-m 0.003
  palpate predict block3d --grid 10x10 --depth-m 0.003 --plots out/ --json out/predict3d.json
3D (--grid): the same keys plus y_m (waypoints.y_m, max_von_mises_at_y_m, peak_ratio.y_m), contact_radius_m in
place of half_width_m and no force_n_per_m; figure fig3d_predict.png (force, max stress and contrast maps).
JSON (--json): waypoints {x_m, force_n, force_n_per_m, max_von_mises_pa, max_von_mises_at_x_m,
max_von_mises_at_depth_m, half_width_m}, reference {the same}, ratio [force ratio per waypoint],
ratio_von_mises [...], peak_ratio {x_m (sub-waypoint fit), ratio, x_max_sample_m}, peak_ratio_von_mises {...},
timings_s {...}."""


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser("predict", help="tip force and max stress at N waypoints across the surface (load B)",
                       description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", metavar="SCENE", help="built-in name (paper, paper-left, paper-right, paper-deep, "
                                                  "healthy; 3D: block3d, block3d-healthy, block3d-left, "
                                                  "block3d-front, block3d-deep) or a TOML file")
    p.add_argument("--waypoints", type=int_range(2, MAX_WAYPOINTS), metavar="N",
                   help=f"2D scenes: number of waypoints, 2..{MAX_WAYPOINTS} (default 50)")
    p.add_argument("--depth-m", type=positive_float,
                   help=f"indentation depth at every waypoint (default {DEFAULT_DEPTH_M}, or {TIP_DEPTH_FRACTION:g} of "
                        f"the tip's radius when that is less)")
    p.add_argument("--margin-m", type=finite_float,
                   help=f"2D scenes: keep the waypoints this far from the side edges (default {DEFAULT_MARGIN_M})")
    p.add_argument("--compare", metavar="SCENE", default="prior",
                   help="reference scene: 'prior' (SCENE without stones, default), a scene name or TOML (its tissue "
                        "and stones, probed with SCENE's tip and analysed with SCENE's [analysis]), or 'none'")
    p.add_argument("--grid", metavar="NXxNY",
                   help="3D scenes: an NX x NY grid of waypoints over the probed patch less the tip radius "
                        "(default 10x10); 2D scenes use --waypoints")
    p.add_argument("--force-only", action="store_true", help="skip the stresses (forces only: much faster)")
    p.add_argument("--json", metavar="PATH", help="write the machine-readable result here ('-': stdout)")
    p.add_argument("--plots", metavar="DIR", help=f"write {FIG_PREDICT_2D} into DIR")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    g = p.add_argument_group("analysis overrides (default: the scene's [analysis] table)")
    g.add_argument("--order", type=int, choices=(1, 2), help="1: P1 triangles, 2: P2 triangles")
    g.add_argument("--mesh-size-m", type=positive_float, metavar="H", help="element size at depth (m)")
    g.add_argument("--surface-refine", type=positive_float, metavar="F", help="top-surface size = H / F")
    g.add_argument("--plane", choices=("strain", "stress"), help="plane strain or plane stress")
    g.add_argument("--indenter-radius-m", type=positive_float, help="tip radius (m; default: the scene's [indenter])")
    p.set_defaults(func=run)
    return p


def _scenes(args):
    sc = load_scene(args.scene)
    changes = analysis_changes(args, sc)
    if changes:
        sc = sc.with_analysis(**changes)
    if args.indenter_radius_m is not None:
        sc = dataclasses.replace(sc, indenter=dataclasses.replace(sc.indenter, radius_m=args.indenter_radius_m))
    c = (args.compare or "prior").strip()
    if c.lower() == "none":
        ref = None
    elif c.lower() == "prior":
        ref = sc.prior()
    else:   # another scene's tissue and stones, probed with SCENE's tip and analysed like SCENE
        other = load_scene(c, "--compare")
        if other.is_3d != sc.is_3d:
            raise UsageError(f"--compare {c}: is a {'3D block' if other.is_3d else '2D section'} and scene "
                             f"{sc.name!r} a {'3D block' if sc.is_3d else '2D section'}: compare like with like")
        for name in ("width_m", "length_m") if sc.is_3d else ("width_m",):
            a, b = getattr(other.tissue, name), getattr(sc.tissue, name)
            if a != b:
                raise UsageError(f"--compare {c}: its tissue.{name} is {a:g} m and scene {sc.name}'s {b:g} m: the "
                                 f"reference is probed at the scene's waypoints, so they must be equal")
        tip = lambda x: (x.indenter.shape, x.indenter.radius_m, x.indenter.thickness_m,    # noqa: E731
                         tip_taken_as_rigid(x) or x.indenter)       # (a rigid-treated tip's modulus changes nothing)
        dropped = [t for t, differs in (("indenter", tip(other) != tip(sc)), ("analysis", other.analysis != sc.analysis))
                   if differs]
        if dropped:         # said, not silently replaced: the comparison is of tissues under one tip
            print(f"palpate predict: --compare {c}: its [{'] and ['.join(dropped)}] {'differs' if len(dropped) == 1 else 'differ'} from scene {sc.name}'s; "
                  f"the reference is probed with {sc.name}'s tip and analysis (the comparison is of the tissues)",
                  file=sys.stderr)
        try:
            ref = dataclasses.replace(other, indenter=sc.indenter, analysis=sc.analysis)
        except SceneError as e:
            raise UsageError(f"--compare {c} with scene {sc.name}'s tip and analysis: {e}") from None
    return sc, ref


def waypoints(width_m: float, n: int, margin_m: float) -> np.ndarray:
    """N evenly spaced positions on [margin, width - margin] (the centre when N = 1); as planner.raster does."""
    if n < 1:
        raise ValueError(f"--waypoints must be at least 1, got {n}")
    if not (0 <= margin_m < width_m / 2):
        raise ValueError(f"--margin-m {margin_m} must lie in [0, width/2 = {width_m / 2:g}) m")
    return np.array([0.5 * width_m]) if n == 1 else np.linspace(margin_m, width_m - margin_m, n)


def predict(scene, xs: np.ndarray, depth_m: float, *, stresses: bool = True, progress=None) -> dict:
    """Force and maximum von Mises at each x for one scene: {"x_m", "force_n", ..., "timings_s"} (lists)."""
    t0 = time.perf_counter()
    m = surface_model(scene)
    t1 = time.perf_counter()
    rows = []
    for k in range(0, len(xs), BATCH):
        rows += m.indent_many(xs[k:k + BATCH], depth_m, stresses=stresses)
        if progress:
            progress(min(k + BATCH, len(xs)), len(xs))
    t2 = time.perf_counter()
    mesh = m.model.mesh
    return {"x_m": [r.x_m for r in rows], "force_n": [r.force_n for r in rows],
            "force_n_per_m": [r.force_n_per_m for r in rows],
            "max_von_mises_pa": [r.max_von_mises_pa for r in rows] if stresses else None,
            "max_von_mises_at_x_m": [r.max_von_mises_at_m[0] for r in rows] if stresses else None,
            "max_von_mises_at_depth_m": [r.max_von_mises_at_m[1] for r in rows] if stresses else None,
            "half_width_m": [r.half_width_m for r in rows],
            "tip_note": m.tip_note,
            "mesh": {"nodes": int(mesh.n_nodes), "elements": int(len(mesh.tris)), "dofs": int(m.model.n_dofs),
                     "contact_candidates": int(len(m.top))},
            "timings_s": {"setup_s": t1 - t0, "predict_s": t2 - t1, "per_waypoint_s": (t2 - t1) / len(xs)}}


def ratio_line(out: dict) -> str:
    """The reference line: where the force (and von Mises) ratio peaks, and how many waypoints have none."""
    pr, pv = out["peak_ratio"], out.get("peak_ratio_von_mises")
    undefined = max(sum(v is None for v in out[k]) for k in ("ratio", "ratio_von_mises") if k in out)
    if pr is None:
        return (f"  vs {out['reference_scene']}: no force ratio: the reference feels no force at any waypoint (the "
                f"tip touches no surface node: a depth below the mesh's resolution)")
    s = f"  vs {out['reference_scene']}: force ratio peaks at {pr['ratio']:.4f} at x = {pr['x_m'] * 1e3:.1f} mm"
    if pv is not None:
        s += f"; max von Mises ratio peaks at {pv['ratio']:.4f} at x = {pv['x_m'] * 1e3:.1f} mm"
    if undefined:
        s += (f"\n  warning: no ratio (null) at {undefined} of {len(out['ratio'])} waypoints: the reference feels no "
              f"force there (the tip touches no surface node: a depth below the mesh's resolution)")
    return s


def _peak(xs, ratio) -> dict | None:
    """Peak of a ratio profile. Near its top the ratio is flat to ~1e-6 while the two meshes differ by ~1e-4, so the
    largest sample can sit a waypoint or two off; ``x_m`` is the vertex of a least-squares parabola through the
    contiguous samples in the peak's upper quarter up to a valley (``core.peak.upper_window``; where fewer than three
    lie there, a peak sharper than the spacing, the largest and its two neighbours; ``x_max_sample_m``:
    the largest sample); ``ratio``: the parabola's value there, or the largest sample's where that is higher (a
    lopsided hump). Where the window's parabola rises above the largest sample by more than the drop from it to its
    lower neighbour (it does not describe the top), both come from the parabola through the largest sample and its
    two neighbours. Undefined ratios (NaN) are skipped; None when there is none."""
    ratio = np.asarray(ratio, float)
    if not np.isfinite(ratio).any():
        return None
    i = int(np.nanargmax(ratio))
    out = {"x_m": float(xs[i]), "ratio": float(ratio[i]), "index": i, "x_max_sample_m": float(xs[i])}
    lo, hi = upper_window(ratio, i)
    if hi - lo < 2 and 0 < i < len(ratio) - 1 and np.isfinite(ratio[i - 1:i + 2]).all():
        lo, hi = i - 1, i + 1       # a peak sharper than the waypoints' spacing: the parabola through its top three
    x_fit, fit = parabola_peak(xs, ratio, lo, hi)
    near = ratio[max(i - 1, 0):i + 2]
    near = near[np.isfinite(near)]
    if fit - ratio[i] > ratio[i] - np.min(near):
        # the window's parabola does not describe the top (a plateau falling off steeply: it rose 2.6e-3 above a
        # largest sample 1.3e-3 above its lower neighbour): the parabola through the top three samples, which
        # rises at most a quarter of that drop above the largest; the largest sample itself at an end of the
        # profile or beside an undefined ratio
        three = 0 < i < len(ratio) - 1 and len(near) == 3
        x_fit, fit = parabola_peak(xs, ratio, i - 1, i + 1) if three else (float(xs[i]), ratio[i])
    out["x_m"] = x_fit
    # the peak is at least the largest sample: on a lopsided hump (two stones) the window's parabola peaks below it
    out["ratio"] = max(float(fit), float(ratio[i]))
    return out


def run(args) -> int:
    t0 = time.perf_counter()
    check_output_file(args.json, "--json", inputs={"SCENE": args.scene, "--compare": args.compare})
    check_output_dir(args.plots, "--plots")
    refuse_figures(args.plots, (FIG_PREDICT_2D, FIG_PREDICT_3D), {"--json": args.json})
    if args.plots and args.force_only:
        raise UsageError("--plots needs the stresses (drop --force-only)")
    if args.depth_m is not None:
        check_depth_floor(args.depth_m)
    sc, ref = _scenes(args)
    args.depth_note = None
    args.depth_name = f"--depth-m {args.depth_m:g}" if args.depth_m is not None else ""
    if args.depth_m is None:         # as a run's depth limit: 4 mm, or 0.8 of a smaller tip's radius (session 52)
        args.depth_m = default_depth_limit_m(sc.indenter.radius_m)
        if said := default_depth_said(sc.indenter.radius_m):   # (said once the options are checked: bad input
            args.depth_note = f"palpate predict: depth {said}; --depth-m to choose"    # gets one line)
        check_depth_floor(args.depth_m)
        args.depth_name = (f"the default depth {args.depth_m:g} m ({DEFAULT_DEPTH_M:g} m, or {TIP_DEPTH_FRACTION:g} of "
                           f"the tip's radius where that is less; --depth-m to choose)")
    if sc.is_3d:                     # a block (tissue.length_m): fem's 3D path
        for opt, v in (("--waypoints", args.waypoints), ("--margin-m", args.margin_m)):
            if v is not None:
                raise UsageError(f"{opt} {v}: scene {sc.name!r} is a 3D block: its waypoints are a grid over the probed "
                                 f"patch less the tip radius (--grid NXxNY)")
        from app.commands import sim3d  # the 3D path (scipy.linalg, CHOLMOD): loaded for a 3D scene only
        return sim3d.run_predict(args, sc, ref)
    args.waypoints = args.waypoints or 50
    args.margin_m = DEFAULT_MARGIN_M if args.margin_m is None else args.margin_m
    if args.grid is not None:
        raise UsageError(f"--grid {args.grid}: scene {sc.name!r} is a 2D section (no tissue.length_m); use "
                         f"--waypoints N")
    try:
        xs = waypoints(sc.tissue.width_m, args.waypoints, args.margin_m)
    except ValueError as e:
        print(f"palpate predict: {e}", file=sys.stderr)
        return 2
    try:
        check_waypoint(sc, float(xs[0]), args.depth_m)
    except ValueError as e:
        raise UsageError(f"{args.depth_name} on scene {sc.name}: {e}") from None
    if args.depth_note:
        print(args.depth_note, file=sys.stderr)
    stresses = not args.force_only
    verbose = not args.quiet and args.waypoints > BATCH

    def progress(label):
        if not verbose:
            return None
        return lambda done, total: print(f"  {label}: {done}/{total} waypoints ({time.perf_counter() - t0:.1f} s)",
                                         file=sys.stderr, flush=True)

    try:         # fem refuses a waypoint the checks above cannot see (a stone the tip would crush the tissue onto)
        main = predict(sc, xs, args.depth_m, stresses=stresses, progress=progress(sc.name))
    except ValueError as e:
        raise UsageError(f"{args.depth_name} on scene {sc.name}: {e}") from None
    warn_unresolved2d(sc, "predict", main["half_width_m"], stresses)
    out = {"scene": sc.name, "load": "indent", "depth_m": args.depth_m, "margin_m": args.margin_m,
           "indenter": dataclasses.asdict(sc.indenter), "analysis": dataclasses.asdict(sc.analysis),
           "stones": [dataclasses.asdict(s) for s in sc.stones], "waypoints": main, "files": {}}
    if ref is not None:
        try:
            rd = predict(ref, xs, args.depth_m, stresses=stresses, progress=progress(ref.name))
        except ValueError as e:
            raise UsageError(f"{args.depth_name} on the reference (--compare {args.compare}): {e}") from None
        out["reference_scene"] = ref.name
        out["reference"] = rd
        ratio = ratio_of(main["force_n"], rd["force_n"])
        out["ratio"] = or_null(ratio)
        out["peak_ratio"] = _peak(xs, ratio)
        if stresses:
            rs = ratio_of(main["max_von_mises_pa"], rd["max_von_mises_pa"])
            out["ratio_von_mises"] = or_null(rs)
            out["peak_ratio_von_mises"] = _peak(xs, rs)
    t = {"setup_s": main["timings_s"]["setup_s"], "predict_s": main["timings_s"]["predict_s"],
         "per_waypoint_s": main["timings_s"]["per_waypoint_s"]}
    if ref is not None:
        t.update({"reference_setup_s": out["reference"]["timings_s"]["setup_s"],
                  "reference_predict_s": out["reference"]["timings_s"]["predict_s"]})
    if args.plots:
        if not stresses:
            print("palpate predict: --plots needs the stresses (drop --force-only)", file=sys.stderr)
            return 2
        out["files"]["predict"] = str(_figure(Path(args.plots), sc, ref, out))
    t["total_s"] = time.perf_counter() - t0
    out["timings_s"] = t
    write_json(args.json, out)        # (first: a reader that closes the pipe early does not lose the file)
    _summary(sc, out, sys.stderr if args.json == "-" else sys.stdout)
    warn_strain("predict", sc, args.depth_m)
    return 0


def _figure(d: Path, sc, ref, out) -> Path:
    from fem import plots  # matplotlib: loaded only when figures are asked for
    w = out["waypoints"]
    a = sc.analysis
    ref_w = out.get("reference") or w
    title = (f"{sc.name}: {sc.indenter.shape} tip R = {sc.indenter.radius_m * 1e3:g} mm pressed "
             f"{out['depth_m'] * 1e3:g} mm at {len(w['x_m'])} waypoints; plane {a.plane}, P{a.order}, "
             f"h = {a.mesh_size_m * 1e3:g} mm")
    return plots.predict_graph(d / FIG_PREDICT_2D, np.asarray(w["x_m"]), w, ref_w,
                               labels=(sc.name, ref.name if ref is not None else sc.name),
                               stones=[(s.x_m, s.diameter_m) for s in sc.stones], title=title,
                               peak=_peak_xy(out.get("peak_ratio")))


def _peak_xy(pr) -> tuple[float, float] | None:
    """The force ratio's peak as the JSON reports it ((x_m, ratio)), for the figure's marker; None when there is none
    (no reference, or no finite ratio)."""
    if not isinstance(pr, dict):
        return None
    x, r = pr.get("x_m"), pr.get("ratio")
    ok = all(isinstance(v, (int, float)) and np.isfinite(v) for v in (x, r))
    return (float(x), float(r)) if ok else None


def _summary(sc, out, stream) -> None:
    w, t = out["waypoints"], out["timings_s"]
    x, f = np.asarray(w["x_m"]), np.asarray(w["force_n"])
    n = len(x)
    lines = [f"scene {sc.name}: {n} waypoints from x = {x[0] * 1e3:g} to {x[-1] * 1e3:g} mm, depth "
             f"{out['depth_m'] * 1e3:g} mm ({sc.indenter.shape} tip R = {sc.indenter.radius_m * 1e3:g} mm, "
             f"{sc.indenter.thickness_m * 1e3:g} mm thick); {w['mesh']['dofs']} DOFs",
             f"  force: {f.min():.4g} .. {f.max():.4g} N (max at x = {x[np.argmax(f)] * 1e3:.1f} mm)"]
    if w["max_von_mises_pa"] is not None:
        v = np.asarray(w["max_von_mises_pa"])
        lines.append(f"  max von Mises under the tip: {v.min():.4g} .. {v.max():.4g} Pa "
                     f"(max at x = {x[np.argmax(v)] * 1e3:.1f} mm)")
    if "reference" in out:
        lines.append(ratio_line(out))
    if sc.stones:
        lines.append("  stones at x = " + ", ".join(f"{s.x_m * 1e3:g} mm" for s in sc.stones))
    lines.append(f"  tip: {w['tip_note']}")
    lines.append(f"  time: setup {t['setup_s']:.3f} s, {n} waypoints {t['predict_s']:.3f} s "
                 f"({t['per_waypoint_s'] * 1e3:.2f} ms each)"
                 + (f"; reference setup {t['reference_setup_s']:.3f} s, waypoints {t['reference_predict_s']:.3f} s"
                    if "reference_setup_s" in t else "") + f"; total {t['total_s']:.2f} s")
    lines += [f"  wrote {k}: {v}" for k, v in out["files"].items()]
    print("\n".join(lines), file=stream)
