"""Force/torque sensor models for the simulated arm: noise, bias, drift, resolution, zeroing.

A reading is ``true wrench + bias + drift(t) + noise - zero_offset``, quantised to the resolution. ``zero()`` (what
ur_rtde's zeroFtSensor does) stores the current reading as the offset, so zeroing in free air removes bias and the
drift accumulated so far -- but not noise, and drift keeps growing afterwards. Forces are in N, torques in N m; the
model works in the base frame (the probe's orientation does not change during a run). Seeded for reproducibility.

Presets
-------
* ``ur5e-builtin``: the UR5e wrist sensor. REFERENCE.md gives precision ~3.5 N and accuracy ~5.5 N; we read the
  precision as a 2-sigma band (noise std 1.75 N per axis), a bias of a few N and a temperature drift of ~0.05 N/s.
  Far coarser than soft-tissue forces (0.1-1 N): with a 2 N force limit the driver refuses to probe with it.
* ``nano17``: a precise external sensor (ATI Nano17 class): resolution ~3 mN, noise std 3 mN, tiny drift.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class SensorSpec:
    name: str
    noise_std_n: float          # white noise per force axis (N)
    noise_std_nm: float         # white noise per torque axis (N m)
    bias_n: float               # std of the random constant force bias per axis (N)
    drift_n_per_s: float        # std of the random linear drift rate per axis (N/s)
    resolution_n: float = 0.0   # quantisation step of the force reading (0: none)
    range_n: float = float("inf")  # readings saturate here


PRESETS = {
    "ur5e-builtin": SensorSpec("ur5e-builtin", noise_std_n=1.75, noise_std_nm=0.05, bias_n=3.0,
                               drift_n_per_s=0.05, resolution_n=0.0, range_n=50.0),
    "nano17": SensorSpec("nano17", noise_std_n=0.003, noise_std_nm=1.5e-5, bias_n=0.05,
                         drift_n_per_s=1e-4, resolution_n=0.003125, range_n=35.0),
    "ideal": SensorSpec("ideal", noise_std_n=0.0, noise_std_nm=0.0, bias_n=0.0, drift_n_per_s=0.0),
}


def spec(preset: str | SensorSpec, **overrides) -> SensorSpec:
    if isinstance(preset, SensorSpec):
        s = preset
    else:
        try:
            s = PRESETS[preset]
        except KeyError:
            raise ValueError(f"unknown sensor preset {preset!r}; known: {', '.join(PRESETS)}") from None
    return replace(s, **overrides) if overrides else s


class Sensor:
    """One simulated F/T sensor. ``read(true_wrench, t_s)`` gives a measured 6-vector."""

    def __init__(self, preset: str | SensorSpec = "nano17", seed: int = 0, **overrides):
        self.spec = spec(preset, **overrides)
        self.rng = np.random.default_rng(seed)
        s = self.spec
        self.bias = np.concatenate([self.rng.normal(0, s.bias_n, 3), self.rng.normal(0, s.bias_n * 0.01, 3)])
        self.drift = np.concatenate([self.rng.normal(0, s.drift_n_per_s, 3), np.zeros(3)])
        self.offset = np.zeros(6)
        self._std = np.array([s.noise_std_n] * 3 + [s.noise_std_nm] * 3)

    def _raw(self, true_wrench, t_s: float) -> np.ndarray:
        w = np.asarray(true_wrench, dtype=float) + self.bias + self.drift * t_s
        if self._std.any():
            w = w + self.rng.normal(0.0, 1.0, 6) * self._std
        return w

    def read(self, true_wrench, t_s: float) -> np.ndarray:
        w = self._raw(true_wrench, t_s) - self.offset
        s = self.spec
        if s.resolution_n > 0:
            w[:3] = np.round(w[:3] / s.resolution_n) * s.resolution_n
        np.clip(w[:3], -s.range_n, s.range_n, out=w[:3])
        return w

    def zero(self, true_wrench, t_s: float, n_average: int = 50) -> None:
        """Take the current reading (including whatever force acts now), averaged over ``n_average`` samples
        (0.1 s at 500 Hz), as the new zero: the offset keeps a noise error of noise_std / sqrt(n_average)."""
        w = np.asarray(true_wrench, dtype=float) + self.bias + self.drift * t_s
        self.offset = w + self.rng.normal(0.0, 1.0, 6) * self._std / np.sqrt(max(1, n_average))
