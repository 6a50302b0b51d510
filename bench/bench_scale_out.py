"""Scale-out benchmark: the accuracy study serial against a dask LocalCluster, and `palpate run` on a tissue without
a table (time to the first probe and to the answer), optionally against a previous version's checkout.

    python bench/bench_scale_out.py --out bench-out/scale_out [--part study] [--part run] [--before DIR]

study: `palpate study accuracy --quick` with --workers 1 and --workers 2 (fresh output directories, so nothing is
resumed); wall times, the speed-up, and whether the rows are identical (every column but the trials' wall times).
run: `palpate run SCENE --sim` on the paper tissue with Poisson ratio 0.45 (no shipped table: one is built) with an
empty disk cache; the time from start to the first probe (the first line of probes.jsonl written) and to the answer.
--before DIR: the same run with the code in DIR (e.g. `git archive <commit> | tar -x -C DIR`). Each process is
timed from outside (wall clock; the first probe by polling probes.jsonl every 0.2 s). Writes scale_out.json and
scale_out.md in OUT and prints them.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SCENE = """name = "poisson-045"
[tissue]
width_m = 0.070
height_m = 0.050
youngs_pa = 2500.0
poisson = 0.45
[[stone]]
x_m = 0.030
depth_m = 0.020
diameter_m = 0.012
"""


def _env(code: Path, cache: Path) -> dict:
    return {**os.environ, "PYTHONPATH": str(code), "PALPATE_CACHE_DIR": str(cache), "OPENBLAS_NUM_THREADS": "1",
            "OMP_NUM_THREADS": "1"}


def timed(cmd: list[str], env: dict, log: Path, watch: Path | None = None, cwd: Path = ROOT) -> dict:
    """Run ``cmd`` in ``cwd`` (``python -m app.cli`` takes the code of the working directory first); wall time, and
    the time until ``watch`` (a probes.jsonl) has its first line."""
    t0 = time.perf_counter()
    first = None
    with open(log, "w") as f:
        p = subprocess.Popen(cmd, env=env, stdout=f, stderr=subprocess.STDOUT, cwd=cwd)
        while p.poll() is None:
            if first is None and watch is not None and watch.exists() and watch.read_text().strip():
                first = time.perf_counter() - t0
            time.sleep(0.2)
    return {"returncode": p.returncode, "wall_s": time.perf_counter() - t0, "first_probe_s": first,
            "command": " ".join(cmd), "log": str(log)}


def study_part(out: Path) -> dict:
    res = {}
    for workers in (1, 2):
        d = out / f"study_workers{workers}"
        if d.exists():
            raise SystemExit(f"{d} exists: give a fresh --out (a study there would resume)")
        res[workers] = timed([sys.executable, "-m", "app.cli", "study", "accuracy", "--quick", "--workers",
                              str(workers), "--out", str(d), "--no-progress"], _env(ROOT, out / "cache"),
                             out / f"study_workers{workers}.log")
    rows = []
    for workers in (1, 2):
        with open(out / f"study_workers{workers}" / "accuracy.csv") as f:
            rows.append([{k: v for k, v in r.items() if k != "time_s"} for r in csv.DictReader(f)])
    return {"serial": res[1], "workers2": res[2], "speedup": res[1]["wall_s"] / res[2]["wall_s"],
            "rows": len(rows[0]), "identical": rows[0] == rows[1]}


def run_part(out: Path, code: Path, label: str) -> dict:
    scene = out / "poisson045.toml"
    scene.write_text(SCENE)
    d = out / f"run_{label}"
    cache = Path(tempfile.mkdtemp(prefix=f"palpate-cache-{label}-", dir=out))
    r = timed([sys.executable, "-m", "app.cli", "run", str(scene), "--sim", "--no-figure", "--out", str(d)],
              _env(code, cache), out / f"run_{label}.log", watch=d / "probes.jsonl", cwd=code)
    if (d / "result.json").exists():
        res = json.loads((d / "result.json").read_text())
        r["detected"], r["probes_used"] = res.get("detected"), res.get("probes_used")
        r["estimate_x_m"] = res.get("estimate", {}).get("x_m", {}).get("value")
    r["code"] = str(code)
    return r


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True)
    p.add_argument("--part", action="append", choices=["study", "run"])
    p.add_argument("--before", metavar="DIR", help="a previous version's source tree, run the same way")
    a = p.parse_args(argv)
    out = Path(a.out).absolute()
    out.mkdir(parents=True, exist_ok=True)
    parts = a.part or ["study", "run"]
    result = {"cpus": os.cpu_count(), "load_avg_at_start": os.getloadavg()}
    if "run" in parts:
        result["run_now"] = run_part(out, ROOT, "now")
        if a.before:
            result["run_before"] = run_part(out, Path(a.before).absolute(), "before")
    if "study" in parts:
        result["study"] = study_part(out)
    result["load_avg_at_end"] = os.getloadavg()
    (out / "scale_out.json").write_text(json.dumps(result, indent=1))
    lines = ["| measurement | value |", "|---|---|"]
    for key in ("run_now", "run_before"):
        if key in result:
            r = result[key]
            fp = f"{r['first_probe_s']:.1f} s" if r["first_probe_s"] is not None else "-"
            lines.append(f"| palpate run (nu 0.45, no table), {key[4:]}: first probe / answer | {fp} / "
                         f"{r['wall_s']:.1f} s (exit {r['returncode']}, {r.get('probes_used')} probes) |")
    if "study" in result:
        s = result["study"]
        lines.append(f"| accuracy study --quick, serial / 2 workers | {s['serial']['wall_s']:.1f} s / "
                     f"{s['workers2']['wall_s']:.1f} s (speed-up {s['speedup']:.2f}x) |")
        lines.append(f"| rows identical (all columns but wall times) | {s['identical']} ({s['rows']} rows) |")
    (out / "scale_out.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
