"""Property tests: random plans, hostile ones included, never make the driver send a command outside the
workspace box, deeper than the depth limit, faster than the caps, or with a force threshold above the limit."""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, Phase, event, given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).parent))
from robot_fixtures import SCENE, TCP, tissue_point_pose  # noqa: E402

from core import ur5e  # noqa: E402
from core.contracts import Frames, Limits, Motion, Plan, Probe  # noqa: E402
from robot import safety  # noqa: E402
from robot.driver import DriverConfig, run_plan, watchdog_rate_hz  # noqa: E402
from robot.safety import GuardedControl, SafetyLimits, SafetyViolation, TissueFrame  # noqa: E402
from robot.sim import ArmModel, SimRTDEControl, SimRTDEReceive  # noqa: E402
from robot.simforce import standin_force_model  # noqa: E402

ALLOWED = {"moveL", "stopL", "zeroFtSensor", "setTcp", "setPayload", "getAsyncOperationProgress", "initPeriod",
           "waitPeriod", "reconnect", "isConnected", "setWatchdog", "kickWatchdog", "isProgramRunning", "reuploadScript"}


class Recorder:
    """Sits between the guard and the arm: records exactly what reaches the controller."""

    def __init__(self, inner):
        self.inner, self.calls = inner, []

    def __getattr__(self, name):
        fn = getattr(self.inner, name)

        def call(*a, **k):
            self.calls.append((name, a))
            return fn(*a, **k)
        return call


class TrackingArm(ArmModel):
    max_depth_m = -1.0

    def step(self, dt=None):
        super().step(dt)
        x, d = self.tip_in_tissue()
        if 0 <= x <= self.width_m:
            self.max_depth_m = max(self.max_depth_m, d)


def effective(plan):
    L, mo = plan.limits, plan.motion
    lo = [max(a, b) for a, b in zip(L.workspace_min_m, safety.HARD_BOX_MIN_M)]
    hi = [min(a, b) for a, b in zip(L.workspace_max_m, safety.HARD_BOX_MAX_M)]
    return dict(lo=lo, hi=hi, force=min(L.force_limit_n, safety.HARD_FORCE_LIMIT_N),
                depth=min(L.depth_limit_m, safety.HARD_DEPTH_LIMIT_M),
                speed=min(L.max_tool_speed_m_s, safety.HARD_TOOL_SPEED_M_S),
                probe_speed=min(mo.probe_speed_m_s, L.max_tool_speed_m_s, safety.HARD_PROBE_SPEED_M_S))


fl = st.floats


def pick(draw, sane, hostile):
    """Mostly sane values, one in ten hostile (so that most examples move the arm)."""
    return draw(hostile) if draw(st.sampled_from(range(10))) == 9 else draw(sane)


