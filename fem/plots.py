"""Figures (matplotlib, Agg backend): contour plots of nodal fields over the section, top-surface graphs, and
several scenes' surface profiles on one axes.

The functions are generic: they take a mesh, nodal values, stone outlines ``(x_m, y_m, r_m)`` and profiles, not a
particular load case, so the indentation figures can reuse them. Lengths are drawn in mm, stresses in Pa.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from pathlib import Path

import matplotlib  # heavy: fem.plots is imported explicitly, never by fem/__init__.py

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import matplotlib.tri as mtri
import numpy as np
from matplotlib.colors import TwoSlopeNorm
from matplotlib.patches import Circle, Rectangle

from .mesh import Mesh

MM = 1e3
# P2 triangle -> 4 linear sub-triangles (gmsh order: vertices 0 1 2, mid-edge 3 = 01, 4 = 12, 5 = 20)
_P2_SPLIT = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])

LABELS = {
    "sxx_pa": r"$\sigma_{xx}$ (Pa)", "syy_pa": r"$\sigma_{yy}$ (Pa)", "sxy_pa": r"$\sigma_{xy}$ (Pa)",
    "szz_pa": r"$\sigma_{zz}$ (Pa)", "von_mises_pa": "von Mises (Pa)",
    "exx": r"$\varepsilon_{xx}$", "eyy": r"$\varepsilon_{yy}$", "gxy": r"$\gamma_{xy}$",
    "ux_m": r"$u_x$ (mm)", "uy_m": r"$u_y$ (mm)",
}


def outlines_of(scene) -> list[tuple[float, float, float]]:
    """Stone outlines (x_m, y_centre_m, r_m) of a fem.scene.Scene."""
    H = scene.tissue.height_m
    return [(s.x_m, H - s.depth_m, s.radius_m) for s in scene.stones]


def triangulation(mesh: Mesh, hide_regions: Iterable[int] = ()) -> mtri.Triangulation:
    """Linear triangulation (coordinates in mm) of a P1/P2 mesh; elements of ``hide_regions`` are masked."""
    if mesh.order == 1:
        tris, parent = mesh.tris, np.arange(len(mesh.tris))
    else:
        tris = mesh.tris[:, _P2_SPLIT].reshape(-1, 3)
        parent = np.repeat(np.arange(len(mesh.tris)), len(_P2_SPLIT))
    tri = mtri.Triangulation(mesh.nodes[:, 0] * MM, mesh.nodes[:, 1] * MM, tris)
    hide = list(hide_regions)
    if hide:
        tri.set_mask(np.isin(mesh.region[parent], hide))
    return tri


def _levels(values: np.ndarray, n: int, robust: float):
    lo, hi = np.percentile(values, [robust, 100 - robust]) if robust > 0 else (values.min(), values.max())
    if hi - lo <= 1e-12 * max(abs(lo), abs(hi), 1e-300):
        lo, hi = lo - 0.5 * max(abs(lo), 1.0), hi + 0.5 * max(abs(hi), 1.0)
    norm = TwoSlopeNorm(0.0, lo, hi) if lo < 0 < hi else None
    return np.linspace(lo, hi, n + 1), norm


def contour(ax, mesh: Mesh, values: np.ndarray, *, outlines: Sequence[tuple[float, float, float]] = (),
            hide_regions: Iterable[int] | None = None, title: str | None = None, label: str | None = None,
            levels: int = 24, robust: float = 0.5, cmap: str | None = None, scale: float = 1.0):
    """Filled contours of nodal ``values`` (times ``scale``) on ``ax``; stones (region >= 1 by default) are masked
    and drawn grey with their outlines. The colour range spans the ``robust``..``100-robust`` percentiles of the
    shown nodes (the stone's rim concentrates stress); values outside are marked by the colour bar's arrows."""
    values = np.asarray(values, dtype=float) * scale
    if hide_regions is None:
        hide_regions = [r for r in np.unique(mesh.region) if r >= 1]
    tri = triangulation(mesh, hide_regions)
    shown = np.unique(tri.get_masked_triangles())
    lv, norm = _levels(values[shown], levels, robust)
    if cmap is None:
        cmap = "RdBu_r" if norm is not None else ("viridis" if lv[0] >= 0 else "viridis_r")
    cs = ax.tricontourf(tri, values, levels=lv, cmap=cmap, norm=norm, extend="both")
    for x, y, r in outlines:
        ax.add_patch(Circle((x * MM, y * MM), r * MM, facecolor="0.8", edgecolor="k", lw=0.8, zorder=3))
    ax.set_aspect("equal")
    ax.set_xlim(0, mesh.width_m * MM)
    ax.set_ylim(0, mesh.height_m * MM)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    if title:
        ax.set_title(title, fontsize=10)
    cb = ax.figure.colorbar(cs, ax=ax, shrink=0.85)
    cb.set_label(label or "")
    cb.ax.tick_params(labelsize=8)
    return cs


def field_panels(path: str | Path, mesh: Mesh, fields: dict[str, np.ndarray], *,
                 outlines: Sequence[tuple[float, float, float]] = (), suptitle: str = "", ncols: int = 2,
                 scales: dict[str, float] | None = None) -> Path:
    """One contour panel per entry of ``fields`` (key -> nodal values; LABELS gives the colour-bar label)."""
    scales = scales or {}
    n = len(fields)
    nrows = -(-n // ncols)
    w = mesh.width_m / mesh.height_m
    fig, axes = plt.subplots(nrows, ncols, figsize=(ncols * (3.2 * w + 1.4), nrows * 3.4), squeeze=False)
    for ax, (key, v) in zip(axes.flat, fields.items()):
        lab = LABELS.get(key, key)
        contour(ax, mesh, v, outlines=outlines, title=lab, label=lab, scale=scales.get(key, 1.0))
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    if suptitle:
        fig.suptitle(suptitle, fontsize=11)
    fig.tight_layout()
    return _save(fig, path)


def surface_graph(path: str | Path, profile, *, keys: Sequence[str] = ("sxx_pa", "syy_pa", "sxy_pa",
                                                                          "von_mises_pa"),
                  stones_x: Sequence[float] = (), title: str = "") -> Path:
    """Stresses along the top surface against x (the study's Fig 5); dotted verticals at the stones' x."""
    fig, ax = plt.subplots(figsize=(9.5, 4))
    x = np.asarray(profile.x_m) * MM
    for k in keys:
        ax.plot(x, profile.fields[k], lw=1.6 if k == "von_mises_pa" else 1.1, label=LABELS.get(k, k))
    xp, vp = profile.peak()
    ax.plot([xp * MM], [vp], "k^", ms=6, label=f"peak {vp:.1f} Pa at x = {xp * MM:.2f} mm")
    for xs in stones_x:
        ax.axvline(xs * MM, color="0.5", ls=":", lw=1)
    ax.axhline(0, color="0.7", lw=0.6)
    ax.set_xlim(x.min(), x.max())
    return _finish_surface_axes(fig, ax, path, "stress (Pa)", title)


def compare_profiles(path: str | Path, curves: Sequence[tuple[str, object, Sequence[float]]], *,
                     key: str = "von_mises_pa", title: str = "") -> Path:
    """Several scenes' surface profiles on one axes: ``curves`` = [(label, profile, stones_x), ...]. Each curve's
    peak is marked and each stone's x drawn as a short tick of the curve's colour."""
    fig, ax = plt.subplots(figsize=(9.5, 4.2))
    for label, prof, stones_x in curves:
        x = np.asarray(prof.x_m) * MM
        (line,) = ax.plot(x, prof.fields[key], lw=1.4, ls="--" if not len(stones_x) else "-")
        xp, vp = prof.peak(key)
        if len(stones_x):
            ax.plot([xp * MM], [vp], marker="^", color=line.get_color(), ms=6)
            line.set_label(f"{label}: peak {vp:.1f} Pa at {xp * MM:.1f} mm")
        else:
            line.set_label(f"{label}: no stone")
        for xs in stones_x:
            ax.axvline(xs * MM, color=line.get_color(), ls=":", lw=0.9)
    return _finish_surface_axes(fig, ax, path, LABELS.get(key, key), title)


def _finish_surface_axes(fig, ax, path, ylabel: str, title: str) -> Path:
    """Labels, grid, the legend outside the axes, title; then save."""
    ax.set_xlabel("x along the top surface (mm)")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    if title:
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return path


# ------------------------------------------------------------------------------------------- indentation (load B)

def deformed(mesh: Mesh, u: np.ndarray, scale: float = 1.0) -> Mesh:
    """A copy of ``mesh`` with its nodes moved by ``scale`` times the interleaved displacement ``u`` (2N,)."""
    return dataclasses.replace(mesh, nodes=mesh.nodes + scale * np.asarray(u, float).reshape(-1, 2))


def draw_tip(ax, indenter, x_m: float, bottom_y_m: float, **style) -> None:
    """The probe tip's outline (mm) with its lowest point at (x_m, bottom_y_m): a circle of radius_m for a
    cylinder, a rectangle of half-width radius_m for a flat punch."""
    kw = {"facecolor": "none", "edgecolor": "k", "lw": 1.2, "ls": "-", "zorder": 4}
    kw.update(style)
    R = indenter.radius_m
    if indenter.shape == "cylinder":
        ax.add_patch(Circle((x_m * MM, (bottom_y_m + R) * MM), R * MM, **kw))
    else:
        ax.add_patch(Rectangle(((x_m - R) * MM, bottom_y_m * MM), 2 * R * MM, 1.5 * R * MM, **kw))


def indent_panels(path: str | Path, mesh: Mesh, fields: dict[str, np.ndarray], *, indenter, x_m: float,
                  tip_bottom_y_m: float, outlines: Sequence[tuple[float, float, float]] = (),
                  zoom_m: tuple[float, float, float, float] | None = None, overview: str | None = "von_mises_pa",
                  mark_m: tuple[float, float] | None = None, suptitle: str = "") -> Path:
    """Contours under an indenting tip (the study's Fig 10): an optional whole-section panel of ``overview``,
    then one panel per entry of ``fields`` zoomed to ``zoom_m`` = (x_lo, x_hi, y_lo, y_hi) (m). ``mesh`` may be
    the deformed mesh (see ``deformed``); the tip outline is drawn at its final position in every panel, and
    ``mark_m`` = (x, y) (m), e.g. the maximum von Mises point, as a white cross on the von Mises panels."""
    panels = ([("overview", overview)] if overview else []) + [("zoom", k) for k in fields]
    ncols = 2
    nrows = -(-len(panels) // ncols)
    w = mesh.width_m / mesh.height_m
    fig, axes = plt.subplots(nrows, ncols, figsize=(ncols * (3.2 * w + 1.4), nrows * 3.4), squeeze=False)
    for ax, (kind, key) in zip(axes.flat, panels):
        lab = LABELS.get(key, key)
        contour(ax, mesh, fields[key], outlines=outlines, title=lab + (" (whole section)" if kind == "overview"
                                                                       else " (under the tip)"), label=lab)
        draw_tip(ax, indenter, x_m, tip_bottom_y_m)
        if mark_m is not None and key == "von_mises_pa":
            ax.plot([mark_m[0] * MM], [mark_m[1] * MM], "wx", ms=7, mew=1.5, zorder=5)
        top = mesh.height_m * MM + 2 * indenter.radius_m * MM
        if kind == "zoom" and zoom_m is not None:
            ax.set_xlim(zoom_m[0] * MM, zoom_m[1] * MM)
            ax.set_ylim(zoom_m[2] * MM, zoom_m[3] * MM)
        else:
            ax.set_ylim(0, top)
    for ax in list(axes.flat)[len(panels):]:
        ax.set_visible(False)
    if suptitle:
        fig.suptitle(suptitle, fontsize=11)
    fig.tight_layout()
    return _save(fig, path)


def predict_graph(path: str | Path, x_m: np.ndarray, scene: dict[str, np.ndarray], reference: dict[str, np.ndarray],
                  *, labels: tuple[str, str] = ("stone", "healthy"), stones: Sequence[tuple[float, float]] = (),
                  title: str = "", peak: tuple[float, float] | None = None) -> Path:
    """Force and maximum von Mises stress against tip position for a scene and its reference (the study's Fig 11),
    and below their ratios. ``scene``/``reference``: {"force_n": ..., "max_von_mises_pa": ...}; ``stones``:
    (x_m, diameter_m) of the scene's stones, marked as shaded bands; ``peak``: (x_m, ratio) of the force ratio's
    peak as the JSON reports it (a sub-waypoint fit: marked there, the figure and the file then agree; without it,
    the largest sample)."""
    x = np.asarray(x_m) * MM
    fig, (ax, axr) = plt.subplots(2, 1, figsize=(9.5, 7.0), sharex=True, gridspec_kw={"height_ratios": [3, 2]})
    ax2 = ax.twinx()
    cf, cs = "tab:blue", "tab:red"
    ax.plot(x, scene["force_n"], "-", color=cf, lw=1.6, label=f"force, {labels[0]}")
    ax.plot(x, reference["force_n"], "--", color=cf, lw=1.3, label=f"force, {labels[1]}")
    ax2.plot(x, scene["max_von_mises_pa"], "-", color=cs, lw=1.6, label=f"max von Mises, {labels[0]}")
    ax2.plot(x, reference["max_von_mises_pa"], "--", color=cs, lw=1.3, label=f"max von Mises, {labels[1]}")
    ax.set_ylabel("tip force (N)", color=cf)
    ax2.set_ylabel("max von Mises under the tip (Pa)", color=cs)
    ax.tick_params(axis="y", colors=cf)
    ax2.tick_params(axis="y", colors=cs)
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=8, loc="lower center", ncol=2)
    ax.grid(alpha=0.3)
    rf = np.asarray(scene["force_n"]) / np.asarray(reference["force_n"])
    rs = np.asarray(scene["max_von_mises_pa"]) / np.asarray(reference["max_von_mises_pa"])
    axr.plot(x, rf, "-", color=cf, lw=1.6, label="force ratio")
    axr.plot(x, rs, "-", color=cs, lw=1.3, label="max von Mises ratio")
    i = int(np.argmax(rf))
    xp, rp = (peak[0] * MM, peak[1]) if peak is not None else (x[i], rf[i])
    axr.plot([xp], [rp], "k^", ms=6, label=f"peak force ratio {rp:.4f} at x = {xp:.1f} mm")
    axr.axhline(1.0, color="0.6", lw=0.8)
    axr.set_ylabel(f"{labels[0]} / {labels[1]}")
    axr.set_xlabel("tip position x along the top surface (mm)")
    axr.grid(alpha=0.3)
    axr.legend(fontsize=8, loc="upper left")
    for a in (ax, axr):
        for xs, d in stones:
            a.axvspan((xs - d / 2) * MM, (xs + d / 2) * MM, color="0.85", zorder=0)
            a.axvline(xs * MM, color="0.4", ls=":", lw=1)
    axr.set_xlim(x.min(), x.max())
    if title:
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path)
