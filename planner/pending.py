"""A surrogate table built in the background while the arm probes what needs only the prior.

A tissue without a table (another Poisson ratio, size, tip or mesh: planner.surrogate.table_scene) needs a few
hundred fem models before the first fit. The coarse raster needs none of them (its plan uses the prior's fem model
only), so ``palpate run`` starts probing at once and builds the table beside it: ``PendingSurrogate`` builds it in
a thread (on a dask LocalCluster, planner.tasks) and stands in for the Surrogate; the first use of the table (the
fit after the coarse raster) waits for it, saying how far the build is and when it should end.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable

from planner.surrogate import Grid, Surrogate, load_surrogate
from planner.tasks import Runner


class TableBuildError(RuntimeError):
    """The background build failed (fem could not model the prior's candidate stones); the cause is chained."""


class PendingSurrogate:
    """Stands in for ``load_surrogate(prior)`` while it builds; every attribute waits for the table (``result``)."""

    def __init__(self, prior, say: Callable[[str], None], runner: Runner | None = None, grid: Grid = Grid(),
                 every_s: float = 15.0):
        self._prior, self._say, self._grid, self._every_s = prior, say, grid, every_s
        self._runner = runner or Runner(workers=2, progress=False)
        self._sur: Surrogate | None = None
        self._error: BaseException | None = None
        self._done = threading.Event()
        self._state = {"done": 0, "total": 0, "elapsed_s": 0.0}
        self._last_say = 0.0
        self.t_start = time.perf_counter()
        self._thread = threading.Thread(target=self._build, name="surrogate-build", daemon=True)
        self._thread.start()

    def _progress(self, done: int, total: int, elapsed_s: float) -> None:
        self._state.update(done=done, total=total, elapsed_s=elapsed_s)
        now = time.perf_counter()
        if now - self._last_say >= self._every_s or done == total:
            self._last_say = now
            self._say(self.status())

    def status(self, live: bool = False) -> str:
        """The build's progress at its last finished stone; ``live``: its time and time left counted to now (a
        waiting line between two stones said the same words as the one before: a review's log held one line nine
        times)."""
        d, n, t = self._state["done"], self._state["total"], self._state["elapsed_s"]
        if not n:
            return "surrogate table: starting the fem workers"
        now = max(time.perf_counter() - self.t_start, t) if live else t
        eta = f", about {max(t / d * (n - d) - (now - t), 0.0):.0f} s to go" if 0 < d < n else ""
        return f"surrogate table: {d}/{n} stones ({now:.0f} s{eta})"

    def _build(self) -> None:
        try:
            self._sur = load_surrogate(self._prior, grid=self._grid, progress=self._progress, runner=self._runner)
        except BaseException as e:  # noqa: BLE001 - handed to the thread that asks for the table
            self._error = e
        finally:
            self._done.set()

    @property
    def ready(self) -> bool:
        return self._done.is_set()

    def result(self) -> Surrogate:
        """The table (waiting for the build, with a status line every ``every_s``: the build's own as stones finish,
        else this one; not both, as each said the same every 15 s before session 50); a failed build raises
        TableBuildError."""
        while not self._done.wait(self._every_s):
            if time.perf_counter() - self._last_say >= self._every_s:    # the build's own line not said meanwhile
                self._last_say = time.perf_counter()
                self._say("waiting for the table: " + self.status(live=True))
        if isinstance(self._error, Exception):
            raise TableBuildError(f"the surrogate table could not be built: {self._error}") from self._error
        if self._error is not None:
            raise self._error
        return self._sur

    def __getattr__(self, name):
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self.result(), name)
