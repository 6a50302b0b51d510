"""The driver's fast-forward on the in-memory arm (robot.driver._fast_forward over robot.sim's look-ahead): quiet
periods stepped many at once give exactly the run that stepping every period gives -- the same raw samples bit for
bit, the same records, commands, stops, run.json and simulator state -- over force-limit stops, a turning tool,
relaxing tissue on a tilted and offset surface with a drifting sensor, a 3D block with a misregistered tip, a force
model extrapolated beyond its range, and a protective stop mid-descent."""
from __future__ import annotations

import dataclasses
import json
import math
import re
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from robot_fixtures import SCENE, TCP, TISSUE_POSE, make_plan, make_sim, solve_joints  # noqa: E402

from core import ur5e  # noqa: E402
from core.contracts import Frames, Limits, Motion, Plan, Probe  # noqa: E402
from robot.driver import Driver, DriverConfig, window_means  # noqa: E402
from robot.records import load_raw, read_records  # noqa: E402
from robot.recovery import ProbeFault  # noqa: E402
from robot.sim import ArmModel, SimRTDEControl, SimRTDEReceive  # noqa: E402
from robot.simfaults import parse, trigger  # noqa: E402
from robot.simforce import standin_force_model  # noqa: E402
from robot.truth import Relaxation  # noqa: E402

# these tests' plans carry no force exponent and their expectations were set with the rule before session 54
# (tests/conftest.py: exponentless_rule_before_s54)
pytestmark = pytest.mark.usefixtures("exponentless_rule_before_s54")

def _turned(pose, rad):
    T = ur5e.pose_to_T(pose)
    T[:3, :3] = ur5e.rotvec_to_matrix([rad, 0.0, 0.0]) @ T[:3, :3]
    return ur5e.T_to_pose(T)


# when and where, not what happened; and how many periods went at once (0 without fast-forward: compared apart)
WALL_CLOCK = ("out_dir", "wall_s", "wall_time_utc", "detected_unix_s", "periods_fast_forwarded")


def _scrub(d):
    """``d`` without its wall-clock fields, at any depth."""
    if isinstance(d, dict):
        return {k: _scrub(v) for k, v in d.items() if k not in WALL_CLOCK}
    return [_scrub(v) for v in d] if isinstance(d, list) else d


def _failing_below(depth_m: float, error: type):
    """The stand-in force model, raising ``error`` below ``depth_m`` (ValueError: fem's refusal at its range)."""
    base = standin_force_model()

    def f(x, d):
        if d > depth_m:
            raise error("beyond the model's range")
        return base(x, d)
    return f


def _twin_runs(tmp_path, plan, make_arm, config: DriverConfig | None = None, wrap=None):
    """The plan run twice on fresh, equal arms: period by period, then fast-forwarded. ``wrap(arm, c, r)``: the
    interfaces the driver gets instead of the arm's own."""
    out = {}
    for ff in (False, True):
        arm, c, r = make_arm()
        if wrap is not None:
            c, r = wrap(arm, c, r)
        d = Driver(plan, c, r, dataclasses.replace(config or DriverConfig(), fast_forward=ff))
        rep = d.run(tmp_path / str(ff))
        recs = read_records(tmp_path / str(ff))
        run_json = json.loads((tmp_path / str(ff) / "run.json").read_text())
        run = _scrub(run_json)
        out[ff] = dict(rep=rep, recs=[_scrub(dataclasses.asdict(x)) for x in recs], raw=[load_raw(tmp_path / str(ff), x) for x in recs], run=run, arm=arm,
                       sent=list(d.c.sent), n_fast=d.n_fast, run_ff=run_json["periods_fast_forwarded"], next_normal=arm.sensor._normal6().copy(),
                       range=getattr(arm.force_model, "range_report", lambda: None)())
    return out[False], out[True]


def _assert_same(a, b, min_fast=0.7):
    assert a["n_fast"] == 0
    assert a["recs"] == b["recs"]
    for ra, rb in zip(a["raw"], b["raw"]):
        assert ra.keys() == rb.keys()
        for k in ra:
            assert ra[k].shape == rb[k].shape and np.array_equal(ra[k], rb[k], equal_nan=True), k
    assert a["run"] == b["run"] and a["sent"] == b["sent"] and a["range"] == b["range"]
    aa, ab = a["arm"], b["arm"]
    assert aa.t_s == ab.t_s and aa.stops_s == ab.stops_s and aa.max_contact_force_n == ab.max_contact_force_n
    assert aa.motions_ended == ab.motions_ended and aa.protective_stopped == ab.protective_stopped
    assert np.array_equal(aa.T_tcp, ab.T_tcp) and aa.last_input_s == ab.last_input_s
    assert np.array_equal(a["next_normal"], b["next_normal"])          # the sensor's noise stream at the same place
    periods = round(ab.t_s / ab.period_s)
    assert b["n_fast"] >= min_fast * periods, (b["n_fast"], periods)   # it did fast-forward
    assert b["run_ff"] == b["n_fast"] and a["run_ff"] == 0              # and run.json says how much