@st.composite
def plans(draw):
    tp = [pick(draw, fl(0.3, 0.45), fl(0.2, 0.6)), pick(draw, fl(-0.15, 0.1), fl(-0.4, 0.4)),
          pick(draw, fl(0.0, 0.2), fl(-0.3, 0.9)), pick(draw, fl(-0.2, 0.2), fl(-0.6, 0.6)),
          pick(draw, fl(-0.2, 0.2), fl(-0.6, 0.6)), draw(fl(-math.pi, math.pi))]
    lo = pick(draw, st.just([-0.8, -0.8, -0.1]), st.lists(fl(-1.0, 0.3), min_size=3, max_size=3))
    hi = pick(draw, st.just([0.8, 0.8, 0.8]), st.just([a + draw(fl(0.05, 1.5)) for a in lo]))
    hi = [max(h, a + 0.01) for a, h in zip(lo, hi)]
    limits = Limits(force_limit_n=pick(draw, fl(0.05, 10.0), fl(0.0, 100.0).filter(lambda v: v > 0)),
                    depth_limit_m=pick(draw, fl(0.001, 0.02), fl(0.0005, 0.05)),
                    workspace_min_m=lo, workspace_max_m=hi,
                    max_tool_speed_m_s=pick(draw, fl(0.05, 0.25), fl(0.001, 5.0)))
    motion = Motion(approach_height_m=pick(draw, fl(0.003, 0.015), fl(-0.01, 0.02)),
                    approach_speed_m_s=pick(draw, fl(0.02, 0.25), fl(0.001, 3.0)),
                    approach_accel_m_s2=pick(draw, fl(0.1, 1.5), fl(0.01, 10.0)),
                    probe_speed_m_s=pick(draw, fl(0.004, 0.01), fl(0.004, 0.05)),
                    probe_accel_m_s2=pick(draw, fl(0.1, 1.5), fl(0.01, 10.0)),
                    contact_threshold_n=pick(draw, fl(0.005, 0.05), fl(-1.0, 5.0)),
                    dwell_s=draw(fl(0.0, 0.2)))
    probes = []
    for i in range(draw(st.integers(1, 3))):
        x = pick(draw, fl(0.0, 0.07), fl(-0.02, 0.09))
        depth = pick(draw, fl(0.0005, limits.depth_limit_m), fl(-0.005, 0.03))
        a = tissue_point_pose(tp, x, motion.approach_height_m)
        d = tissue_point_pose(tp, x, -depth)
        if draw(st.sampled_from(range(8))) == 7:     # hostile: a deeper or tilted indent pose than declared
            d = list(d[:3] - np.asarray(ur5e.pose_to_T(tp)[:3, 2]) * draw(fl(0, 0.01))) + \
                list(np.asarray(d[3:]) + [draw(fl(-0.5, 0.5)), 0.0, 0.0])
        probes.append(Probe(index=pick(draw, st.just(i), st.integers(0, 3)), x_m=x, depth_m=depth,
                            predicted_force_n=pick(draw, fl(0.0, limits.force_limit_n), fl(-1.0, 50.0)),
                            approach_pose=a, indent_pose=d, q_approach_rad=[0.0] * 6, q_indent_rad=[0.0] * 6))
    tcp = pick(draw, st.just(TCP), st.just([0, 0, draw(fl(0.0, 0.6)), 0, 0, 0]))
    fault = draw(st.sampled_from([None, None, None, "protective_stop", "force_spike", "nan", "stall",
                                  "disconnect"]))
    return Plan(scene=SCENE, frames=Frames(tissue_pose_base=tp, tcp_offset=tcp), limits=limits, motion=motion,
                probes=probes), draw(fl(500.0, 1e5)), draw(st.sampled_from(range(5))) > 0, \
        (fault, draw(fl(0.0, 15.0)), draw(fl(0.0, 20.0)))


@settings(max_examples=30, deadline=None, database=None, phases=[Phase.explicit, Phase.reuse, Phase.generate],
          suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                 HealthCheck.too_slow])
