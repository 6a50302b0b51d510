"""Whole commands as a user runs them, cold and cached, each against one naive full contact re-solve measured in the
same run (issue 19).

    python bench/bench_process.py --out bench-out [--quick] [--repeats 3]

What is timed:
- naive: ``fem.contact.indent_full`` on the paper scene's model (mesh and K reused; the full system refactorized in
  each of its active-set iterations) at three waypoints, 3 mm deep: the median per waypoint. In-process, the fast
  path's 100 waypoints (force only, and with the max von Mises and the no-inversion check) after set-up, against it.
- each command in a fresh process (``python -m app.cli ...``, the same as the ``palpate`` script): wall clock, CPU
  time (user + system, of the child), and the time to its first line of output. *cold*: an empty disk cache
  (a fresh ``PALPATE_CACHE_DIR``); *cached*: the same command again on that cache.
- the floor: ``python -c "import numpy"`` (an interpreter that loads numpy and does nothing else); for ``run``, an
  interpreter that imports what the run's own process needs (numpy, scipy.optimize, casadi), and the figure's child
  process (``python -m app.figchild`` with an empty stdin: matplotlib and a first figure) until it is ready.
  A simulated run's CPU time includes its figure child's (waited for), which works beside it: CPU may exceed wall.

palpate's own modules are compiled to bytecode first (``compileall``, as ``pip install`` does for a regular install):
with ``PYTHONDONTWRITEBYTECODE`` set (this machine sets it) an editable install would otherwise recompile every
module in every command (30 ms of a cached ``predict``), which no installed copy does.

Ratios are naive-per-waypoint x waypoints / command time (predict), or naive-per-waypoint / command time (the other
commands: how many naive re-solves the whole command costs). Writes OUT/process.json and OUT/process.md.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import compileall  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

N_WAYPOINTS = 100
DEPTH_M = 0.003
# what `palpate run`'s own process cannot do without: numpy, scipy.optimize (the localizer's fits), casadi (the
# planner); the figure's matplotlib loads in a child meanwhile (app.figchild: timed as it starts, with an empty stdin)
RUN_LIBRARIES = "import numpy, scipy.optimize, casadi"
TARGETS = {"predict_whole_process_x": 1000.0, "predict_in_process_x": 3000.0, "run_sim_cached_naive": 1.0}


def commands(out: Path) -> dict[str, list[str]]:
    w = str(N_WAYPOINTS)
    return {
        "help": ["--help"],
        "predict": ["predict", "paper", "--waypoints", w, "--depth-m", str(DEPTH_M), "--quiet", "--json",
                    str(out / "predict.json")],
        "predict_force_only": ["predict", "paper", "--waypoints", w, "--depth-m", str(DEPTH_M), "--force-only",
                               "--quiet"],
        "simulate_indent": ["simulate", "paper", "--load", "indent", "--x-m", "0.035", "--depth-m", str(DEPTH_M)],
        "plan": ["plan", "paper", "--out", str(out / "plan-{n}.json")],
        "run_sim": ["run", "paper", "--sim", "--out", str(out / "run-{n}")],
        # another run on the cache the one above left: another sensor-noise seed, so the refinement probes elsewhere
        # and the simulated truth is pressed at other depths (what fem.recall remembers only partly covers it)
        "run_sim_new_seed": ["run", "paper", "--sim", "--seed", "{n}", "--out", str(out / "run-{n}")],
    }


def time_command(argv: list[str], env: dict) -> dict:
    """Wall, CPU (user + sys of the child) and time to the first output line of one process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, "-m", "app.cli", *argv], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                         env=env, cwd=ROOT)
    first = p.stdout.readline()
    t_first = time.perf_counter() - t0
    rest = p.stdout.read()
    rc = p.wait()
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if rc != 0:
        raise RuntimeError(f"{' '.join(argv)} exited {rc}: {(first + rest).decode(errors='replace')[-2000:]}")
    return {"wall_s": wall, "cpu_s": cpu, "first_output_s": t_first if first else wall}