def test_force_limit_stops_and_a_turning_tool(tmp_path):
    plan = make_plan(xs=(0.01, 0.035, 0.06), depth_m=0.003, predicted=0.1,
                     motion=Motion(approach_height_m=0.004, dwell_s=0.1), limits=Limits(force_limit_n=0.27))
    for i, p in enumerate(plan.probes):
        p.indent_pose = _turned(p.indent_pose, 0.004 * (i + 1))
        p.approach_pose = _turned(p.approach_pose, -0.003)
    solve_joints(plan)
    a, b = _twin_runs(tmp_path, plan, lambda: make_sim(seed=5))
    assert [r["status"] for r in b["recs"]] == ["ok", "force_limit", "ok"]
    _assert_same(a, b)


def test_relaxing_tissue_on_a_tilted_offset_surface_with_a_drifting_sensor(tmp_path):
    plan = make_plan(xs=(0.015, 0.035, 0.055), depth_m=0.003, motion=Motion(approach_height_m=0.006, dwell_s=0.5))

    def arm():
        made = make_sim(seed=11, surface_height_m=lambda x: 8e-4 + (x - 0.035) * math.tan(0.05),
                        surface_tilt_rad=0.05, relaxation=Relaxation(0.25, 0.5))    # (pushing along its normal)
        made[0].sensor.bias[:3] += 0.3 * made[0].n_base
        made[0].sensor.drift[:3] += 0.004 * made[0].n_base
        return made
    a, b = _twin_runs(tmp_path, plan, arm)
    # the surface up to 1.8 mm above the plan's: the last probe stops 4 mm past the contact felt (session 38)
    assert [r["status"] for r in b["recs"]] == ["ok", "ok", "depth_limit"]
    _assert_same(a, b)


def _plan3d(points, depth_m, tissue_pose, width_m, length_m, motion):
    T = ur5e.pose_to_T(tissue_pose)

    def pose(x, y, z):
        Tt = np.eye(4)
        Tt[:3, :3] = T[:3, :3] @ ur5e.rotvec_to_matrix([math.pi, 0, 0])
        Tt[:3, 3] = T[:3, :3] @ [x, y, z] + T[:3, 3]
        return ur5e.T_to_pose(Tt)
    probes = [Probe(index=i, x_m=x, y_m=y, depth_m=depth_m, predicted_force_n=0.05,
                    approach_pose=pose(x, y, motion.approach_height_m), indent_pose=pose(x, y, -depth_m),
                    q_approach_rad=[0.0] * 6, q_indent_rad=[0.0] * 6) for i, (x, y) in enumerate(points)]
    scene = {**SCENE, "tissue": {**SCENE["tissue"], "width_m": width_m, "length_m": length_m}}
    return solve_joints(Plan(scene=scene, frames=Frames(tissue_pose_base=list(tissue_pose), tcp_offset=list(TCP)),
                             limits=Limits(), motion=motion, probes=probes))


def test_a_3d_block_with_a_misregistered_tip(tmp_path):
    """y matters (the force depends on it, off the block's length it is zero) and the physical tip sits 0.5 mm
    beyond and 0.3 mm beside the TCP the driver set (the tip's position is computed from the TCP's rotation)."""
    pose = [0.40, -0.015, 0.020, 0.0, 0.0, math.pi / 2]

    def force(x, y, d):
        return 900.0 * d ** 1.5 * (1.0 + 0.8 * math.exp(-((x - 0.015) ** 2 + (y - 0.012) ** 2) / 2e-5))
    plan = _plan3d([(0.015, 0.012), (0.010, 0.020), (0.020, 0.005)], 0.003, pose, 0.030, 0.030,
                   Motion(approach_height_m=0.004, dwell_s=0.2))
    plan.probes[1].indent_pose = _turned(plan.probes[1].indent_pose, 0.01)
    solve_joints(plan)
    q0 = ur5e.ik(plan.probes[0].approach_pose, ur5e.IK_SEED, TCP)
    tool = [0.0003, 0.0, 0.1005, 0.0, 0.0, 0.0]

    def arm():
        m = ArmModel(force, tissue_pose_base=pose, width_m=0.030, length_m=0.030, seed=2, q0=q0, tcp_offset=TCP,
                     tool_offset=tool)
        return m, SimRTDEControl(m), SimRTDEReceive(m)
    a, b = _twin_runs(tmp_path, plan, arm)
    assert all(r["status"] == "ok" for r in b["recs"])
    assert len({round(r["force_mean_n"], 4) for r in b["recs"]}) == 3
    _assert_same(a, b)


