"""Force/torque sensor models for the simulated arm: noise, bias, drift, resolution, zeroing.

A reading is ``true wrench + bias + drift(t) + noise - zero_offset``, quantised to the resolution. ``zero()`` (what
ur_rtde's zeroFtSensor does) stores the current reading as the offset, so zeroing in free air removes bias and the
drift accumulated so far -- but not noise, and drift keeps growing afterwards. Forces are in N, torques in N m; the
model works in the base frame (the probe's orientation does not change during a run). Seeded for reproducibility.
The presets' datasheet figures are core.contracts.SENSORS (the planner's detectability reads them too).
"""
from __future__ import annotations

import numpy as np

from core.contracts import SensorSpec, sensor_spec

NORMAL_BLOCK = 4096        # noise drawn this many samples ahead (8 s at 500 Hz)


class Sensor:
    """One simulated F/T sensor. ``read(true_wrench, t_s)`` gives a measured 6-vector."""

    def __init__(self, preset: str | SensorSpec = "nano17", seed: int = 0, **overrides):
        self.spec = sensor_spec(preset, **overrides)
        self.rng = np.random.default_rng(seed)
        s = self.spec
        self.bias = np.concatenate([self.rng.normal(0, s.bias_n, 3), self.rng.normal(0, s.bias_n * 0.01, 3)])
        self.drift = np.concatenate([self.rng.normal(0, s.drift_n_per_s, 3), np.zeros(3)])
        self.offset = np.zeros(6)
        self._std = np.array([s.noise_std_n] * 3 + [s.noise_std_nm] * 3)
        self._normals = np.empty((0, 6))          # standard normals drawn ahead, in the generator's order
        self._next = 0                            # the next row of _normals to hand out
        self._noisy = bool(self._std.any())

    def _normal6(self) -> np.ndarray:
        """The next six standard normals: the same stream as rng.normal(0, 1, 6) per call, drawn in blocks."""
        if self._next >= len(self._normals):
            self._normals, self._next = self.rng.standard_normal((NORMAL_BLOCK, 6)), 0
        self._next += 1
        return self._normals[self._next - 1]

    def normals_ahead(self, n: int) -> np.ndarray:
        """The next ``n`` rows of the stream, not handed out (``skip`` hands them out): more blocks are drawn as
        needed, in the generator's order, so the stream stays the same."""
        while len(self._normals) - self._next < n:
            self._normals = np.concatenate([self._normals[self._next:], self.rng.standard_normal((NORMAL_BLOCK, 6))])
            self._next = 0
        return self._normals[self._next:self._next + n]

    def skip(self, n: int) -> None:
        """Hand out ``n`` rows of the stream (after ``normals_ahead`` of at least ``n``)."""
        self._next += n

    def read_many(self, true_wrenches: np.ndarray, t_s: np.ndarray, normals: np.ndarray | None) -> np.ndarray:
        """``read`` of many samples at once (rows), with the stream's ``normals`` (rows; None without noise): the
        same operations element by element, so the same values exactly."""
        w = true_wrenches + self.bias
        w += self.drift * t_s[:, None]
        if self._noisy:
            w += normals * self._std
        w -= self.offset
        s = self.spec
        f = w[:, :3]
        if s.resolution_n > 0:
            f[:] = np.rint(f / s.resolution_n) * s.resolution_n
        np.minimum(np.maximum(f, -s.range_n, out=f), s.range_n, out=f)
        return w

    def _raw(self, true_wrench, t_s: float) -> np.ndarray:
        w = np.asarray(true_wrench, dtype=float) + self.bias
        w += self.drift * t_s
        if self._noisy:
            w += self._normal6() * self._std
        return w

    def read(self, true_wrench, t_s: float) -> np.ndarray:
        w = self._raw(true_wrench, t_s)
        w -= self.offset
        s = self.spec
        f = w[:3]
        if s.resolution_n > 0:
            f[:] = np.rint(f / s.resolution_n) * s.resolution_n
        np.minimum(np.maximum(f, -s.range_n, out=f), s.range_n, out=f)
        return w

    def zero(self, true_wrench, t_s: float, n_average: int = 50) -> None:
        """Take the current reading (including whatever force acts now), averaged over ``n_average`` samples
        (0.1 s at 500 Hz), as the new zero: the offset keeps a noise error of noise_std / sqrt(n_average)."""
        w = np.asarray(true_wrench, dtype=float) + self.bias + self.drift * t_s
        self.offset = w + self._normal6() * self._std / np.sqrt(max(1, n_average))
