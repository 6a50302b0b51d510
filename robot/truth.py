"""What the simulated world does that the belief does not know: the truth's conditions beyond its scene.

The TRUE scene (fem.scene.Scene) already holds the truth's tissue (modulus, Poisson ratio, thickness = its height)
and stones; ``TruthConditions`` holds the rest, which only the simulated arm applies:

* ``surface_offset_m``: the true tissue surface lies this far *above* the nominal (registered) one along the tissue
  frame's outward normal (positive: the tip meets tissue earlier and presses deeper than planned);
* ``surface_tilt_rad``: the true surface is rotated by this angle about the tissue frame's y axis through the
  middle of the section: at tissue-frame x the surface is ``offset + (x - W/2) tan(tilt)`` above the nominal one;
  the force keeps acting along the nominal normal and the indentation is measured along it (the cos error is
  1.4e-3 at 3 deg);
* ``relaxation_fraction`` and ``relaxation_tau_s``: a standard linear solid (quasi-linear viscoelastic) tissue: the
  force at a constant indentation relaxes from the elastic value (the scene's modulus is the instantaneous one) to
  ``1 - relaxation_fraction`` of it with time constant ``relaxation_tau_s``; ``DEFAULT_RELAXATION`` (25 %, 2 s) is
  the documented default when relaxation is switched on (soft-tissue indentation studies report 20-30 % with
  seconds-scale time constants);
* ``sensor_bias_n`` and ``sensor_drift_n_per_s``: a force bias and a linear drift along the tissue normal, added to
  the sensor preset's own random ones;
* ``hyperelastic``: the tissue is a finite-strain compressible neo-Hookean solid (fem.hypertruth: W = mu/2 (I1 - 3)
  - mu ln J + lambda/2 (ln J)^2 with the scene's E and nu, the rigid tip in exact frictionless contact) instead of
  fem's small-strain linear model: at the paper scene's 4 mm it pushes back 4.9 % harder over the stone and up to
  17 % harder 5 mm from the sides (2D sections, plane strain; one sweep in depth per probe position, 2-10 s each
  with the machine's load, kept in the disk cache).

In a scene TOML file they are the ``[truth]`` table (fem ignores it: the belief never reads it); ``palpate run``'s
``--truth-*`` options override it. Nothing in planner/ or the driver imports this module.
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

from core.textfile import NESTED_TOO_DEEP, read_user_text

DEFAULT_RELAXATION = (0.25, 2.0)      # (fraction, tau_s) when relaxation is on without values


class TruthError(ValueError):
    """A bad truth condition (a [truth] field or a --truth-* option); the message names it and what is allowed."""


# field -> (lo, hi, unit): every field is checked against its range (never clamped)
RANGES = {"surface_offset_m": (-0.005, 0.005, "m"), "surface_tilt_rad": (-0.175, 0.175, "rad"),
          "relaxation_fraction": (0.0, 0.9, ""), "relaxation_tau_s": (0.01, 1000.0, "s"),
          "sensor_bias_n": (-10.0, 10.0, "N"), "sensor_drift_n_per_s": (-0.01, 0.01, "N/s")}


@dataclass(frozen=True)
class TruthConditions:
    surface_offset_m: float = 0.0
    surface_tilt_rad: float = 0.0
    relaxation_fraction: float = 0.0
    relaxation_tau_s: float = DEFAULT_RELAXATION[1]
    sensor_bias_n: float = 0.0
    sensor_drift_n_per_s: float = 0.0
    hyperelastic: bool = False

    def __post_init__(self):
        if not isinstance(self.hyperelastic, bool):
            raise TruthError(f"[truth] hyperelastic = {self.hyperelastic!r}: must be true or false")
        for name, (lo, hi, unit) in RANGES.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise TruthError(f"[truth] {name} = {v!r}: must be a finite number in [{lo:g}, {hi:g}] {unit}")
            if not lo <= v <= hi:
                raise TruthError(f"[truth] {name} = {v!r} is outside the allowed range [{lo:g}, {hi:g}] {unit}")

    @property
    def ideal(self) -> bool:
        """True when the simulated world adds nothing to its scene."""
        return not any((self.surface_offset_m, self.surface_tilt_rad, self.relaxation_fraction, self.sensor_bias_n,
                        self.sensor_drift_n_per_s, self.hyperelastic))

    def check_scene(self, scene) -> None:
        """TruthError if these conditions cannot apply to ``scene`` (a fem.scene.Scene): the neo-Hookean truth is a
        plane-strain 2D section with a rigid-treated tip."""
        if not self.hyperelastic:
            return
        if scene.is_3d:
            raise TruthError("[truth] hyperelastic = true: the neo-Hookean truth is 2D (a plane-strain section); "
                             f"scene {scene.name!r} is a 3D block")
        if scene.analysis.plane != "strain":
            raise TruthError(f"[truth] hyperelastic = true: the neo-Hookean truth is plane strain; scene "
                             f"{scene.name!r} has analysis.plane = {scene.analysis.plane!r}")
        tip = scene.indenter.youngs_pa
        if tip is not None and tip < 1e3 * scene.tissue.youngs_pa:
            raise TruthError(f"[truth] hyperelastic = true: the neo-Hookean truth needs a rigid tip; scene "
                             f"{scene.name!r} has indenter.youngs_pa = {tip:g} Pa, less than 1000 times the tissue's")

    def surface_height_m(self, x_m: float, width_m: float) -> float:
        """Height of the true surface above the nominal one at tissue-frame ``x_m``."""
        return self.surface_offset_m + (x_m - 0.5 * width_m) * math.tan(self.surface_tilt_rad)

    def replace(self, **changes) -> "TruthConditions":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """The fields; ``hyperelastic`` only when on (the options of runs made before it existed stay equal)."""
        d = dataclasses.asdict(self)
        if not self.hyperelastic:
            del d["hyperelastic"]
        return d

    @staticmethod
    def from_dict(d: dict, where: str = "[truth]") -> "TruthConditions":
        if not isinstance(d, dict):
            raise TruthError(f"{where} must be a table, got {type(d).__name__}")
        known = [f.name for f in dataclasses.fields(TruthConditions)]
        unknown = sorted(set(d) - set(known))
        if unknown:
            raise TruthError(f"unknown key(s) in {where}: {', '.join(map(str, unknown))} (known: {', '.join(known)})")
        if "relaxation_tau_s" in d and not d.get("relaxation_fraction"):
            raise TruthError(f"{where} relaxation_tau_s = {d['relaxation_tau_s']!r} without a relaxation_fraction "
                             f"above 0: the truth does not relax, so the time constant would do nothing; give "
                             f"relaxation_fraction (0 < f <= {RANGES['relaxation_fraction'][1]:g}) or drop it")
        return TruthConditions(**d)


def conditions_of(scene_spec) -> TruthConditions:
    """The ``[truth]`` table of a scene TOML file (as ``fem.scene.load`` reads one: a path ending in .toml or an
    existing file, whatever its name); the ideal world for a name that is no file, a Scene object or a file without
    the table. (A built-in scene's name that is also a file here: callers that know fem's built-ins pass the name
    only when it is not one of them, as fem.scene.load takes the built-in.)"""
    if not isinstance(scene_spec, (str, Path)):
        return TruthConditions()
    p = Path(scene_spec)
    if not (p.suffix == ".toml" or p.is_file()):
        return TruthConditions()
    try:
        d = tomllib.loads(read_user_text(scene_spec, "scene"))
    except tomllib.TOMLDecodeError as e:
        raise TruthError(f"{scene_spec}: not valid TOML ({e})") from None
    except RecursionError:
        raise TruthError(f"{scene_spec}: not valid TOML ({NESTED_TOO_DEEP})") from None
    return TruthConditions.from_dict(d.get("truth", {}), f"[truth] of {scene_spec}")


class Relaxation:
    """Standard linear solid on the tip's force: F = (1 - g) F_e + g h, dh/dt = dF_e/dt - h / tau, where F_e is the
    elastic force at the current indentation (relaxation function 1 - g (1 - exp(-t/tau))). Out of contact the state
    is reset (the tissue recovers while the tip is away: seconds between probes against tau)."""

    def __init__(self, fraction: float, tau_s: float):
        self.g, self.tau = float(fraction), float(tau_s)
        self.h = 0.0
        self.fe = 0.0

    def step(self, fe: float, dt: float) -> None:
        """Advance by ``dt`` to the elastic force ``fe`` (exact for F_e linear over the step)."""
        if fe <= 0.0:
            self.h, self.fe = 0.0, 0.0
            return
        a = math.exp(-dt / self.tau)
        self.h = self.h * a + (fe - self.fe) * (1.0 - a) * self.tau / dt
        self.fe = fe

    def force(self, fe: float) -> float:
        """The force now, for the elastic force ``fe`` at the current indentation."""
        if fe <= 0.0:
            return 0.0
        return max((1.0 - self.g) * fe + self.g * (self.h + fe - self.fe), 0.0)