def test_a_force_model_beyond_its_range(tmp_path):
    """The cached force model refuses depths beyond 2 mm (as fem refuses the tip radius): the simulator
    extrapolates and counts those forces for run.json, the same count either way."""
    plan = make_plan(xs=(0.02, 0.05), depth_m=0.003)
    a, b = _twin_runs(tmp_path, plan, lambda: make_sim(_failing_below(0.002, ValueError), seed=4))
    assert b["range"] is not None and b["range"]["samples_beyond_model_range"] > 100
    _assert_same(a, b)


def test_a_protective_stop_mid_descent(tmp_path):
    """The controller's own force limit (0.15 N) is below the plan's: it stops the arm during the first
    descent; the look-ahead ends before that period, which runs one period at a time; the run ends in a fault."""
    plan = make_plan(xs=(0.035, 0.05), depth_m=0.003, limits=Limits(force_limit_n=1.0))
    a, b = _twin_runs(tmp_path, plan, lambda: make_sim(seed=6, safety_force_n=0.15))
    assert b["rep"].status == "fault" and b["rep"].fault["kind"] == "protective_stop"
    assert b["arm"].protective_stopped
    _assert_same(a, b, min_fast=0.5)


def test_a_collision_on_the_way_to_a_probe(tmp_path):
    """The true surface lies 5 mm above the nominal one, the approach pose 2 mm above the nominal: the move to the
    first probe runs into the tissue and the collision watch ends the run (a fault) at the same period."""
    plan = make_plan(xs=(0.035, 0.05), depth_m=0.002, motion=Motion(approach_height_m=0.002),
                     limits=Limits(force_limit_n=0.2))
    a, b = _twin_runs(tmp_path, plan, lambda: make_sim(seed=8, surface_height_m=lambda x: 0.005))
    assert b["rep"].status == "fault" and b["rep"].fault["kind"] == "collision"
    _assert_same(a, b, min_fast=0.5)


def _injected(kind: str, **kw):
    def make():
        made = make_sim(seed=9)
        made[0].inject(kind, **kw)
        return made
    return make


@pytest.mark.parametrize("kind, kw, status", [
    ("force_spike", dict(at_s=1.6, duration_s=0.02, magnitude_n=0.05), "ok"),    # in free air, descending
    ("nan", dict(at_s=2.5, duration_s=0.01), "fault"),
    ("stall", dict(when=lambda arm: arm.tip_xyz()[2] > 0.001), "fault"),
    ("disconnect", dict(at_s=3.0, reconnectable=True), "fault"),
    # across the normal in the tissue: small; the force far off the normal; above the lateral limit (2 N)
    ("side_push", dict(when=lambda arm: arm.tip_in_tissue()[1] > 0.001, duration_s=0.2, magnitude_n=0.02), "ok"),
    ("side_push", dict(when=lambda arm: arm.tip_in_tissue()[1] > 0.002, duration_s=0.2, magnitude_n=1.0), "fault"),
    ("side_push", dict(when=lambda arm: arm.tip_in_tissue()[1] > 0.001, duration_s=0.2, magnitude_n=2.5), "fault"),
])
def test_injected_faults(tmp_path, kind, kw, status):
    """A fault scheduled or acting is stepped one period at a time (the look-ahead refuses it); before and after it
    the quiet periods go at once: the same run either way."""
    plan = make_plan(xs=(0.02, 0.05), depth_m=0.003)
    a, b = _twin_runs(tmp_path, plan, _injected(kind, **kw))
    assert b["rep"].status == status
    _assert_same(a, b, min_fast=0.0)
    assert b["n_fast"] > 0 or kind != "force_spike"