@given(plans())
def test_random_plans_never_command_outside_limits(tmp_path_factory, case):
    plan, k, skip_invalid, (fault, at_s, magnitude_n) = case
    out = tmp_path_factory.mktemp("run")
    start = tissue_point_pose(plan.frames.tissue_pose_base, 0.035, 0.03)
    q0 = ur5e.ik(start, ur5e.IK_SEED, plan.frames.tcp_offset)
    arm = TrackingArm(standin_force_model(k_n_per_m15=k), tissue_pose_base=plan.frames.tissue_pose_base,
                      q0=q0, tcp_offset=plan.frames.tcp_offset, sensor="nano17")
    if fault:
        arm.inject(fault, at_s=at_s, magnitude_n=magnitude_n, duration_s=0.02, reconnectable=True)
    c = Recorder(SimRTDEControl(arm))
    rep = run_plan(plan, c, SimRTDEReceive(arm), out, config=DriverConfig(skip_invalid=skip_invalid))
    eff = effective(plan)
    tf = TissueFrame(plan.frames.tissue_pose_base)
    assert {name for name, _ in c.calls} <= ALLOWED
    for name, a in c.calls:
        if name != "moveL":
            continue
        pose, speed, accel = a[0], a[1], a[2]
        assert all(math.isfinite(v) for v in pose)
        assert all(eff["lo"][i] <= pose[i] <= eff["hi"][i] for i in range(3)), (pose, eff)
        assert 0 < speed <= eff["speed"] + 1e-12 and 0 < accel <= safety.HARD_ACCEL_M_S2
        x, depth = tf.x_depth(pose)
        if depth > 0 and -1e-3 <= x <= 0.071:
            assert depth <= eff["depth"] + 1e-9 and speed <= eff["probe_speed"] + 1e-12
    run = json.loads((out / "run.json").read_text())
    assert run["force_stop_threshold_n"] <= eff["force"]
    for rec in rep.records:
        if rec.contact_threshold_n is not None:
            assert rec.contact_threshold_n < eff["force"]
    # what the arm physically did, to rest (a lost link may leave a move running): never deeper than the depth
    # limit, force overshoot bounded by reaction time
    arm.run_until_still(5.0)
    assert arm.max_depth_m <= eff["depth"] + 1e-6
    # overshoot allowance: the force at the stiffest place (over the stone, F = 1.7 k d^1.5) once the probe has gone
    # on past the depth where it reaches the limit, for two control periods of reaction -- or, over a lost link,
    # until the controller's watchdog stops it (1/rate more)
    f = standin_force_model(k_n_per_m15=k)
    d_lim = (eff["force"] / (k * 1.7)) ** (2 / 3)
    reaction_s = 0.004
    if fault == "disconnect":
        reaction_s += 1.0 / watchdog_rate_hz(DriverConfig(), eff["probe_speed"])
    allowed = 1.7 * k * (d_lim + eff["probe_speed"] * reaction_s) ** 1.5 + 0.01
    event(f"peak/limit {arm.max_contact_force_n / eff['force']:.2f}")
    assert arm.max_contact_force_n <= allowed, (arm.max_contact_force_n, eff["force"], allowed)
    assert f(0.035, 0.0) == 0.0
    assert not arm.is_moving or fault == "disconnect"
    event(f"status {rep.status}, {sum(r.status in ('ok', 'force_limit') for r in rep.records)} probed")
    event(f"fault {fault}: {rep.fault and rep.fault['kind']}")


@settings(max_examples=300, deadline=None, database=None)
@given(pose=st.lists(fl(-1.0, 1.0) | st.sampled_from([math.nan, math.inf]), min_size=3, max_size=3),
       rot=st.lists(fl(-4, 4), min_size=3, max_size=3), speed=fl(-1, 5) | st.just(math.nan), accel=fl(-1, 50))
def test_guard_forwards_only_safe_moves(pose, rot, speed, accel):
    plan = Plan(scene=SCENE)
    lim = SafetyLimits.from_plan(plan)
    sent = []

    class Sink:
        def moveL(self, *a):
            sent.append(a)
            return True
    g = GuardedControl(Sink(), lim)
    try:
        g.moveL(pose + rot, speed, accel, True)
    except SafetyViolation:
        assert not sent
        return
    p = sent[0][0]
    assert all(lim.box_min[i] <= p[i] <= lim.box_max[i] for i in range(3))
    assert 0 < sent[0][1] <= lim.tool_speed_m_s and 0 < sent[0][2] <= lim.accel_m_s2
    x, depth = TissueFrame(lim.tissue_pose_base).x_depth(p)
    if depth > 0 and 0 <= x <= lim.width_m:
        assert depth <= lim.depth_limit_m and sent[0][1] <= lim.probe_speed_m_s


def test_forbidden_commands_are_refused():
    g = GuardedControl(SimRTDEControl(ArmModel()), SafetyLimits.from_plan(Plan(scene=SCENE)))
    for name in ("moveUntilContact", "speedL", "servoL", "forceMode", "moveJ"):
        try:
            getattr(g, name)
        except SafetyViolation:
            continue
        raise AssertionError(f"{name} passed the guard")
