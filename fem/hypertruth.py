"""A finite-strain (neo-Hookean) simulated truth's tip force, fast enough for the simulated arm: per probe position
one load-stepped sweep in depth (fem.hyperindent), kept on disk (fem.diskcache), interpolated in depth.

The force at (x, d) is the linear model's force on the scene's own mesh (fem.contact, exact and cheap at any depth)
times the finite-strain correction r(x, d) = F_neo-Hookean / F_linear, both computed on a *correction mesh*: the
scene's mesh with the same top-surface element size and bulk elements twice as large (``correction_scene``).
Measured on the paper scene at 4 mm (bench/hyper_truth.py --own-mesh): r is 1.0485 on the correction mesh (8.9k
DOFs) and 1.0472 on the scene's own (18.5k DOFs) at x = 35 mm, 1.1728 and 1.1727 at x = 5 mm: the correction mesh
changes the truth's force by at most about 0.13 % (0.15 mN of 0.12 N; a probe's noise is 0.2 mN). r is
smooth in depth (the sweep's depths every ``DEPTH_STEP_M``, r(0) = 1), so it is interpolated linearly there; the
sweep is made at the x asked (robot.simforce.CachedForce snaps x to 10 um), no interpolation in x (r varies from
1.05 over the stone to 1.17 at 5 mm from the sides along the paper section at 4 mm: the free sides soften the
linear model's response more than the neo-Hookean's).

Beyond the depths the sweep reached (the tip radius, or where the tissue folds over), or where the linear model
refuses (fem.contact.check_waypoint: the tip's radius, or a tissue crushed against a shallow stone), ``force_n``
raises ValueError like the linear truth: the simulator then extrapolates from the depths below and reports it
(robot.simforce.CachedForce.range_report). The ratio is kept to the depths where both models answer: over a shallow
stone the sweep goes deeper than the linear model's crush limit, so r stops at the last sweep depth below that limit
and is held from there to the limit. (Before, the first refused depth made every depth at that x refused, which the
simulator extrapolated from zero: a zero force over a shallow stone in a neo-Hookean truth.)
"""
from __future__ import annotations

import numpy as np

from . import diskcache
from .contact import SurfaceModel, surface_model
from .hyperindent import HyperIndenter, HyperSweep
from .scene import Scene
from .scene_mesh import code_version, sources_version
from .tip import contact_scene

DEPTH_STEP_M = 0.5e-3             # the sweep's depth step
DEPTH_LAST_FRACTION = 0.98        # its last depth, as a fraction of the tip radius (the linear model's range ends there)
FORMAT = 1


def correction_scene(scene: Scene) -> Scene:
    """The scene on the correction mesh: the same top-surface element size, bulk elements twice as large."""
    a = scene.analysis
    return scene.with_analysis(mesh_size_m=2 * a.mesh_size_m, surface_refine=2 * a.surface_refine)


def sweep_depths(scene: Scene) -> np.ndarray:
    """The depths a sweep passes through: every DEPTH_STEP_M below DEPTH_LAST_FRACTION of the tip radius, then
    that."""
    last = DEPTH_LAST_FRACTION * scene.indenter.radius_m
    d = np.arange(1, int(last / DEPTH_STEP_M) + 1) * DEPTH_STEP_M
    return np.append(d[d < last - 1e-9], last)


def _code() -> str:
    return sources_version(("neohooke.py", "finite_strain.py", "hyperindent.py", "hypertruth.py"),
                           f"hyper format {FORMAT}; linear {code_version()}")


