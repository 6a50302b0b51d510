"""The accuracy study's figure (matplotlib, imported when drawn)."""
from __future__ import annotations

import numpy as np

from planner.accuracy import DENSE, PEAK_ONLY, errors_by_seed


def figure(rows, path, sensor):
    import matplotlib
    import matplotlib.ticker
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axs = plt.subplots(2, 2, figsize=(11, 8))
    ad = [r for r in rows if r["method"] == "adaptive-design" and "err_x_m" in r and r["sensor"] == sensor]
    det = [r for r in ad if r["detected"]]
    ax = axs[0, 0]
    bins = np.linspace(0, 2, 41)
    ax.hist(np.clip(np.abs([r["err_x_m"] * 1e3 for r in det]), 0, 1.99), bins=bins, alpha=0.6,
            label="lateral |error|")
    ax.hist(np.clip(np.abs([r["err_depth_m"] * 1e3 for r in det]), 0, 1.99), bins=bins, alpha=0.6,
            label="depth |error| (> 2 mm in the last bin)")
    ax.axvline(0.5, color="C0", ls="--")
    ax.axvline(1.0, color="C1", ls="--")
    ax.set_xlabel("|error| (mm), adaptive, detected stones")
    ax.legend()
    ax = axs[0, 1]
    ax.scatter([r["depth_m"] * 1e3 for r in ad], [r["diam_m"] * 1e3 for r in ad],
               c=["g" if r["detected"] else "r" for r in ad], s=15)
    ax.set_xlabel("true depth of centre (mm)")
    ax.set_ylabel("true diameter (mm)")
    ax.set_title("adaptive: detected (green) / missed (red)")
    ax = axs[1, 0]
    for key, lab in (("err_x_m", "lateral (fem fit)"), ("err_depth_m", "depth (fem fit)"),
                     ("err_peak_m", "lateral (3-point peak)"), ("err_peakfit_m", "lateral (peak fit)")):
        ns, med = [], []
        for N in DENSE + PEAK_ONLY:
            e = errors_by_seed(rows, sensor, f"dense-{N}" if N in DENSE else f"peak-{N}", key)
            if e:
                ns.append(N)
                med.append(np.median(list(e.values())) * 1e3)
        ax.loglog(ns, med, "o-", ms=4, label=f"even raster, {lab}")
    for strategy, mk in (("design", "*-"), ("raster", "s--")):
        for key, lab, c in (("err_x_m", "lateral", "C0"), ("err_depth_m", "depth", "C1")):
            ns, med = [], []
            for n in (15, 25, 35, 45):
                R = [abs(r[key]) for r in rows if r["method"] == f"round-{strategy}@{n}" and "err_x_m" in r
                     and r["detected"] and r["sensor"] == sensor]
                if R:
                    ns.append(n)
                    med.append(np.median(R) * 1e3)
            ax.loglog(ns, med, mk, color=c, ms=9 if mk[0] == "*" else 5, label=f"adaptive-{strategy}, {lab}")
    ax.set_xticks([15, 25, 35, 45, 57, 81, 113, 161, 241])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax.set_xlabel("probes")
    ax.set_ylabel("median |error| (mm), detected stones")
    ax.set_ylim(0.02, 4)
    ax.legend(fontsize=6, loc="upper center", ncol=2)
    ax.grid(True, which="both", alpha=0.3)
    ax = axs[1, 1]
    ax.scatter([r["sigma_x_m"] * 1e3 for r in det], np.abs([r["err_x_m"] * 1e3 for r in det]), s=10, label="x")
    ax.scatter([r["sigma_depth_m"] * 1e3 for r in det], np.abs([r["err_depth_m"] * 1e3 for r in det]), s=10,
               label="depth")
    lim = [1e-2, 10]
    ax.loglog(lim, lim, "k--", lw=0.8, label="|error| = sigma")
    ax.set_xlabel("reported 1-sigma (mm)")
    ax.set_ylabel("|error| (mm)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def detect_figure(rows, path) -> None:
    """Predicted against Monte-Carlo detection rate (with 1 standard error), one point per stone."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5.5, 5))
    pred = np.array([r["predicted"] for r in rows])
    rate = np.array([r["rate"] for r in rows])
    ax.errorbar(pred, rate, yerr=[r["se"] for r in rows], fmt="o", capsize=3)
    for r in rows:
        ax.annotate(f"{r['diameter_m'] * 1e3:g} mm @ {r['depth_m'] * 1e3:g} mm", (r["predicted"], r["rate"]),
                    fontsize=7, xytext=(4, -10), textcoords="offset points")
    ax.plot([0, 1], [0, 1], "k--", lw=0.8)
    ax.set_xlim(-0.03, 1.03)
    ax.set_ylim(-0.03, 1.03)
    ax.set_xlabel("predicted detection rate (planner.detectability)")
    ax.set_ylabel("Monte-Carlo detection rate")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
