"""A run's figure drawn by a child process that imports matplotlib while the run works (issue 19).

A process's first figure costs about 0.5 s more than the same figure drawn again (importing matplotlib's pyplot,
the font cache and glyphs, the PNG writer, the layout's renderer: the child below is ready 0.50 s after it starts,
bench/bench_process.py), about a sixth of a cached (3.1 s) ``palpate run paper --sim``. A child started when the run starts
has paid it, on the machine's other core, by the time the estimate is known. The parent sends the figure's numbers
(a planner.draw_run ``RunFigure`` or planner.draw_run3d ``RunFigure3D``, pickled over the child's stdin) and waits
for the file; the child imports palpate's modules from the parent's own ``sys.path``, so both draw with the same code.

Used for simulated runs on two cores or more only: next to a real arm the control host's cores are left to the
driver, and on one core the child would only compete with the run. If the child
cannot be started, or cannot draw (it failed, wrote no file, or gave no answer within ``FigureChild.timeout_s``), the
parent says so in one line and draws in its own process, so a figure is never lost to the child. A child not asked
to draw (an error or a fault ended the run) finds its stdin closed once its warm-up is done, and exits; the parent
does not wait for it.

    python -m app.figchild      # the child: reads one pickled (path, figure) from stdin, draws it, exits
"""
from __future__ import annotations

import io
import json
import os
import pickle
import subprocess
import sys
from pathlib import Path

from planner.draw_run import RunFigure, draw_run
from planner.draw_run3d import RunFigure3D, draw_run3d

# the child's start: the parent's module search path (its '' as its working directory), then this module as __main__
START = ("import json, runpy, sys; sys.path[:] = json.loads(sys.argv[1]); "
         "runpy.run_module('app.figchild', run_name='__main__', alter_sys=True)")


def usable_cores() -> int:
    """The cores this process may run on (its affinity, where the platform tells it)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:          # no affinity call on this platform
        return os.cpu_count() or 1


def draw(path, fig: RunFigure | RunFigure3D) -> None:
    """``fig`` drawn to ``path`` in this process (planner.draw_run or planner.draw_run3d)."""
    if isinstance(fig, RunFigure3D):
        draw_run3d(path, fig)
    elif isinstance(fig, RunFigure):
        draw_run(path, fig)
    else:
        raise TypeError(f"not a run's figure: {type(fig).__name__}")


class FigureChild:
    """A child started at construction (``start``: None, with a warning, when it cannot be); ``draw(path, fig,
    say)`` once, or ``close()``."""

    timeout_s = 60.0

    def __init__(self, cmd: list[str] | None = None):
        search = [os.path.abspath(p) if p else os.getcwd() for p in sys.path]
        self.proc = subprocess.Popen(cmd or [sys.executable, "-c", START, json.dumps(search)],
                                     stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                     env=dict(os.environ, MPLBACKEND="Agg"))

    @classmethod
    def start(cls, say, cmd: list[str] | None = None) -> FigureChild | None:
        """A started child, or None: on a single core (the child's 0.5 s warm-up would only compete with the run;
        the figure is drawn in this process, as before) or, said in one line, when it cannot be started."""
        if usable_cores() < 2:
            return None
        try:
            return cls(cmd)
        except OSError as e:            # no interpreter there, no process or file descriptor left
            say(f"warning: no child process for the figure ({e}): it will be drawn in this process")
            return None

    def draw(self, path, fig: RunFigure | RunFigure3D, say) -> str:
        """Draw ``fig`` to ``path`` in the child, else here; returns where it was drawn ("child" or "here")."""
        try:
            _, err = self.proc.communicate(pickle.dumps((str(path), fig)), timeout=self.timeout_s)
            if self.proc.returncode == 0 and Path(path).is_file() and Path(path).stat().st_size > 0:
                return "child"
            why = (err.decode(errors="replace").strip().splitlines()
                   or [f"exit status {self.proc.returncode}" if self.proc.returncode else "it wrote no file"])[-1]
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.communicate()
            why = f"no answer within {self.timeout_s:g} s"
        say(f"warning: the figure's child process did not draw it ({why}): drawing it here")
        draw(path, fig)
        return "here"

    def close(self) -> None:
        """Let a child that was not asked to draw end: its stdin closes, and it exits when its warm-up is done (not
        killed: matplotlib may be writing its font cache, under a lock file a kill would leave behind)."""
        if self.proc.returncode is None and self.proc.stdin is not None and not self.proc.stdin.closed:
            try:
                self.proc.stdin.close()
            except OSError:
                pass


def warm_up() -> None:
    """What a process's first figure pays once (matplotlib's import, the font cache and the font's glyphs, the PNG
    writer, the layout's renderer), paid now."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle
    fig, ax = plt.subplots(2, 1)
    ax[0].errorbar([0.0, 1.0], [0.0, 1.0], yerr=[0.1, 0.1], fmt="o", label="a")
    ax[0].add_patch(Circle((0.5, 0.5), 0.1))
    ax[0].legend(fontsize=7)
    ax[1].scatter([0.0], [1.0], c=[0.5], cmap="RdBu_r")
    ax[1].set_title("b", fontsize=9)
    fig.tight_layout()
    fig.set_layout_engine(None)
    fig.savefig(io.BytesIO(), format="png", dpi=110)
    plt.close(fig)


def main() -> int:
    warm_up()                   # while the parent works
    data = sys.stdin.buffer.read()
    if not data:            # the parent ended without a figure to draw
        return 0
    path, fig = pickle.loads(data)
    draw(path, fig)
    return 0


if __name__ == "__main__":
    try:
        rc = main()
    except Exception as e:  # noqa: BLE001 -- one line for the parent, which then draws the figure itself
        print(f"{type(e).__name__}: {e}", file=sys.stderr)
        sys.exit(1)
    # the file is written and closed: end without the interpreter's tear-down of matplotlib (about 0.1 s the parent
    # would wait for)
    sys.stderr.flush()
    os._exit(rc)