class HyperelasticForce:
    """``force_n(x_m, depth_m)`` of the TRUE scene as a neo-Hookean tissue (a callable for the simulated arm).
    ``linear``: the scene's linear SurfaceModel (default: fem.contact.surface_model); ``cache``: the disk cache (None
    follows $PALPATE_CACHE). ``sweeps``: the sweeps made or read, by x (what a run cost: their ``time_s``)."""

    def __init__(self, scene: Scene, linear: SurfaceModel | None = None, cache: bool | None = None):
        if scene.is_3d:
            raise ValueError("the neo-Hookean truth is 2D (a plane-strain section)")
        if scene.analysis.plane != "strain":
            raise ValueError(f"the neo-Hookean truth is plane strain; the scene's analysis.plane is "
                             f"{scene.analysis.plane!r}")
        self.scene = scene
        self.linear = linear or surface_model(scene, cache=cache)
        # (the sweeps' key: a tip fem treats as rigid keyed without its modulus, as fem.tip.contact_scene keys the
        # linear model's operators; the finite-strain model's tip is rigid whatever it is given)
        self.corr = correction_scene(contact_scene(scene))
        self.depths = sweep_depths(scene)
        self.cache = cache
        self._indenter: HyperIndenter | None = None
        self._corr_linear: SurfaceModel | None = None
        self.sweeps: dict[float, HyperSweep] = {}
        self._ratio: dict[float, tuple[np.ndarray, np.ndarray]] = {}
        self._held: set[float] = set()     # x whose ratio the linear model's range cut short (a shallow stone)

    def _spec(self, x_m: float) -> dict:
        return {"scene": self.corr.key(), "x_m": repr(float(x_m)), "depths": [repr(float(d)) for d in self.depths],
                "code": _code()}

    def sweep(self, x_m: float) -> HyperSweep:
        """The sweep at ``x_m`` on the correction mesh: from the disk cache, else computed (and stored)."""
        x_m = float(x_m)
        if x_m not in self.sweeps:
            def build() -> HyperSweep:
                if self._indenter is None:
                    self._indenter = HyperIndenter(self.corr)
                return self._indenter.sweep(x_m, self.depths)
            self.sweeps[x_m] = diskcache.load_or_build("hyper", self._spec(x_m), build=build, to_arrays=_to_arrays,
                                                       from_arrays=lambda d: _from_arrays(d, x_m), use=self.cache)
        return self.sweeps[x_m]

    def ratio(self, x_m: float) -> tuple[np.ndarray, np.ndarray]:
        """(depths from 0, r = F_neo-Hookean / F_linear at each) on the correction mesh at ``x_m``."""
        x_m = float(x_m)
        if x_m not in self._ratio:
            sw = self.sweep(x_m)
            if self._corr_linear is None:
                self._corr_linear = surface_model(self.corr, cache=self.cache)
            lin = []
            for d in sw.depth_m:          # the depths the linear model answers too (over a shallow stone it stops
                try:                      # at its crush limit, where the sweep may go on): r needs both forces
                    lin.append(self._corr_linear.force_n(x_m, float(d)))
                except ValueError:
                    break
            lin = np.array(lin)
            r = np.divide(sw.force_n[:len(lin)], lin, out=np.ones_like(lin), where=lin > 0)
            self._ratio[x_m] = (np.concatenate([[0.0], sw.depth_m[:len(lin)]]), np.concatenate([[1.0], r]))
            if len(lin) < len(sw.depth_m):
                self._held.add(x_m)
        return self._ratio[x_m]

    def force_n(self, x_m: float, depth_m: float) -> float:
        """The neo-Hookean tissue's force on the tip at ``x_m`` pressed ``depth_m`` (N); ValueError beyond the
        sweep's reach or the linear model's range."""
        f = self.linear.force_n(x_m, depth_m)
        if f <= 0.0:
            return f
        d, r = self.ratio(x_m)
        if depth_m > d[-1] + 1e-12 and float(x_m) in self._held:
            return f * float(r[-1])     # the sweep went on; the linear model's own range ends (above) before its next
        if depth_m > d[-1] + 1e-12:     # depth: r held from its last depth (it changes by about 2 % a millimetre)
            raise ValueError(f"depth_m={depth_m} beyond the finite-strain sweep at x_m={x_m} (it reached "
                             f"{d[-1]:.4g} m)")
        return f * float(np.interp(depth_m, d, r))

    __call__ = force_n


def _to_arrays(sw: HyperSweep) -> dict[str, np.ndarray]:
    return {"depth_m": sw.depth_m, "force_n_per_m": sw.force_n_per_m, "force_n": sw.force_n,
            "newton_iterations": sw.newton_iterations, "time_s": np.float64(sw.time_s),
            "stopped": np.array(sw.stopped)}


def _from_arrays(d: dict[str, np.ndarray], x_m: float) -> HyperSweep:
    if not (d["depth_m"].shape == d["force_n"].shape == d["force_n_per_m"].shape):
        raise ValueError("inconsistent sweep arrays")
    return HyperSweep(x_m=x_m, depth_m=np.asarray(d["depth_m"]), force_n_per_m=np.asarray(d["force_n_per_m"]),
                      force_n=np.asarray(d["force_n"]), newton_iterations=np.asarray(d["newton_iterations"]),
                      stopped=str(d["stopped"]), time_s=float(d["time_s"]))