def test_a_long_latency_without_move_tapes(tmp_path):
    """Readings five periods old, and moves stepped pose by pose (no tape: the look-ahead refuses a move without
    one, and takes the waits and dwells)."""
    plan = make_plan(xs=(0.02, 0.035), depth_m=0.003)
    a, b = _twin_runs(tmp_path, plan, lambda: make_sim(seed=12, latency_s=0.01, tape=False))
    _assert_same(a, b, min_fast=0.05)


def test_relaxing_tissue_with_a_force_model_beyond_its_range(tmp_path):
    plan = make_plan(xs=(0.02, 0.05), depth_m=0.003)
    a, b = _twin_runs(tmp_path, plan, lambda: make_sim(_failing_below(0.002, ValueError), seed=13,
                                                       relaxation=Relaxation(0.25, 0.5)))
    assert b["range"]["samples_beyond_model_range"] > 100
    _assert_same(a, b)


def test_a_force_model_failing_where_the_arm_never_goes(tmp_path):
    """The model raises below 2.8 mm; the force limit stops every probe above that. The look-ahead computes the
    path beyond the stop: it must end there, not fail (stepping never asks for that force)."""
    plan = make_plan(xs=(0.02, 0.05), depth_m=0.003, limits=Limits(force_limit_n=0.15))
    a, b = _twin_runs(tmp_path, plan, lambda: make_sim(_failing_below(0.0028, RuntimeError), seed=14))
    assert [r["status"] for r in b["recs"]] == ["force_limit", "force_limit"]
    _assert_same(a, b, min_fast=0.5)


def test_an_unfed_watchdog(tmp_path):
    """With stale_periods 3 the driver never kicks (its kick waits for fresh data: stale < 3 // 4); the
    controller's watchdog stops the program in the first move, with or without the look-ahead."""
    plan = make_plan(xs=(0.02,), depth_m=0.003)
    a, b = _twin_runs(tmp_path, plan, lambda: make_sim(seed=15), config=DriverConfig(stale_periods=3))
    assert b["rep"].status == "fault" and b["arm"].watchdog_fired_s is not None
    _assert_same(a, b, min_fast=0.0)


class _Forwarding:
    """A receive interface wrapping the simulator's (as a test's recorder does): forwards everything, but its force
    reading turns NaN after 2 s."""

    def __init__(self, inner, arm):
        self.inner, self.arm = inner, arm

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def getActualTCPForce(self):
        w = self.inner.getActualTCPForce()
        return [float("nan")] * 6 if self.arm.t_s > 2.0 else w


class _OwnStep(ArmModel):
    """An arm with its own step (a test counting what the arm did)."""
    steps = 0

    def step(self, dt=None):
        self.steps += 1
        super().step(dt)


def test_no_look_ahead_through_a_wrapper_or_a_subclass(tmp_path):
    """Only the simulator's own interfaces over its own arm look ahead: a wrapper's getters and a subclassed arm's
    step are met every period."""
    plan = make_plan(xs=(0.02, 0.05), depth_m=0.003)
    a, b = _twin_runs(tmp_path / "wrapped", plan, lambda: make_sim(seed=1),
                      wrap=lambda arm, c, r: (c, _Forwarding(r, arm)))
    assert b["n_fast"] == 0 and b["rep"].fault["kind"] == "invalid_reading"
    assert a["recs"] == b["recs"]

    def own_step():
        from robot_fixtures import TISSUE_POSE, start_q
        arm = _OwnStep(standin_force_model(), tissue_pose_base=TISSUE_POSE, seed=2, q0=start_q(), tcp_offset=TCP)
        return arm, SimRTDEControl(arm), SimRTDEReceive(arm)
    a, b = _twin_runs(tmp_path / "subclass", plan, own_step)
    assert b["n_fast"] == 0 and b["arm"].steps == a["arm"].steps == round(b["arm"].t_s / b["arm"].period_s)


def _arm_state(arm) -> dict:
    m = arm.motion
    return {"t_s": arm.t_s, "last_input_s": arm.last_input_s, "T_tcp": arm.T_tcp.tolist(),
            "motion": None if m is None else (m.s, m.sdot, m.k), "ended": arm.motions_ended,
            "samples": [(t, list(p), w.tolist()) for t, p, w in arm.samples], "max_f": arm.max_contact_force_n,
            "relax": (arm.relaxation.h, arm.relaxation.fe), "next_normal": arm.sensor.normals_ahead(1).tolist()}


def _driver_state(d) -> dict:
    raw = d.samples.arrays()
    return {"ts": d.ts, "last_ts": d.last_ts, "last_kick_ts": d.last_kick_ts, "stale": d.stale,
            "filt": list(d.filt), **{k: v.tolist() for k, v in raw.items()}}