def floor(env: dict, repeats: int) -> dict:
    out = {}
    for label, args in (("python", ["-c", "pass"]), ("python_numpy", ["-c", "import numpy"]),
                        ("python_run_libraries", ["-c", RUN_LIBRARIES]),
                        ("figure_child_ready", ["-m", "app.figchild"])):
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            subprocess.run([sys.executable, *args], env=env, check=True, stdin=subprocess.DEVNULL, cwd=ROOT)
            ts.append(time.perf_counter() - t0)
        out[label] = statistics.median(ts)
    return out


def in_process(repeats: int) -> dict:
    from fem import scene as S
    from fem.contact import indent_full, surface_model
    sc = S.load("paper")
    m = surface_model(sc)
    xs = np.linspace(0.005, sc.tissue.width_m - 0.005, N_WAYPOINTS)
    m.indent_many(xs, DEPTH_M)                                         # operators built or loaded
    naive, naive_cpu = [], []
    for x in (0.02, 0.035, 0.05):
        t0, c0 = time.perf_counter(), time.process_time()
        r = indent_full(sc, x, DEPTH_M, model=m.model)
        naive.append(time.perf_counter() - t0)
        naive_cpu.append(time.process_time() - c0)
        assert abs(r["force_n"] / m.force_n(x, DEPTH_M) - 1) < 1e-9     # the same answer
    prior = surface_model(sc.prior())                                  # predict's reference, the same way
    prior.indent_many(xs, DEPTH_M)
    force, stress, stress_prior = [], [], []
    for _ in range(repeats):
        c0 = time.process_time()
        m.indent_many(xs, DEPTH_M, stresses=False)
        c1 = time.process_time()
        m.indent_many(xs, DEPTH_M)
        c2 = time.process_time()
        prior.indent_many(xs, DEPTH_M)
        force.append(c1 - c0)
        stress.append(c2 - c1)
        stress_prior.append(time.process_time() - c2)
    return {"dofs": int(m.model.n_dofs), "naive_per_waypoint_s": statistics.median(naive), "naive_s": naive,
            "naive_per_waypoint_cpu_s": statistics.median(naive_cpu),
            "fast_100_force_cpu_s": statistics.median(force), "fast_100_stresses_cpu_s": statistics.median(stress),
            "fast_100_stresses_prior_cpu_s": statistics.median(stress_prior)}


def period_floor(n: int = 20000) -> dict:
    """The bare cost of one simulated 2 ms control period as the driver sees it: the simulated arm steps (at rest)
    and the four getters the driver reads each period, with no driver logic at all."""
    from robot.sim import make_sim
    arm, c, r = make_sim()
    t0 = time.process_time()
    for _ in range(n):
        c.waitPeriod(c.initPeriod())
        r.getTimestamp(), r.getActualTCPPose(), r.getActualTCPForce(), r.isProtectiveStopped()
    return {"per_period_cpu_s": (time.process_time() - t0) / n, "period_s": arm.period_s}


PACKAGES = ("app", "core", "fem", "planner", "robot")


def compile_bytecode() -> bool:
    """palpate's modules to bytecode (__pycache__, ignored by git), as an installed copy has them."""
    return all(compileall.compile_dir(str(ROOT / pkg), quiet=1) for pkg in PACKAGES)


