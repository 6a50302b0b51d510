"""Figures of a plan (matplotlib, Agg): the raster over the section with the predicted force (a 3D block: the area
raster from above, in probing order), and the joint trajectories over the planned time."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

JOINTS = ("base", "shoulder", "elbow", "wrist 1", "wrist 2", "wrist 3")


def plot_raster(plan, path) -> Path:
    """Section (mm) with every probe drawn to its planned depth, coloured by predicted force; below, depth and
    predicted force against x."""
    t = plan.scene["tissue"]
    w, h = t["width_m"] * 1e3, t["height_m"] * 1e3
    x = np.array([p.x_m for p in plan.probes]) * 1e3
    d = np.array([p.depth_m for p in plan.probes]) * 1e3
    f = np.array([p.predicted_force_n for p in plan.probes])
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(7, 6.5), gridspec_kw={"height_ratios": [3, 2]})
    ax.add_patch(plt.Rectangle((0, 0), w, h, fc="#f3d9d0", ec="k", lw=1))
    cmap = plt.get_cmap("viridis")
    fmax = max(float(np.nanmax(f)) if f.size else 1.0, 1e-12)
    a = plan.motion.approach_height_m * 1e3
    for xi, di, fi in zip(x, d, f):
        c = cmap(fi / fmax) if np.isfinite(fi) else "grey"
        ax.plot([xi, xi], [h + a, h - di], color=c, lw=2)
        ax.plot(xi, h - di, "v", color=c, ms=5)
    ax.axhline(h - plan.limits.depth_limit_m * 1e3, color="r", ls=":", lw=1, label="depth limit")
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, fmax))
    fig.colorbar(sm, ax=ax, label="predicted force on the prior tissue [N]")
    ax.set(xlim=(-2, w + 2), ylim=(0, h + a + 3), aspect="equal", xlabel="x [mm]", ylabel="y [mm]",
           title=f"{plan.scene['name']}: {len(x)} probes (approach height {a:.0f} mm -> planned depth)")
    ax.legend(loc="lower right", fontsize=8)
    ax2.plot(x, d, "o-", color="C0", label="depth")
    ax2.set(xlabel="x [mm]", ylabel="depth [mm]", xlim=(-2, w + 2))
    ax2.set_ylim(0, max(plan.limits.depth_limit_m * 1e3, float(d.max(initial=0))) * 1.1)
    ax3 = ax2.twinx()
    ax3.plot(x, f, "s--", color="C1", label="predicted force")
    ax3.axhline(plan.limits.force_limit_n, color="r", ls=":", lw=1)
    ax3.set_ylabel("force [N] (red: limit)")
    ax3.set_ylim(0, plan.limits.force_limit_n * 1.1)
    ax2.legend(loc="lower left", fontsize=8)
    ax3.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def joint_timeline(plan):
    """(t, q) samples at the end of every move: arrive at approach, at depth, end of dwell, back at approach."""
    tm = plan.notes.get("timing", {})
    ts, qs = [], []
    for k, p in enumerate(plan.probes):
        t0 = p.t_start_s + (tm["move_in_s"][k] + tm.get("zero_s", [0.0] * (k + 1))[k] if tm else 0.0)
        t1 = t0 + (tm["descend_s"][k] if tm else 0.0)
        t2 = t1 + (tm["dwell_s"][k] if tm else 0.0)
        t3 = p.t_start_s + p.duration_s
        ts += [t0, t1, t2, t3]
        qs += [p.q_approach_rad, p.q_indent_rad, p.q_indent_rad, p.q_approach_rad]
    return np.array(ts), np.array(qs).reshape(-1, 6)


def plot_joints(plan, path) -> Path:
    t, q = joint_timeline(plan)
    fig, axes = plt.subplots(6, 1, figsize=(7, 8), sharex=True)
    for j, ax in enumerate(axes):
        ax.plot(t, np.degrees(q[:, j]), "-", lw=1)
        ax.set_ylabel(f"{JOINTS[j]}\n[deg]", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].set_title(f"joint targets over the plan ({len(plan.probes)} probes, {plan.total_time_s:.1f} s)")
    axes[-1].set_xlabel("planned time [s]")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_area(plan, path) -> Path:
    """A 3D plan from above (tissue frame, mm): the block's top face, fem's probed patch, the raster's region and
    the waypoints in probing order (the path between them, start and end marked), coloured by predicted force
    (left) and by planned depth (right)."""
    sc = plan.scene
    t, R = sc["tissue"], sc.get("indenter", {}).get("radius_m", 0.005) * 1e3
    w, L = t["width_m"] * 1e3, t["length_m"] * 1e3
    patch = sc.get("analysis", {}).get("patch_m")
    x = np.array([p.x_m for p in plan.probes]) * 1e3
    y = np.array([p.y_m for p in plan.probes]) * 1e3
    d = np.array([p.depth_m for p in plan.probes]) * 1e3
    f = np.array([p.predicted_force_n for p in plan.probes])
    r = plan.notes.get("raster", {})
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.6))
    for ax, val, label, cmap, lim in ((axes[0], f, "predicted force on the prior tissue [N] (scale: 0 to the limit)",
                                       "viridis", (0.0, plan.limits.force_limit_n)),
                                      (axes[1], d, "planned depth [mm]", "magma", (None, None))):
        ax.add_patch(plt.Rectangle((0, 0), w, L, fc="#f3d9d0", ec="k", lw=1, label="top face"))
        if patch:
            p = patch * 1e3
            ax.add_patch(plt.Rectangle((0.5 * (w - p), 0.5 * (L - p)), p, p, fc="none", ec="0.3", ls="--", lw=1,
                                       label="probed patch (fem)"))
            ax.add_patch(plt.Rectangle((0.5 * (w - p) + R, 0.5 * (L - p) + R), p - 2 * R, p - 2 * R, fc="none",
                                       ec="0.5", ls=":", lw=1, label="tip centre allowed"))
        if r.get("region_m"):
            v = np.array(r["region_m"]) * 1e3
            ax.add_patch(plt.Polygon(v, closed=True, fc="none", ec="C3", lw=1.2, label="region"))
        ax.plot(x, y, "-", color="0.35", lw=0.7, zorder=2)
        sc_ = ax.scatter(x, y, c=val, cmap=cmap, s=max(8.0, 1600.0 / max(len(x), 1)), zorder=3, edgecolors="none",
                         vmin=lim[0], vmax=lim[1])
        ax.plot(x[0], y[0], "o", mfc="none", mec="g", ms=11, mew=2, zorder=4, label="first probe")
        ax.plot(x[-1], y[-1], "s", mfc="none", mec="k", ms=11, mew=2, zorder=4, label="last probe")
        if len(x) > 1:
            ax.annotate("", xy=(x[1], y[1]), xytext=(x[0], y[0]), zorder=5,
                        arrowprops=dict(arrowstyle="->", color="g", lw=1.5))
        fig.colorbar(sc_, ax=ax, label=label, shrink=0.85)
        ax.set(xlim=(-2, w + 2), ylim=(-2, L + 2), aspect="equal", xlabel="x [mm] (tissue frame)",
               ylabel="y [mm]")
    axes[0].legend(loc="upper left", fontsize=7, framealpha=0.85)
    order = r.get("order", "as given")
    travel = f", travel {r['travel_m'] * 1e3:.0f} mm" if "travel_m" in r else ""
    fig.suptitle(f"{sc['name']}: {len(x)} probes, order {order}{travel}, force limit "
                 f"{plan.limits.force_limit_n:g} N, depth limit {plan.limits.depth_limit_m * 1e3:g} mm; "
                 f"execution ~{plan.total_time_s:.0f} s", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_plan(plan, out_dir) -> list[Path]:
    """The plan's figures: a 2D section's raster or a 3D block's area raster, and the joint targets over time."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if plan.scene.get("tissue", {}).get("length_m") is not None:
        return [plot_area(plan, out / "plan_area.png"), plot_joints(plan, out / "plan_joints.png")]
    return [plot_raster(plan, out / "plan_raster.png"), plot_joints(plan, out / "plan_joints.png")]
