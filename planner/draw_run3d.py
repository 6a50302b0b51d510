"""Drawing a 3D run's figure (fig_run.png) from plain numbers: ``RunFigure3D`` and ``draw_run3d``: the contrast map
over the probed area with the estimate and its uncertainty ellipses, and two sections through the estimate (along x
and along y) with the fitted stone's contrast.

Nothing here asks the localizer's surrogate: ``planner.plots_run3d`` computes the fitted curves, so the drawing can
happen in another process (``app.figchild``). matplotlib is imported inside ``draw_run3d`` only.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

MM = 1e3
SECTION_HALF_WIDTH_M = 1.5e-3      # probes this close to a section's line are drawn on it


@dataclass
class Section3D:
    """One section of the figure: along x (``along`` 0, at y = ``fixed_m``) or along y (1, at x = ``fixed_m``;
    nan: no section line); per indentation level the probes on it and, with a stone fitted, its contrast curve."""
    along: int
    fixed_m: float
    levels_m: list[float] = field(default_factory=list)
    selected: list[np.ndarray] = field(default_factory=list)            # bool masks over the probes
    curve_m: list[np.ndarray | None] = field(default_factory=list)      # positions along the section
    curve_n: list[np.ndarray | None] = field(default_factory=list)      # the fitted stone's contrast there


@dataclass
class RunFigure3D:
    """What the figure shows, in SI units (the drawing converts to mm and mN)."""
    x_m: np.ndarray                 # per probe
    y_m: np.ndarray
    sigma_n: np.ndarray
    contrast_n: np.ndarray
    sections: list[Section3D]
    detected: bool
    x_est_m: float
    y_est_m: float
    diameter_m: float
    cov_xy_m2: np.ndarray
    region_m: tuple | None = None           # (x0, x1, y0, y1) of the probed area
    truth_stones_m: list[tuple[float, float, float]] = field(default_factory=list)   # (x, y, radius)
    title: str = ""


def _ellipse(cov: np.ndarray, k: float, n: int = 100) -> np.ndarray:
    w, v = np.linalg.eigh(cov)
    t = np.linspace(0, 2 * math.pi, n)
    return (v @ (k * np.sqrt(np.maximum(w, 0.0))[:, None] * np.array([np.cos(t), np.sin(t)]))).T


def draw_run3d(path, f: RunFigure3D) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = f.contrast_n
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.8), gridspec_kw={"width_ratios": [1.15, 1, 1]})
    lim = float(np.max(np.abs(c))) * MM or 1.0
    sc = ax[0].scatter(f.x_m * MM, f.y_m * MM, c=c * MM, cmap="RdBu_r", vmin=-lim, vmax=lim, s=28,
                       edgecolors="k", linewidths=0.3)
    fig.colorbar(sc, ax=ax[0], label="contrast: measured - prior (mN)")
    if f.region_m is not None:
        x0, x1, y0, y1 = f.region_m
        ax[0].plot(np.array([x0, x1, x1, x0, x0]) * MM, np.array([y0, y0, y1, y1, y0]) * MM, "k:", lw=0.8,
                   label="probed area")
    for sx, sy, sr in f.truth_stones_m:
        t = np.linspace(0, 2 * math.pi, 100)
        ax[0].plot((sx + sr * np.cos(t)) * MM, (sy + sr * np.sin(t)) * MM, "g-", lw=1.2,
                   label="true stone (simulator)")
    if f.detected and math.isfinite(f.x_est_m):
        for k, ls in ((1.0, "-"), (2.0, "--")):
            e = _ellipse(f.cov_xy_m2, k)
            ax[0].plot((f.x_est_m + e[:, 0]) * MM, (f.y_est_m + e[:, 1]) * MM, "m" + ls, lw=1.2,
                       label=f"{k:g} sigma" if k == 1 else "2 sigma")
        ax[0].plot(f.x_est_m * MM, f.y_est_m * MM, "m+", ms=12, mew=2, label="estimate")
        t = np.linspace(0, 2 * math.pi, 100)
        r = 0.5 * f.diameter_m
        ax[0].plot((f.x_est_m + r * np.cos(t)) * MM, (f.y_est_m + r * np.sin(t)) * MM, "m:", lw=1,
                   label="estimated size")
    ax[0].set_aspect("equal")
    ax[0].set_xlabel("x (mm)")
    ax[0].set_ylabel("y (mm)")
    ax[0].legend(fontsize=7, loc="upper right")
    ax[0].set_title("contrast over the top face")

    for a, s, name in ((ax[1], f.sections[0], "x"), (ax[2], f.sections[1], "y")):
        pos = f.x_m if s.along == 0 else f.y_m
        for j, (lev, sel, sx, model) in enumerate(zip(s.levels_m, s.selected, s.curve_m, s.curve_n)):
            a.errorbar(pos[sel] * MM, c[sel] * MM, yerr=f.sigma_n[sel] * MM, fmt="o", ms=4, capsize=2,
                       color=f"C{j}", label=f"probes {lev * MM:.1f} mm deep, within "
                                            f"{SECTION_HALF_WIDTH_M * MM:g} mm of the section")
            if model is not None:
                a.plot(sx * MM, model * MM, "-", color=f"C{j}", label=f"fitted stone, probes {lev * MM:.1f} mm deep")
        for sx, sy, _ in f.truth_stones_m:
            a.axvline((sx if s.along == 0 else sy) * MM, color="g", lw=0.8, ls="--", label="true centre")
        a.axhline(0, color="k", lw=0.5)
        a.set_xlabel(f"{name} (mm)")
        a.set_ylabel("contrast (mN)")
        other_name = "y" if s.along == 0 else "x"
        a.set_title(f"section along {name} at {other_name} = {s.fixed_m * MM:.1f} mm" if math.isfinite(s.fixed_m)
                    else f"section along {name}")
        a.legend(fontsize=7)
    fig.suptitle(f.title, fontsize=9)
    fig.tight_layout()
    fig.set_layout_engine(None)   # laid out: else savefig draws the whole figure once more first (the same PNG)
    fig.savefig(path, dpi=110)
    plt.close(fig)