def run(out_dir, quick: bool = False, repeats: int | None = None) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    bytecode = compile_bytecode()
    repeats = repeats or (1 if quick else 3)
    work = Path(tempfile.mkdtemp(prefix="bench-process-", dir=out_dir))
    env = dict(os.environ, PALPATE_CACHE_DIR=str(work / "cache"), PYTHONPATH=str(ROOT))
    os.environ["PALPATE_CACHE_DIR"] = env["PALPATE_CACHE_DIR"]    # the in-process part shares the cache
    ip = in_process(max(repeats, 3))
    naive, naive_cpu = ip["naive_per_waypoint_s"], ip["naive_per_waypoint_cpu_s"]
    print(f"naive full re-solve: {naive:.3f} s per waypoint ({naive_cpu:.3f} s CPU; {ip['dofs']} DOFs); in-process "
          f"fast path, {N_WAYPOINTS} waypoints: CPU force {ip['fast_100_force_cpu_s']:.4f} s, with stresses "
          f"{ip['fast_100_stresses_cpu_s']:.4f} s", flush=True)
    fl = floor(env, 5)
    pf = period_floor()
    rows = {}
    n = 0
    for name, argv in commands(work).items():
        if quick and name.startswith("run_sim"):
            continue
        if name == "run_sim_new_seed":
            env["PALPATE_CACHE_DIR"] = str(work / "cache-run_sim")
        for phase in (("cached",) if name == "run_sim_new_seed" else ("cold", "cached")):
            if phase == "cold":                           # an empty cache for each command's cold run
                env["PALPATE_CACHE_DIR"] = str(work / f"cache-{name}")
            reps = 1 if phase == "cold" else repeats
            ts = []
            for _ in range(reps):
                n += 1
                ts.append(time_command([a.replace("{n}", str(n)) for a in argv], env))
            med = {k: statistics.median(t[k] for t in ts) for k in ts[0]}
            shown = " ".join(argv).replace(str(work), "OUT").replace("-{n}", "").replace("{n}", "N")
            rows[f"{name}:{phase}"] = {"command": "palpate " + shown, "runs": len(ts), **med}
            if name == "predict":           # the command's own split: set-up and waypoints, scene and reference
                rows[f"{name}:{phase}"]["own_timings_s"] = json.loads((work / "predict.json").read_text())["timings_s"]
            if name.startswith("run_sim"):
                robot_s = json.loads((work / f"run-{n}" / "result.json").read_text())["time"]["robot_s"]
                periods = robot_s / pf["period_s"]
                rows[f"{name}:{phase}"].update(robot_s=robot_s, periods=periods,
                                               cpu_per_period_s=med["cpu_s"] / periods)
            print(f"  {name:20s} {phase:6s} wall {med['wall_s']:7.3f} s  cpu {med['cpu_s']:7.3f} s  "
                  f"first output {med['first_output_s']:.3f} s", flush=True)
    for cache in work.glob("cache*"):       # the commands' disk caches: scratch (0.5 GB), not measurements
        shutil.rmtree(cache, ignore_errors=True)
    ratio = {}
    for key, r in rows.items():
        k = N_WAYPOINTS if key.startswith("predict") else 1
        ratio[key] = {"wall": naive * k / r["wall_s"], "cpu": naive_cpu * k / r["cpu_s"]}
    best = naive * N_WAYPOINTS / fl["python_numpy"]
    # a predict's least work: the interpreter with numpy, then both scenes' waypoints in-process and warm
    best_predict = naive * N_WAYPOINTS / (fl["python_numpy"] + ip["fast_100_stresses_cpu_s"]
                                          + ip["fast_100_stresses_prior_cpu_s"])
    result = {
        "machine": {"cpus": os.cpu_count(), "load_avg_1m": os.getloadavg()[0],
                    "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
                    "bytecode_compiled": bytecode, "python": sys.version.split()[0],
                    "numpy": np.__version__},
        "in_process": ip, "floor_s": fl, "period_floor": pf, "commands": rows, "ratio_to_naive": ratio,
        "in_process_ratio": {"force": naive_cpu * N_WAYPOINTS / ip["fast_100_force_cpu_s"],
                             "stresses": naive_cpu * N_WAYPOINTS / ip["fast_100_stresses_cpu_s"]},
        "best_possible_predict_ratio": best, "best_possible_predict_with_work_ratio": best_predict,
    }
    (out_dir / "process.json").write_text(json.dumps(result, indent=1) + "\n")
    md = markdown(result)
    (out_dir / "process.md").write_text(md)
    print(md)
    return result


