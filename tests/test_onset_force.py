"""The contact onset's true force (session 38): a probe record carries the zero-force reading at the moment contact
was noticed (the free-air baseline's straight line in time, so the drift since the zeroing is in it), and the
localizer takes the onset's force as the threshold less that reading, less the first noisy crossing's 1.25 sigma."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from core.contracts import FILTER_WINDOW, Probe, ProbeStatus  # noqa: E402
from planner.localize import ONSET_BIAS_SIGMAS, Measurements  # noqa: E402
from robot.records import DESCENT, DWELL, summarise  # noqa: E402

DRIFT_N_PER_S, OFFSET_N, THRESHOLD_N, NOISE_N = 5e-4, 2e-3, 0.02, 3e-3


def _raw(period_s=0.002, speed_m_s=0.002, top_m=-0.006, bottom_m=0.003, dwell_s=0.5, seed=1):
    """A descent from 6 mm above the surface to 3 mm into it and a dwell, read by a sensor that drifts (zeroed at
    t = 0) with noise; the tissue pushes back from depth 0 (100 N/m^1.5-ish: the shape does not matter here)."""
    rng = np.random.default_rng(seed)
    n_d = int(round((bottom_m - top_m) / speed_m_s / period_s))
    n_w = int(round(dwell_s / period_s))
    t = np.arange(n_d + n_w) * period_s
    depth = np.r_[top_m + speed_m_s * period_s * np.arange(n_d), np.full(n_w, bottom_m)]
    true = 30.0 * np.maximum(depth, 0.0) ** 1.2
    f = true + OFFSET_N + DRIFT_N_PER_S * t + rng.normal(0.0, NOISE_N, len(t))
    ph = np.r_[np.full(n_d, DESCENT), np.full(n_w, DWELL)]
    return {"time_s": t, "force_n": f, "depth_m": depth, "x_m": np.full(len(t), 0.02), "phase": ph,
            "tcp_pose": np.zeros((len(t), 6)), "wrench": np.zeros((len(t), 6))}, true


def test_the_record_has_the_zero_force_reading_at_the_contact():
    raw, true = _raw()
    filt = np.convolve(raw["force_n"], np.ones(FILTER_WINDOW) / FILTER_WINDOW)[: len(true)]
    k = int(np.argmax((filt > THRESHOLD_N) & (raw["phase"] == DESCENT)))
    contact = {"depth": float(raw["depth_m"][k]), "x": 0.02, "t": float(raw["time_s"][k])}
    p = Probe(index=0, x_m=0.02, depth_m=0.003, predicted_force_n=0.1, approach_pose=[0.0] * 6,
              indent_pose=[0.0] * 6, q_approach_rad=[0.0] * 6, q_indent_rad=[0.0] * 6)
    rec = summarise(p, raw, ProbeStatus.OK, contact, 0.0, float(raw["time_s"][-1]), THRESHOLD_N, NOISE_N, 0.004)
    want = OFFSET_N + DRIFT_N_PER_S * contact["t"]
    # the line through ~2000 baseline samples: within a few of their noise / sqrt(n) of the truth at the contact
    assert abs(rec.force_baseline_at_contact_n - want) < 4 * NOISE_N / math.sqrt(rec.n_samples_baseline) * 3
    # the baseline's mean alone misses the drift between the baseline's middle and the contact
    assert abs(rec.force_baseline_n - want) > 10 * abs(rec.force_baseline_at_contact_n - want)
    m = Measurements.from_records([rec], statuses=("ok",))
    expect = THRESHOLD_N - rec.force_baseline_at_contact_n - ONSET_BIAS_SIGMAS * NOISE_N / math.sqrt(FILTER_WINDOW)
    assert m.onset_threshold_n[0] == expect
    # and that force is what the tissue pushed with at the onset, to about the noise's crossing allowance
    assert abs(true[k] - m.onset_threshold_n[0]) < 2.5 * NOISE_N / math.sqrt(FILTER_WINDOW)


def test_an_older_record_without_it_uses_the_baseline():
    raw, _ = _raw()
    p = Probe(index=0, x_m=0.02, depth_m=0.003, predicted_force_n=0.1, approach_pose=[0.0] * 6,
              indent_pose=[0.0] * 6, q_approach_rad=[0.0] * 6, q_indent_rad=[0.0] * 6)
    rec = summarise(p, raw, ProbeStatus.OK, {"depth": 0.001, "x": 0.02}, 0.0, 1.0, THRESHOLD_N, NOISE_N, 0.004)
    assert rec.force_baseline_at_contact_n is None            # no contact time: as an older record
    m = Measurements.from_records([rec], statuses=("ok",))
    assert m.onset_threshold_n[0] == (THRESHOLD_N - rec.force_baseline_n
                                      - ONSET_BIAS_SIGMAS * NOISE_N / math.sqrt(FILTER_WINDOW))
