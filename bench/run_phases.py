"""Where `palpate run` spends its time: the main job in-process, with its phases timed (issue 19).

    python bench/run_phases.py --out bench-out/phases [--scene paper] [--label NAME]

Runs ``palpate run SCENE --sim`` (a fresh output directory under OUT; the disk cache as it is: run it twice for the
cached figures) with wall-clock timers around its phases: planning (``plan_raster``, every round), the detectability
table, loading the surrogate table, the arm (``run_plan``: the simulated arm and the driver stepping every 2 ms
period), the localizations (every round's and the final one) and the figure. The imports before ``main`` are
``before_main_s``; what no timer covers (the refinement's design, result.json, writing what the process would write
at its exit: fem.memo's remembered forces) is ``rest_s``, so the phases add up to ``wall_s`` (before session 30
``rest_s`` held the imports too). Appends one JSON line to OUT/phases.jsonl and prints it. The timers wrap the
functions where the run command looks them up, so the same script times an older checkout too
(``PYTHONPATH=OLD python bench/run_phases.py ...`` from inside OLD).
"""
from __future__ import annotations

import argparse
import functools
import importlib
import json
import os
import sys
import time
from collections import Counter
from pathlib import Path

T0 = time.perf_counter()
ROOT = Path(os.environ.get("PYTHONPATH", "").split(os.pathsep)[0] or Path(__file__).resolve().parents[1])
sys.path.insert(0, str(ROOT))

# (module, function, phase, modules that imported it by name and call it from there)
PHASES = (("planner.plan", "plan_raster", "plan_s", ("app.commands.run",)),
          ("planner.detectability", "detectability", "detectability_s", ("app.commands.run",)),
          ("planner.surrogate", "load_surrogate", "load_surrogate_s", ("app.commands.run", "planner.localize")),
          ("robot.driver", "run_plan", "arm_s", ("app.runexec",)),
          ("planner.localize", "localize", "localize_s", ("app.commands.run", "planner.refine")),
          ("planner.plots_run", "plot_run", "figure_s", ()),        # before session 31: computed and drawn here
          ("planner.plots_run", "run_figure", "figure_s", ()),      # since: computed here ...
          ("app.figchild", "FigureChild.draw", "figure_s", ()),     # ... and drawn by the child (waited for here)
          ("planner.draw_run", "draw_run", "figure_s", ("app.commands.run",)),   # or here (no child)
          ("planner.plots_run3d", "run_figure3d", "figure_s", ()),  # a 3D block's: computed here ...
          ("planner.draw_run3d", "draw_run3d", "figure_s", ("app.commands.run3d",)))   # ... drawn here (no child)


def instrument() -> tuple[Counter, Counter]:
    spent, calls = Counter(), Counter()
    for mod, name, phase, users in PHASES:
        try:
            m = importlib.import_module(mod)
        except ImportError:             # an older checkout without it
            continue
        owner, _, name = name.rpartition(".")
        m = getattr(m, owner) if owner else m
        f = getattr(m, name, None)
        if f is None:
            continue

        @functools.wraps(f)
        def timed(*a, _f=f, _phase=phase, **k):
            t = time.perf_counter()
            try:
                return _f(*a, **k)
            finally:
                spent[_phase] += time.perf_counter() - t
                calls[_phase] += 1
        setattr(m, name, timed)
        for u in users:
            um = importlib.import_module(u)
            if getattr(um, name, None) is f:
                setattr(um, name, timed)
    return spent, calls


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True)
    p.add_argument("--scene", default="paper")
    p.add_argument("--label", default="")
    a = p.parse_args()
    out = Path(a.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    run_dir = out / f"run-{time.strftime('%Y%m%dT%H%M%S')}-{os.getpid()}"
    import app.cli  # here, not at the top: the imports are part of what before_main_s measures
    spent, calls = instrument()
    t_main = time.perf_counter()
    rc = app.cli.main(["run", a.scene, "--sim", "--out", str(run_dir)])
    if "fem.memo" in sys.modules:       # what the process writes at its exit (remembered forces: fem.memo), timed
        sys.modules["fem.memo"].save_all()
    wall = time.perf_counter() - T0
    row = {"label": a.label, "scene": a.scene, "rc": rc, "code": str(ROOT), "load_avg_1m": os.getloadavg()[0],
           "wall_s": wall, "before_main_s": t_main - T0,
           "calls": dict(calls), "rest_s": wall - (t_main - T0) - sum(spent.values())}
    row.update({k: spent[k] for _, _, k, _ in PHASES})
    with open(out / "phases.jsonl", "a") as f:
        f.write(json.dumps(row) + "\n")
    print(json.dumps(row, indent=1))
    return 0 if rc == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
