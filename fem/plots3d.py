"""3D figures (matplotlib, Agg): maps over the top face and a vertical section through a stone.

Imported explicitly (never by fem/__init__.py). Lengths in mm, stresses in Pa.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import matplotlib.tri as mtri
import numpy as np
from matplotlib.patches import Circle
from scipy.interpolate import LinearNDInterpolator

MM = 1e3


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _stones(ax, scene, plane: str = "xy") -> None:
    H = scene.tissue.height_m
    for s in scene.stones:
        if plane == "xy":
            ax.add_patch(Circle((s.x_m * MM, s.y_m * MM), s.radius_m * MM, fill=False, ls="--", color="k", lw=0.8))
        else:
            ax.add_patch(Circle((s.x_m * MM, (H - s.depth_m) * MM), s.radius_m * MM, fill=False, color="k", lw=0.8))


def surface_maps(path, scene, x_m: np.ndarray, y_m: np.ndarray, fields: dict[str, np.ndarray], title: str,
                 peak: tuple[float, float] | None = None) -> Path:
    """Filled contours of nodal values over the top face (scattered nodes, Delaunay), stones dashed."""
    tri = mtri.Triangulation(x_m * MM, y_m * MM)
    fig, axes = plt.subplots(1, len(fields), figsize=(5.2 * len(fields), 4.4), squeeze=False)
    for ax, (k, v) in zip(axes[0], fields.items()):
        cs = ax.tricontourf(tri, v, levels=24, cmap="viridis")
        fig.colorbar(cs, ax=ax, shrink=0.85).set_label(k)
        _stones(ax, scene)
        if peak is not None:
            ax.plot(peak[0] * MM, peak[1] * MM, "r+", ms=12)
        ax.set_aspect("equal")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
    fig.subplots_adjust(wspace=0.4)
    fig.suptitle(title, fontsize=9)
    return _save(fig, path)


def grid_maps(path, scene, xs: np.ndarray, ys: np.ndarray, maps: dict[str, np.ndarray], title: str) -> Path:
    """Maps of values on a waypoint grid (maps[k] of shape (len(ys), len(xs))), stones dashed."""
    fig, axes = plt.subplots(1, len(maps), figsize=(5.0 * len(maps), 4.3), squeeze=False)
    for ax, (k, v) in zip(axes[0], maps.items()):
        pc = ax.pcolormesh(xs * MM, ys * MM, v, shading="nearest", cmap="viridis")
        fig.colorbar(pc, ax=ax, shrink=0.85)
        _stones(ax, scene)
        ax.set_aspect("equal")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title(k, fontsize=9)
    fig.suptitle(title, fontsize=9)
    return _save(fig, path)


def section(path, scene, mesh, values: np.ndarray, y_m: float, label: str, title: str, n: int = 160) -> Path:
    """Nodal values interpolated (linearly, over the nodes' Delaunay tetrahedra) onto the vertical plane y = y_m."""
    X = mesh.nodes
    near = np.abs(X[:, 1] - y_m) <= 0.15 * max(mesh.width_m, mesh.length_m)
    f = LinearNDInterpolator(X[near], values[near])
    xs = np.linspace(0, mesh.width_m, n)
    zs = np.linspace(0, mesh.height_m, max(8, int(n * mesh.height_m / mesh.width_m)))
    XX, ZZ = np.meshgrid(xs, zs)
    V = f(XX, np.full_like(XX, y_m), ZZ)
    fig, ax = plt.subplots(figsize=(7.5, 4.6))
    pc = ax.pcolormesh(xs * MM, zs * MM, V, shading="nearest", cmap="viridis")
    fig.colorbar(pc, ax=ax, shrink=0.85).set_label(label)
    _stones(ax, scene, plane="xz")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_title(title, fontsize=9)
    return _save(fig, path)
