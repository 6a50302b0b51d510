"""The 3D loop on blocks thicker and thinner than the prior believes (docs/loop3d.md, docs/localize.md "The block's
thickness in 3D").

    python bench/thickness3d.py --out bench-out/thickness3d [--seeds 0 1 2] [--code DIR --label before]
                                [--label measured-1mm --extra "--thickness-sigma-m 0.001"]

Each truth is block3d's prior (70 x 70 x 50 mm, 2500 Pa, its own mesh) with its height scaled, its modulus
possibly changed, and a stone or none; each is run as a user would, `palpate run TRUTH.toml --prior block3d --sim
--seed S` (84-probe budget, nano17, the figure left out), and its result.json read back. ``--code DIR`` runs another
checkout of palpate instead of this one (``PYTHONPATH=DIR``; the same truths, seeds and cache), labelled
``--label``: the before/after table in one sitting; ``--extra`` adds options to every run (e.g. the thickness's
prior). Runs already in OUT are read, not repeated (resumable); every
row goes to OUT/thickness3d.jsonl and the table to OUT/thickness3d.md.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fem import scene as S  # noqa: E402

# (tag, height factor, modulus (Pa), stone (x, y, depth, diameter) in m or None)
TRUTHS = [
    ("healthy-h0.80-E3000", 0.80, 3000.0, None),
    ("healthy-h0.90-E3000", 0.90, 3000.0, None),
    ("healthy-h0.94", 0.94, 2500.0, None),
    ("healthy-h1.00", 1.00, 2500.0, None),
    ("healthy-h1.06", 1.06, 2500.0, None),
    ("healthy-h1.16", 1.16, 2500.0, None),
    ("stone12-d18-h0.84", 0.84, 2500.0, (0.035, 0.035, 0.018, 0.012)),
    ("paper-h0.92", 0.92, 2500.0, (0.035, 0.035, 0.025, 0.015)),
    ("paper-h1.00", 1.00, 2500.0, (0.035, 0.035, 0.025, 0.015)),
    ("stone12-d20-h1.16", 1.16, 2500.0, (0.030, 0.036, 0.020, 0.012)),
]


def truth_scene(tag: str, factor: float, youngs_pa: float, stone) -> S.Scene:
    prior = S.load("block3d").prior()
    t = prior.tissue
    sc = dataclasses.replace(prior, name=tag, tissue=dataclasses.replace(t, height_m=t.height_m * factor,
                                                                         youngs_pa=youngs_pa))
    if stone is not None:
        x, y, dep, D = stone
        sc = sc.with_stones([S.Stone(x_m=x, y_m=y, depth_m=dep, diameter_m=D)])
    return sc


def run_one(out: Path, tag: str, seed: int, code: Path | None, label: str, extra: list[str]) -> dict:
    run_dir = out / "runs" / f"{label}-{tag}-s{seed}"
    res = run_dir / "result.json"
    wall = None
    if not res.exists():
        env = dict(os.environ)
        if code is not None:
            env["PYTHONPATH"] = str(code)
        cmd = [sys.executable, "-c", "import sys; sys.argv = ['palpate'] + sys.argv[1:]; "
               "from app.entry import palpate; palpate()", "run", str(out / "scenes" / f"{tag}.toml"),
               "--prior", "block3d", "--sim", "--seed", str(seed), "--no-figure", "--fit-workers", "1",
               "--out", str(run_dir)] + extra
        t0 = time.perf_counter()
        p = subprocess.run(cmd, env=env, cwd=str(code or ROOT), capture_output=True, text=True)
        wall = time.perf_counter() - t0
        (out / "logs").mkdir(exist_ok=True)
        (out / "logs" / f"{label}-{tag}-s{seed}.log").write_text(p.stdout + p.stderr)
        if p.returncode != 0 or not res.exists():
            return {"label": label, "truth": tag, "seed": seed, "error": (p.stderr.strip().splitlines() or ["?"])[-1]}
    r = json.loads(res.read_text())
    est, nu = r.get("estimate", {}), r.get("nuisance", {})

    def v(d, k):
        x = (d.get(k) or {}).get("value") if isinstance(d.get(k), dict) else None
        return x if x is not None and math.isfinite(x) else None

    def sd(d, k):
        return (d.get(k) or {}).get("sigma") if isinstance(d.get(k), dict) else None
    err = (r.get("sim") or {}).get("error") or {}
    return {"label": label, "truth": tag, "seed": seed, "detected": bool(r.get("detected")),
            "lr": (r.get("evidence") or {}).get("likelihood_ratio"), "probes": r.get("probes_used"),
            "x_m": v(est, "x_m"), "y_m": v(est, "y_m"), "depth_m": v(est, "depth_m"), "diameter_m": v(est, "diameter_m"),
            "sigma_x_m": sd(est, "x_m"), "sigma_y_m": sd(est, "y_m"), "sigma_depth_m": sd(est, "depth_m"),
            "sigma_diameter_m": sd(est, "diameter_m"), "err": err,
            "thickness_scale": v(nu, "thickness_scale"), "stiffness_scale": v(nu, "stiffness_scale"),
            "at_bound": (r.get("evidence") or {}).get("fit_at_bound"), "wall_s": wall}


def table(rows: list[dict]) -> str:
    lines = ["| truth | version | seed | answer (LR) | lateral error (mm) | depth error (mm, sigmas) | "
             "diameter error (mm, sigmas) | thickness scale fitted | stiffness scale |",
             "|---|---|---|---|---|---|---|---|---|"]

    def f(x, fmt):
        return "-" if x is None else format(x, fmt)
    for r in sorted(rows, key=lambda r: ([t[0] for t in TRUTHS].index(r["truth"]), r["seed"], r["label"])):
        if "error" in r:
            lines.append(f"| {r['truth']} | {r['label']} | {r['seed']} | failed: {r['error']} | | | | | |")
            continue
        e = r["err"]
        ans = f"{'STONE' if r['detected'] else 'no stone'} ({f(r['lr'], '.1f')})"
        lat = f(e.get("lateral_m") and e["lateral_m"] * 1e3, ".2f") if r["detected"] and e else "-"
        dep = (f"{e['depth_m'] * 1e3:+.2f} ({e['depth_m'] / r['sigma_depth_m']:+.1f})"
               if r["detected"] and e.get("depth_m") is not None and r["sigma_depth_m"] else "-")
        dia = (f"{e['diameter_m'] * 1e3:+.2f} ({e['diameter_m'] / r['sigma_diameter_m']:+.1f})"
               if r["detected"] and e.get("diameter_m") is not None and r["sigma_diameter_m"] else "-")
        bound = f" at bound: {', '.join(r['at_bound'])}" if r["detected"] and r.get("at_bound") else ""
        lines.append(f"| {r['truth']} | {r['label']} | {r['seed']} | {ans}{bound} | {lat} | {dep} | {dia} | "
                     f"{f(r['thickness_scale'], '.3f')} | {f(r['stiffness_scale'], '.3f')} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--code", type=Path, default=None, help="another checkout of palpate to run (default: this one)")
    ap.add_argument("--label", default="this", help="the version's name in the table (default: this)")
    ap.add_argument("--only", nargs="*", default=None, help="truth tags to run (default: all)")
    ap.add_argument("--extra", default="", help="more options for every `palpate run`, one string")
    a = ap.parse_args()
    a.out = a.out.resolve()          # (another checkout runs in its own directory)
    (a.out / "scenes").mkdir(parents=True, exist_ok=True)
    for tag, factor, E, stone in TRUTHS:
        p = a.out / "scenes" / f"{tag}.toml"
        if not p.exists():
            p.write_text(S.dump_toml(truth_scene(tag, factor, E, stone)))
    log = a.out / "thickness3d.jsonl"
    for tag, *_ in TRUTHS:
        if a.only and tag not in a.only:
            continue
        for seed in a.seeds:
            row = run_one(a.out, tag, seed, a.code, a.label, a.extra.split())
            with log.open("a") as fh:
                fh.write(json.dumps(row) + "\n")
            print(json.dumps({k: row.get(k) for k in ("label", "truth", "seed", "detected", "lr",
                                                      "thickness_scale", "error") if k in row}), flush=True)
    latest = {}
    for line in log.read_text().splitlines():
        r = json.loads(line)
        latest[(r["label"], r["truth"], r["seed"])] = r
    (a.out / "thickness3d.md").write_text(table(list(latest.values())))
    print(a.out / "thickness3d.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