@pytest.mark.parametrize("periods", [1, 2, 7, 499, 500, 501, 1400])
def test_one_stretch_fast_forwarded_leaves_the_states_of_period_by_period(periods):
    """The arm's and the driver's whole state after ``periods`` quiet periods of a descent into relaxing tissue
    (free air, then contact from about period 1000) equals stepping them one at a time: time, the watchdog's last
    input and the last kick's time, the pose, the move's progress, the readings in flight, the relaxation's state,
    the sensor's noise stream, the filter and the samples."""
    plan = make_plan(xs=(0.035,), depth_m=0.003, motion=Motion(approach_height_m=0.004))
    states = {}
    for ff in (False, True):
        arm, c, r = make_sim(seed=3, relaxation=Relaxation(0.25, 0.5))
        d = Driver(plan, c, r, DriverConfig(fast_forward=ff))
        d._setup()
        p = plan.probes[0]
        d._move(p.approach_pose, 0.05, 0.5, what="to the probe")
        d._zero()
        assert d.c.moveL(p.indent_pose, 0.002, 0.1, True) is True
        before, n0 = arm.t_s, d.n_fast
        with pytest.raises(ProbeFault, match="did not finish"):    # a body that never ends: a time-out
            d._loop((periods - 0.5) * d.cfg.period_s, lambda s: None, quiet=lambda b: b.n)
        assert round((arm.t_s - before) / arm.period_s) == periods
        states[ff] = (_arm_state(arm), _driver_state(d), d.n_fast - n0)
    (sa, da, na), (sb, db, nb) = states[False], states[True]
    assert na == 0 and nb == periods
    assert sa == sb
    assert da == db


@pytest.mark.parametrize("n_prev", [0, 1, 3, 5])
def test_window_means_sum_as_the_filter_does(n_prev):
    """The block filter: each window summed in order, as the per-period filter (a deque, summed left to right)."""
    from collections import deque
    from functools import reduce
    from operator import add
    rng = np.random.default_rng(n_prev)
    prev = deque(rng.normal(size=n_prev).tolist(), maxlen=5)
    f = rng.normal(size=40) * 10.0 ** rng.integers(-8, 3, size=40)
    got = window_means(prev, f, 5)
    q = deque(prev, maxlen=5)
    for i, v in enumerate(f.tolist()):
        q.append(v)
        assert got[i] == reduce(add, q) / len(q)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_look_many_is_look_in_turn(seed):
    """CachedForce.look_many gives each point the force and the range flag look gives it in turn, on fresh caches --
    also for a model that refuses only some depths (not monotone: a later point's refused node must not flag an
    earlier point) and across columns."""
    from robot.simforce import CachedForce

    def model(x, d):
        if abs(d - 0.0030) < 1e-9 or d > 0.0045:        # refuses the 3.0 mm node and everything below 4.5 mm
            raise ValueError("beyond the model's range")
        return 900.0 * d ** 1.5 * (1 + x)
    rng = np.random.default_rng(seed)
    x = np.round(rng.uniform(0.01, 0.0101, 60), 5)             # a few columns (x snapped to 10 um), shared
    x[:2] = x[10:14] = 0.01
    d = np.concatenate([[0.0035, 0.00295], rng.uniform(1e-4, 0.005, 58)])
    d[10:14] = [0.0030, 0.0031, 0.0046, 0.0029]
    one, many = CachedForce(model), CachedForce(model)
    f1, b1 = zip(*(one.look(float(a), float(c)) for a, c in zip(x, d)))
    f2, b2 = many.look_many(x, d, np.zeros(len(x)))
    assert list(f1) == f2.tolist() and list(b1) == b2.tolist()
    assert one.extrapolated == many.extrapolated > 0 and any(b1) and not all(b1)


def test_a_moves_tape_is_what_its_steps_compute_bit_for_bit():
    """robot.sim._Motion.uninterrupted (the tape the look-ahead reads) against step() itself: the same progress, s
    and speed after every step, float for float, over random moves (short, long, started moving, ending within a
    step, under one period's acceleration)."""
    from robot.sim import _Motion
    rng = np.random.default_rng(7)
    for _ in range(300):
        L = float(rng.choice([0.0, 1e-9, rng.uniform(0, 0.3)]))
        m = _Motion(L, float(rng.choice([0.25, 1e-3, rng.uniform(1e-4, 1.0)])),
                    float(rng.choice([1.2, rng.uniform(0.01, 5.0)])), None)
        m.s, m.sdot = float(rng.uniform(0, L)) if rng.random() < 0.3 else 0.0, float(rng.uniform(0, m.v)) * (rng.random() < 0.3)
        dt = float(rng.choice([0.002, 0.008]))
        us, ss, vs = m.uninterrupted(dt)
        got = []
        while True:
            done = m.step(dt)
            got.append((m.progress.hex(), m.s.hex(), m.sdot.hex()))
            if done:
                break
        assert got == [(u.hex(), s.hex(), v.hex()) for u, s, v in zip(us, ss, vs)]


