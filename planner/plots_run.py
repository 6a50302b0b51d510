"""The figure of a run: measured against predicted force along the surface, and the estimate on the section."""
from __future__ import annotations

import math

import numpy as np

from fem import recall


def plot_run(path, prior, loc, meas, *, surrogate=None, truth_stones=(), rounds=None, title: str = "") -> None:
    """Top: measured force (error bars: 2 sigma) and fem's prior prediction; middle: the contrast (measured - prior -
    fitted drift offset) with the fitted stone's contrast; bottom: the section, probes, the estimate and its 1- and
    2-sigma (x, depth) ellipses; true stones dashed when known (simulation only: drawn after the fact)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Ellipse, Rectangle

    W, H = prior.tissue.width_m * 1e3, prior.tissue.height_m * 1e3
    x = meas.x_m * 1e3
    fig, axs = plt.subplots(3, 1, figsize=(8, 10), gridspec_kw={"height_ratios": [1, 1, 1.3]})
    rnd = np.zeros(len(x), int)
    if rounds:
        bounds = np.cumsum([r.n_probes for r in rounds])
        rnd = np.searchsorted(bounds, meas.index - meas.index.min(), side="right")
    colors = plt.cm.viridis(np.linspace(0, 0.85, max(1, rnd.max() + 1)))

    ax = axs[0]
    xx = np.linspace(max(0.0, x.min() - 1), min(W, x.max() + 1), 200)
    for dep in np.unique(np.round(meas.depth_m, 5)):
        f0 = np.array([recall.force_n(prior, v * 1e-3, float(dep)) for v in xx])
        ax.plot(xx, f0 * 1e3, "k-", lw=1, label=f"fem prior (no stone), depth {dep * 1e3:.1f} mm")
        if surrogate is not None and loc.detected:
            c = surrogate.contrast(xx * 1e-3, float(dep), loc.x_m, loc.depth_m, loc.diameter_m)
            ax.plot(xx, (f0 + c) * 1e3, "r-", lw=1, label="fem with the fitted stone")
    for k in range(rnd.max() + 1):
        s = rnd == k
        ax.errorbar(x[s], meas.force_n[s] * 1e3, yerr=2e3 * meas.sigma_n[s], fmt="o", ms=3, color=colors[k],
                    label=f"measured, round {k}")
    ax.set_ylabel("force (mN)")
    ax.legend(fontsize=7)
    ax.set_title(title or "measured and predicted force along the surface", fontsize=9)

    ax = axs[1]
    for k in range(rnd.max() + 1):
        s = rnd == k
        ax.errorbar(x[s], loc.contrast_n[s] * 1e3, yerr=2e3 * meas.sigma_n[s], fmt="o", ms=3, color=colors[k])
    if surrogate is not None and loc.detected:
        for dep in np.unique(np.round(meas.depth_m, 5)):
            c = surrogate.contrast(xx * 1e-3, float(dep), loc.x_m, loc.depth_m, loc.diameter_m)
            ax.plot(xx, c * 1e3, "r-", lw=1, label=f"fitted stone's contrast ({dep * 1e3:.1f} mm)")
    ax.axhline(0, color="k", lw=0.5)
    if math.isfinite(loc.peak_x_m):
        ax.axvline(loc.peak_x_m * 1e3, color="g", ls=":", label=f"sub-waypoint peak {loc.peak_x_m * 1e3:.2f} mm")
    ax.set_ylabel("contrast: measured - prior (mN)")
    ax.legend(fontsize=7)

    ax = axs[2]
    ax.add_patch(Rectangle((0, -H), W, H, fc="#f4d9d0", ec="k"))
    for st in truth_stones:
        ax.add_patch(Circle((st.x_m * 1e3, -st.depth_m * 1e3), st.radius_m * 1e3, fc="none", ec="k", ls="--",
                            label="true stone (simulator)"))
    ax.plot(x, np.zeros_like(x), "v", color="b", ms=4, label=f"probes ({len(x)})")
    if loc.detected:
        ax.add_patch(Circle((loc.x_m * 1e3, -loc.depth_m * 1e3), loc.diameter_m * 500, fc="r", alpha=0.3, ec="r",
                            label=f"estimate ({loc.diameter_m * 1e3:.1f} +- {loc.sigma_diameter_m * 1e3:.1f} mm)"))
        for k, ls in ((1, "-"), (2, ":")):
            ax.add_patch(Ellipse((loc.x_m * 1e3, -loc.depth_m * 1e3), 2 * k * loc.sigma_x_m * 1e3,
                                 2 * k * loc.sigma_depth_m * 1e3, fc="none", ec="r", ls=ls))
        iv = loc.depth_interval_m.get("95")
        if iv:
            ax.plot([loc.x_m * 1e3] * 2, [-iv[0] * 1e3, -iv[1] * 1e3], "-", color="darkred", lw=3, alpha=0.5,
                    label=f"depth 95 % profile interval {iv[0] * 1e3:.1f}-{iv[1] * 1e3:.1f} mm")
        ax.plot(loc.x_m * 1e3, -loc.depth_m * 1e3, "r+", ms=10,
                label=f"centre x {loc.x_m * 1e3:.2f} +- {loc.sigma_x_m * 1e3:.2f}, depth {loc.depth_m * 1e3:.2f} "
                      f"+- {loc.sigma_depth_m * 1e3:.2f} mm (1, 2 sigma)")
    else:
        ax.text(W / 2, -H / 2, f"no stone detected (LR {loc.lr:.1f} < {loc.lr_threshold:g})", ha="center")
    ax.set_xlim(-1, W + 1)
    ax.set_ylim(-H - 1, 3)
    ax.set_aspect("equal")
    ax.set_xlabel("x along the surface (mm)")
    ax.set_ylabel("depth (mm)")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.17), ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
