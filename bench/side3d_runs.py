"""Simulated 3D runs on stones near a block's side, with and without fem's correction of the table (session 54).

    python bench/side3d_runs.py --out DIR SCENE.toml [SCENE.toml ...] [--seeds 0,1] [--sensor nano17]

Each scene (a 3D block with one stone: bench-out/side3d-s53's, or your own) is run as ``palpate run SCENE --sim``
and as ``palpate run SCENE --sim --no-fem-correction`` for each seed, into DIR/<scene>-<seed>-<fem|table>/ (a run
already there is resumed, never overwritten: its result is read again). Prints, per
run the error of x, y, depth and diameter (mm) and in sigmas, the probes, the stop reason, the wall time and the
correction's passes and time; then the share of coordinates within 1 and 2 sigma per mode (DIR/side3d_runs-TIME.txt; the
rows appended to DIR/side3d_runs.jsonl).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.options import float_list  # noqa: E402

KEYS = ("x", "y", "depth", "diameter")


def one(scene: Path, seed: int, mode: str, sensor: str, out: Path) -> dict:
    run = out / f"{scene.stem}-{seed}-{mode}"
    cmd = [sys.executable, "-c", "import sys; from app.entry import palpate; sys.argv[0] = 'palpate'; "
           "sys.exit(palpate())", "run", str(scene), "--sim", "--seed", str(seed), "--sensor", sensor,
           "--no-figure", "--out", str(run)] + (["--no-fem-correction"] if mode == "table" else [])
    t0 = time.perf_counter()
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    (out / f"{run.name}.log").write_text(p.stdout + p.stderr)
    if not (run / "result.json").exists():
        return {"run": run.name, "rc": p.returncode, "error": (p.stderr.strip().splitlines() or ["?"])[-1]}
    r = json.loads((run / "result.json").read_text())
    row = {"run": run.name, "rc": p.returncode, "wall_s": wall, "probes": r.get("probes_used"),
           "stop": r.get("stop_reason"), "fit_at_bound": r["evidence"]["fit_at_bound"],
           "fem_correction": r["evidence"].get("fem_correction")}
    err = (r.get("sim") or {}).get("error")
    if err:
        row["error_m"] = {k: err[f"{k}_m"] for k in KEYS}
        row["sigma_m"] = {k: r["estimate"][f"{k}_m"]["sigma"] for k in KEYS}
    return row


def line(row: dict) -> str:
    if "error_m" not in row:
        return f"{row['run']:28s} {row.get('error', 'no stone detected')}"
    e, s = row["error_m"], row["sigma_m"]
    fc = row["fem_correction"]
    return (f"{row['run']:28s} error mm " + " ".join(f"{e[k] * 1e3:+.2f}" for k in KEYS)
            + " | sigma mm " + " ".join(f"{s[k] * 1e3:.2f}" for k in KEYS)
            + " | sigmas off " + " ".join(f"{e[k] / s[k]:+.1f}" for k in KEYS)
            + f" | {row['probes']} probes, {row['stop']}, {row['wall_s']:.0f} s"
            + (f", fem {fc['passes']} passes {fc['solve_s']:.0f} s" if fc else "")
            + (f", at bound {row['fit_at_bound']}" if row["fit_at_bound"] else ""))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenes", nargs="+", type=Path)
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--seeds", type=float_list(what="seeds"), default=[0.0, 1.0])
    p.add_argument("--sensor", default="nano17")
    a = p.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for scene in a.scenes:
        for seed in a.seeds:
            for mode in ("table", "fem"):
                rows.append(one(scene.resolve(), int(seed), mode, a.sensor, a.out))
                print(line(rows[-1]), flush=True)
    text = [line(r) for r in rows]
    for mode in ("table", "fem"):
        offs = [abs(r["error_m"][k] / r["sigma_m"][k]) for r in rows if r["run"].endswith(mode) and "error_m" in r
                for k in KEYS]
        if offs:
            text.append(f"{mode}: {len(offs)} coordinates, within 1 sigma {sum(o <= 1 for o in offs) / len(offs):.0%}, "
                        f"within 2 sigma {sum(o <= 2 for o in offs) / len(offs):.0%}, worst {max(offs):.1f} sigma")
    with open(a.out / "side3d_runs.jsonl", "a") as f:
        for r in rows:
            f.write(json.dumps(r) + "\n")
    (a.out / f"side3d_runs-{time.strftime('%Y%m%dT%H%M%S')}.txt").write_text("\n".join(text) + "\n")
    print("\n".join(text[-2:]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
