"""Drawing a 2D run's figure (fig_run.png) from plain numbers: ``RunFigure`` and ``draw_run``.

Nothing here asks fem or the localizer: ``planner.plots_run`` computes the curves, so the drawing can happen in
another process (``app.figchild``: a child that imports matplotlib while the run works). matplotlib is imported
inside ``draw_run`` only (a figure is optional: ``--no-figure``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

LEGEND_BELOW_PT = 34.0      # the section panel's legend: its top this far below the axes (past tick labels and x label)


@dataclass
class RunFigure:
    """What the figure shows, in SI units (the drawing converts to mm and mN); per probe arrays in probe order."""
    width_m: float
    height_m: float
    x_m: np.ndarray
    force_n: np.ndarray
    sigma_n: np.ndarray
    contrast_n: np.ndarray           # measured - prior - fitted drift offset
    round_of: np.ndarray             # the round each probe belongs to (int)
    curve_x_mm: np.ndarray           # where the curves are drawn (the figure's own axis, mm)
    # per probed depth: the depth, fem's prior force along curve_x_mm, and with a stone fitted the prior plus its
    # contrast and the contrast alone (None: no stone fitted)
    depths_m: list[float]
    prior_n: list[np.ndarray]
    fitted_n: list[np.ndarray | None]
    fit_contrast_n: list[np.ndarray | None]
    detected: bool
    lr: float
    lr_threshold: float
    peak_x_m: float                  # nan: none
    x_est_m: float = float("nan")
    depth_est_m: float = float("nan")
    diameter_m: float = float("nan")
    sigma_diameter_m: float = float("nan")
    sigma_x_m: float = float("nan")
    sigma_depth_m: float = float("nan")
    depth95_m: tuple[float, float] | None = None
    truth_stones_m: list[tuple[float, float, float]] = field(default_factory=list)   # (x, depth, radius)
    title: str = ""


def draw_run(path, f: RunFigure) -> None:
    """Top: measured force (error bars: 2 sigma) and fem's prior prediction; middle: the contrast with the fitted
    stone's contrast; bottom: the section, probes, the estimate and its 1- and 2-sigma (x, depth) ellipses; true
    stones dashed when known (simulation only: drawn after the fact)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Ellipse, Rectangle
    from matplotlib.transforms import offset_copy

    W, H = f.width_m * 1e3, f.height_m * 1e3
    x, rnd, xx = f.x_m * 1e3, f.round_of, f.curve_x_mm
    fig, axs = plt.subplots(3, 1, figsize=(8, 10), gridspec_kw={"height_ratios": [1, 1, 1.3]})
    colors = plt.cm.viridis(np.linspace(0, 0.85, max(1, rnd.max() + 1)))

    ax = axs[0]
    for dep, f0, fit in zip(f.depths_m, f.prior_n, f.fitted_n):
        ax.plot(xx, f0 * 1e3, "k-", lw=1, label=f"fem prior (no stone) as fitted, depth {dep * 1e3:.2f} mm")
        if fit is not None:
            ax.plot(xx, fit * 1e3, "r-", lw=1, label="fem with the fitted stone")
    for k in range(rnd.max() + 1):
        s = rnd == k
        ax.errorbar(x[s], f.force_n[s] * 1e3, yerr=2e3 * f.sigma_n[s], fmt="o", ms=3, color=colors[k],
                    label=f"measured, round {k}")
    ax.set_ylabel("force (mN)")
    ax.legend(fontsize=7)
    ax.set_title(f.title or "measured and predicted force along the surface", fontsize=9)

    ax = axs[1]
    for k in range(rnd.max() + 1):
        s = rnd == k
        ax.errorbar(x[s], f.contrast_n[s] * 1e3, yerr=2e3 * f.sigma_n[s], fmt="o", ms=3, color=colors[k])
    for dep, c in zip(f.depths_m, f.fit_contrast_n):
        if c is not None:
            ax.plot(xx, c * 1e3, "r-", lw=1, label=f"fitted stone's contrast ({dep * 1e3:.1f} mm)")
    ax.axhline(0, color="k", lw=0.5)
    if math.isfinite(f.peak_x_m):
        ax.axvline(f.peak_x_m * 1e3, color="g", ls=":", label=f"sub-waypoint peak {f.peak_x_m * 1e3:.2f} mm")
    ax.set_ylabel("contrast: measured - prior (mN)")
    ax.legend(fontsize=7)

    ax = axs[2]
    ax.add_patch(Rectangle((0, -H), W, H, fc="#f4d9d0", ec="k"))
    for sx, sd, sr in f.truth_stones_m:
        ax.add_patch(Circle((sx * 1e3, -sd * 1e3), sr * 1e3, fc="none", ec="k", ls="--",
                            label="true stone (simulator)"))
    ax.plot(x, np.zeros_like(x), "v", color="b", ms=4, label=f"probes ({len(x)})")
    if f.detected:
        xe, de = f.x_est_m, f.depth_est_m
        ax.add_patch(Circle((xe * 1e3, -de * 1e3), f.diameter_m * 500, fc="r", alpha=0.3, ec="r",
                            label=f"estimate ({f.diameter_m * 1e3:.1f} +- {f.sigma_diameter_m * 1e3:.1f} mm)"))
        for k, ls in ((1, "-"), (2, ":")):
            ax.add_patch(Ellipse((xe * 1e3, -de * 1e3), 2 * k * f.sigma_x_m * 1e3, 2 * k * f.sigma_depth_m * 1e3,
                                 fc="none", ec="r", ls=ls))
        if f.depth95_m:
            lo, hi = f.depth95_m
            ax.plot([xe * 1e3] * 2, [-lo * 1e3, -hi * 1e3], "-", color="darkred", lw=3, alpha=0.5,
                    label=f"depth 95 % profile interval {lo * 1e3:.1f}-{hi * 1e3:.1f} mm")
        ax.plot(xe * 1e3, -de * 1e3, "r+", ms=10,
                label=f"centre x {xe * 1e3:.2f} +- {f.sigma_x_m * 1e3:.2f}, depth {de * 1e3:.2f} "
                      f"+- {f.sigma_depth_m * 1e3:.2f} mm (1, 2 sigma)")
    else:
        ax.text(W / 2, -H / 2, f"no stone detected (LR {f.lr:.1f} < {f.lr_threshold:g})", ha="center")
    ax.set_xlim(-1, W + 1)
    ax.set_ylim(-H - 1, 3)
    ax.set_aspect("equal")
    ax.set_xlabel("x along the surface (mm)")
    ax.set_ylabel("depth (mm)")
    # below the x label, a fixed distance in points: a fraction of the axes' height (-0.17 before) lands on the label
    # when an equal-aspect section is wide or thin (session 51's review: a 100 x 20 mm section)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=2,
              bbox_transform=offset_copy(ax.transAxes, fig=fig, y=-LEGEND_BELOW_PT, units="points"))
    fig.tight_layout()
    fig.set_layout_engine(None)   # laid out: else savefig draws the whole figure once more first (the same PNG)
    fig.savefig(path, dpi=110)
    plt.close(fig)
