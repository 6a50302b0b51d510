"""A run's figure drawn by a child process that imports matplotlib while the run works (issue 19).

Importing matplotlib's pyplot takes about 0.3 s, a tenth of a cached ``palpate run paper --sim``; a child started
when the run starts has it loaded by the time the estimate is known, on the machine's other core. The parent sends
the figure's numbers (a planner.draw_run ``RunFigure`` or planner.draw_run3d ``RunFigure3D``, pickled over the child's stdin) and waits for the file.

Used for simulated runs only: next to a real arm the control host's cores are left to the driver. If the child
cannot draw (it failed, or gave no answer within ``FigureChild.timeout_s``), the parent says so in one line and
draws in its own process, so a figure is never lost to the child. A child whose parent ends without sending reads
the end of its stdin and exits.

    python -m app.figchild      # the child: reads one pickled (path, figure) from stdin, draws it, exits
"""
from __future__ import annotations

import io
import os
import pickle
import subprocess
import sys
from pathlib import Path

from planner.draw_run import RunFigure, draw_run
from planner.draw_run3d import RunFigure3D, draw_run3d

ROOT = Path(__file__).resolve().parents[1]


def draw(path, fig: RunFigure | RunFigure3D) -> None:
    """``fig`` drawn to ``path`` in this process (planner.draw_run or planner.draw_run3d)."""
    if isinstance(fig, RunFigure3D):
        draw_run3d(path, fig)
    elif isinstance(fig, RunFigure):
        draw_run(path, fig)
    else:
        raise TypeError(f"not a run's figure: {type(fig).__name__}")


class FigureChild:
    """A child started at construction; ``draw(path, fig, say)`` once, or ``close()``."""

    timeout_s = 60.0

    def __init__(self, cmd: list[str] | None = None):
        env = dict(os.environ, MPLBACKEND="Agg")
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in [env.get("PYTHONPATH")] if p])
        self.proc = subprocess.Popen(cmd or [sys.executable, "-m", "app.figchild"], stdin=subprocess.PIPE,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)

    def draw(self, path, fig: RunFigure | RunFigure3D, say) -> str:
        """Draw ``fig`` to ``path`` in the child, else here; returns where it was drawn ("child" or "here")."""
        try:
            _, err = self.proc.communicate(pickle.dumps((str(path), fig)), timeout=self.timeout_s)
            if self.proc.returncode == 0:
                return "child"
            why = (err.decode(errors="replace").strip().splitlines() or [f"exit status {self.proc.returncode}"])[-1]
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.communicate()
            why = f"no answer within {self.timeout_s:g} s"
        except OSError as e:            # the child ended before reading (a broken pipe)
            self.proc.kill()
            self.proc.communicate()
            why = str(e)
        say(f"warning: the figure's child process did not draw it ({why}): drawing it here")
        draw(path, fig)
        return "here"

    def close(self) -> None:
        """End a child that was not asked to draw (its stdin closes: it reads the end and exits)."""
        if self.proc.poll() is None:
            try:
                self.proc.communicate(b"", timeout=self.timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.communicate()


def warm_up() -> None:
    """What a process's first figure pays once (matplotlib's import, the font cache and the font's glyphs, the PNG
    writer, the layout's renderer: 0.4 s of a first 2D figure against 0.3 s for a second), paid now."""
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