def markdown(r: dict) -> str:
    ip, fl = r["in_process"], r["floor_s"]
    lines = [f"Naive full contact re-solve (paper, {ip['dofs']:,} DOFs, 3 mm): **{ip['naive_per_waypoint_s']:.3f} s** "
             f"per waypoint, {ip['naive_per_waypoint_cpu_s']:.3f} s of CPU (median of 3, this run; load average "
             f"{r['machine']['load_avg_1m']:.1f}). In-process after set-up, {N_WAYPOINTS} waypoints, CPU time: force "
             f"only {ip['fast_100_force_cpu_s'] * 1e3:.1f} ms (**{r['in_process_ratio']['force']:.0f}x**), with "
             f"stresses and the inversion check {ip['fast_100_stresses_cpu_s'] * 1e3:.1f} ms "
             f"(**{r['in_process_ratio']['stresses']:.0f}x**). Ratios: wall against wall, CPU against CPU.", "",
             "| command | cache | wall | CPU | first output | x naive (wall / CPU) |", "|---|---|---:|---:|---:|---:|"]
    for key, row in r["commands"].items():
        name, phase = key.split(":")
        ra = r["ratio_to_naive"][key]
        unit = f"{N_WAYPOINTS} waypoints" if name.startswith("predict") else "1 re-solve"
        lines.append(f"| `{row['command']}` | {phase} | {row['wall_s']:.3f} s | {row['cpu_s']:.3f} s | "
                     f"{row['first_output_s']:.3f} s | {ra['wall']:.1f} / {ra['cpu']:.1f} ({unit}) |")
    lines += ["", f"Floor: an interpreter that does nothing takes {fl['python'] * 1e3:.0f} ms, one that imports numpy "
              f"{fl['python_numpy'] * 1e3:.0f} ms: no Python command that loads numpy can beat "
              f"{r['best_possible_predict_ratio']:.0f}x on {N_WAYPOINTS} waypoints against this run's naive re-solve; "
              f"with the two scenes' waypoints as warm in-process work added ({ip['fast_100_stresses_cpu_s'] * 1e3:.1f} "
              f"+ {ip['fast_100_stresses_prior_cpu_s'] * 1e3:.1f} ms), "
              f"{r['best_possible_predict_with_work_ratio']:.0f}x."]
    if "python_run_libraries" in fl:
        lines += ["", f"An interpreter that only imports what `palpate run`'s own process cannot do without (numpy, "
                  f"scipy.optimize for the fits, casadi for the plans) takes {fl['python_run_libraries']:.3f} s: "
                  f"{fl['python_run_libraries'] / ip['naive_per_waypoint_s']:.2f} of one naive re-solve before any "
                  f"work."]
        if "figure_child_ready" in fl:
            lines[-1] += (f" The figure's child process (`python -m app.figchild`: matplotlib's pyplot and a first "
                          f"figure, on the other core meanwhile) takes {fl['figure_child_ready']:.3f} s to be ready.")
    pf = r["period_floor"]
    for key, row in r["commands"].items():
        if "periods" in row:
            lines.append(f"`{row['command']}` ({key.split(':')[1]}): {row['robot_s']:.0f} s of robot time = "
                         f"{row['periods']:,.0f} control periods of {pf['period_s'] * 1e3:g} ms, "
                         f"{row['cpu_per_period_s'] * 1e6:.0f} us of CPU per period in all; a bare simulated period "
                         f"(the arm's step and the driver's four getters, no driver logic) costs "
                         f"{pf['per_period_cpu_s'] * 1e6:.0f} us, so stepping every period one at a time would "
                         f"cost at least {row['periods'] * pf['per_period_cpu_s']:.1f} s of CPU; the driver steps "
                         f"the quiet ones many at once (robot.driver._fast_forward).")
    return "\n".join(lines) + "\n"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True)
    p.add_argument("--quick", action="store_true", help="one repeat, no palpate run")
    p.add_argument("--repeats", type=int)
    a = p.parse_args()
    run(a.out, quick=a.quick, repeats=a.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