@pytest.mark.parametrize("periods", [1, 37])
def test_the_records_do_not_depend_on_the_looks_length(tmp_path, monkeypatch, periods):
    """The driver takes the leading quiet periods of whatever the simulator computed ahead, so how far it looks
    (robot.driver.FF_PERIODS: 500) changes how many looks a run takes, never what it records."""
    import robot.driver as driver_module
    monkeypatch.setattr(driver_module, "FF_PERIODS", periods)
    plan = make_plan(xs=(0.015, 0.035, 0.055), depth_m=0.003, motion=Motion(approach_height_m=0.006, dwell_s=0.3))

    def arm():
        made = make_sim(seed=12, surface_height_m=lambda x: 5e-4 + (x - 0.035) * math.tan(0.03),
                        relaxation=Relaxation(0.25, 0.5))
        made[0].sensor.drift[:3] += 0.004 * made[0].n_base
        return made
    a, b = _twin_runs(tmp_path, plan, arm)
    assert all(r["status"] == "ok" for r in b["recs"])
    _assert_same(a, b)


def test_a_force_far_off_the_normal(tmp_path):
    """The simulated tissue turned 40 degrees about its y axis through the probe (the plan's normal is not the
    tissue's): the force on the tip points 40 degrees off the normal the tool is held along, past
    FORCE_ANGLE_MAX_RAD once it is two thresholds along it: the fault force_direction, at the same period with the
    look-ahead's blocks (session 55: the side push steps one period at a time; this force comes in blocks)."""
    plan = make_plan(xs=(0.035,), depth_m=0.003)
    T0 = ur5e.pose_to_T(TISSUE_POSE)
    pivot = T0[:3, :3] @ [0.035, 0.0, 0.0] + T0[:3, 3]
    T = np.eye(4)
    T[:3, :3] = T0[:3, :3] @ ur5e.rotvec_to_matrix([0.0, math.radians(40.0), 0.0])
    T[:3, 3] = pivot - T[:3, :3] @ [0.035, 0.0, 0.0]
    a, b = _twin_runs(tmp_path, plan, lambda: make_sim(seed=12, tissue_pose=ur5e.T_to_pose(T)))
    assert b["rep"].fault["kind"] == "force_direction", b["rep"].fault
    deg = int(re.search(r"points (\d+) degrees from the tissue normal", b["rep"].fault["message"]).group(1))
    assert 36 <= deg <= 44          # (the filtered force's direction when it is first judged: noise moves it)
    _assert_same(a, b, min_fast=0.5)


@pytest.mark.parametrize("kind, magnitude_n, status", [("force_spike", -10.0, "fault"), ("side_push", 1.0, "ok")])
def test_a_retract_watched(tmp_path, kind, magnitude_n, status):
    """The retract's watch (session 56), in probe 1's retract: a pull towards the tissue that stops it, a push across
    it within the limits; the quiet retract periods at once (probe 0's, and probe 1's after the push), the same run
    as period by period."""
    def make():
        made = make_sim(seed=9)
        leaving = trigger(parse("nan-leaving-depth-m=0.0015"))    # (a fresh trigger per arm: it remembers the way)
        made[0].inject(kind, when=lambda a: abs(a.tip_in_tissue()[0] - 0.05) < 1e-4 and leaving(a),
                       duration_s=0.2, magnitude_n=magnitude_n)
        return made
    a, b = _twin_runs(tmp_path, make_plan(xs=(0.02, 0.05), depth_m=0.003), make)
    assert b["rep"].status == status, b["rep"].fault
    assert b["rep"].status == "ok" or b["rep"].fault["kind"] == "retract_force"
    _assert_same(a, b, min_fast=0.0)
    # (a fault scheduled or acting refuses the look-ahead: the pull's run ends before any period goes at once)
    assert b["n_fast"] > 0 if status == "ok" else b["n_fast"] == 0
