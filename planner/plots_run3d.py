"""The figure of a 3D run (fig_run.png): the contrast map over the probed area with the estimate and its uncertainty
ellipses, and two sections through the estimate (along x and along y) with the fitted stone's contrast.

matplotlib is imported here only (a figure is optional: ``--no-figure``).
"""
from __future__ import annotations

import math

import numpy as np

MM = 1e3
SECTION_HALF_WIDTH_M = 1.5e-3      # probes this close to a section's line are drawn on it


def _ellipse(cov: np.ndarray, k: float, n: int = 100) -> np.ndarray:
    w, v = np.linalg.eigh(cov)
    t = np.linspace(0, 2 * math.pi, n)
    return (v @ (k * np.sqrt(np.maximum(w, 0.0))[:, None] * np.array([np.cos(t), np.sin(t)]))).T


def plot_run3d(path, prior, loc, meas, *, surrogate, truth_stones=(), region=None, title: str = "") -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = loc.contrast_n if loc.contrast_n is not None else np.zeros(len(meas))
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.8), gridspec_kw={"width_ratios": [1.15, 1, 1]})
    lim = float(np.max(np.abs(c))) * MM or 1.0
    sc = ax[0].scatter(meas.x_m * MM, meas.y_m * MM, c=c * MM, cmap="RdBu_r", vmin=-lim, vmax=lim, s=28,
                       edgecolors="k", linewidths=0.3)
    fig.colorbar(sc, ax=ax[0], label="contrast: measured - prior (mN)")
    if region is not None:
        x0, x1, y0, y1 = region
        ax[0].plot(np.array([x0, x1, x1, x0, x0]) * MM, np.array([y0, y0, y1, y1, y0]) * MM, "k:", lw=0.8,
                   label="probed area")
    for s in truth_stones:
        t = np.linspace(0, 2 * math.pi, 100)
        ax[0].plot((s.x_m + s.radius_m * np.cos(t)) * MM, (s.y_m + s.radius_m * np.sin(t)) * MM, "g-", lw=1.2,
                   label="true stone (simulator)")
    if loc.detected and math.isfinite(loc.x_m):
        cov = loc.cov_xy_m2()
        for k, ls in ((1.0, "-"), (2.0, "--")):
            e = _ellipse(cov, k)
            ax[0].plot((loc.x_m + e[:, 0]) * MM, (loc.y_m + e[:, 1]) * MM, "m" + ls, lw=1.2,
                       label=f"{k:g} sigma" if k == 1 else "2 sigma")
        ax[0].plot(loc.x_m * MM, loc.y_m * MM, "m+", ms=12, mew=2, label="estimate")
        t = np.linspace(0, 2 * math.pi, 100)
        r = 0.5 * loc.diameter_m
        ax[0].plot((loc.x_m + r * np.cos(t)) * MM, (loc.y_m + r * np.sin(t)) * MM, "m:", lw=1, label="estimated size")
    ax[0].set_aspect("equal")
    ax[0].set_xlabel("x (mm)")
    ax[0].set_ylabel("y (mm)")
    ax[0].legend(fontsize=7, loc="upper right")
    ax[0].set_title("contrast over the top face")

    cx = loc.x_m if loc.detected else loc.peak_x_m
    cy = loc.y_m if loc.detected else loc.peak_y_m
    k_scale = loc.nuisance.get("stiffness_scale", (1.0, 0.0))[0] if loc.nuisance else 1.0
    for a, along, fixed, name in ((ax[1], 0, cy, "x"), (ax[2], 1, cx, "y")):
        pos = meas.x_m if along == 0 else meas.y_m
        other = meas.y_m if along == 0 else meas.x_m
        if math.isfinite(fixed):
            near = np.abs(other - fixed) <= SECTION_HALF_WIDTH_M
            levels = np.unique(np.round(meas.depth_m[near], 4))
            for j, lev in enumerate(levels[::-1]):       # one colour per indentation (the coarse grid has two)
                sel = near & (np.abs(meas.depth_m - lev) <= 5e-5)
                a.errorbar(pos[sel] * MM, c[sel] * MM, yerr=meas.sigma_n[sel] * MM, fmt="o", ms=4, capsize=2,
                           color=f"C{j}", label=f"probes {lev * MM:.1f} mm deep, within "
                                                f"{SECTION_HALF_WIDTH_M * MM:g} mm of the section")
                if loc.detected:
                    if region is not None:
                        lo, hi = (region[0], region[1]) if along == 0 else (region[2], region[3])
                    else:
                        lo, hi = pos.min(), pos.max()
                    sx = np.linspace(lo, hi, 200)
                    xs = sx if along == 0 else np.full(len(sx), fixed)
                    ys = np.full(len(sx), fixed) if along == 0 else sx
                    dd = np.full(len(sx), float(np.clip(lev, surrogate.levels[0], surrogate.levels[-1])))
                    model = k_scale * surrogate.contrast(xs, ys, dd, loc.x_m, loc.y_m, loc.depth_m, loc.diameter_m)
                    a.plot(sx * MM, model * MM, "-", color=f"C{j}", label=f"fitted stone at {lev * MM:.1f} mm")
        for st in truth_stones:
            a.axvline((st.x_m if along == 0 else st.y_m) * MM, color="g", lw=0.8, ls="--", label="true centre")
        a.axhline(0, color="k", lw=0.5)
        a.set_xlabel(f"{name} (mm)")
        a.set_ylabel("contrast (mN)")
        other_name = "y" if along == 0 else "x"
        a.set_title(f"section along {name} at {other_name} = {fixed * MM:.1f} mm" if math.isfinite(fixed)
                    else f"section along {name}")
        a.legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
