"""Timing of a raster's moves under the UR joint speed/acceleration limits and the plan's tool speeds.

Every move is a straight tool-space ``moveL`` (trapezoidal speed profile: accelerate, cruise, decelerate). Its time
is the larger of the tool-space profile's time and the time the slowest joint needs for its own travel under the
joint limits (a lower bound that matters when a short Cartesian move turns a wrist a lot). Per probe:

* ``move_in``: previous approach pose -> this approach pose at ``motion.approach_speed_m_s`` (0 for the first probe;
  the arm is assumed to start at the first approach pose),
* ``descend``: approach -> indent pose at ``motion.probe_speed_m_s`` (approach height + depth),
* ``zero``: the sensor zeroed in free air at the approach pose before the descent: a settle, the zeroing, a settle
  and the free-air noise sample (``2 ZERO_SETTLE_S + NOISE_SAMPLE_S``, robot.driver's),
* ``descend``: as above,
* ``dwell``: ``motion.dwell_s``,
* ``retract``: indent -> approach pose at the driver's ``RETRACT_SPEED_M_S`` (at most the tool speed limit) with
  ``motion.probe_accel_m_s2``.

Before session 48 the zeroing was left out and the retract timed at the approach speed: plans were 6-12 % shorter
than the simulated driver took (a helper's phase-by-phase comparison: 0.58 s of 8.60 s a probe on the paper
section, 0.18 s zeroing and 0.41 s retract); with both, within 0.6 % on the paper section, block3d's 7 x 7 grid and
four motion variants. Not in a plan: a probe stopped early by the depth or force limit (shorter), and the move to
a refinement round's first probe from the previous round's last.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from core.contracts import NOISE_SAMPLE_S, RETRACT_SPEED_M_S, ZERO_SETTLE_S
from core.ur5e import MAX_JOINT_ACCEL_RAD_S2, MAX_JOINT_SPEED_RAD_S

ZERO_S = 2 * ZERO_SETTLE_S + NOISE_SAMPLE_S      # the driver's free-air zeroing before each descent


def trapezoid_time(distance: float, v_max: float, a_max: float) -> float:
    """Rest-to-rest time over ``distance`` with speed <= v_max and |acceleration| <= a_max."""
    distance = abs(float(distance))
    if distance == 0.0:
        return 0.0
    if distance >= v_max * v_max / a_max:     # reaches cruise speed
        return distance / v_max + v_max / a_max
    return 2.0 * math.sqrt(distance / a_max)  # triangular profile


@dataclass
class JointLimits:
    speed_rad_s: float = MAX_JOINT_SPEED_RAD_S
    accel_rad_s2: float = MAX_JOINT_ACCEL_RAD_S2


def move_time(p0, p1, q0, q1, v_tool: float, a_tool: float, joints: JointLimits) -> float:
    t_tool = trapezoid_time(float(np.linalg.norm(np.subtract(p1, p0))), v_tool, a_tool)
    dq = float(np.max(np.abs(np.subtract(q1, q0))))
    t_joint = trapezoid_time(dq, joints.speed_rad_s, joints.accel_rad_s2)
    return max(t_tool, t_joint)


@dataclass
class Timing:
    move_in_s: list[float] = field(default_factory=list)
    zero_s: list[float] = field(default_factory=list)
    descend_s: list[float] = field(default_factory=list)
    dwell_s: list[float] = field(default_factory=list)
    retract_s: list[float] = field(default_factory=list)
    t_start_s: list[float] = field(default_factory=list)
    duration_s: list[float] = field(default_factory=list)
    total_s: float = 0.0

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("move_in_s", "zero_s", "descend_s", "dwell_s", "retract_s", "total_s")}


def raster_timing(p_approach, p_indent, q_approach, q_indent, motion, joints: JointLimits | None = None,
                  tool_speed_m_s: float = math.inf) -> Timing:
    """Per-probe and total time. Positions (N, 3) in m, joints (N, 6) in rad; ``motion`` is a planfile.Motion;
    ``tool_speed_m_s``: the plan's tool speed limit (the driver moves no faster)."""
    joints = joints or JointLimits()
    tm = Timing()
    t = 0.0
    for k in range(len(p_approach)):
        move_in = 0.0 if k == 0 else move_time(p_approach[k - 1], p_approach[k], q_approach[k - 1], q_approach[k],
                                               min(motion.approach_speed_m_s, tool_speed_m_s),
                                               motion.approach_accel_m_s2, joints)
        descend = move_time(p_approach[k], p_indent[k], q_approach[k], q_indent[k],
                            min(motion.probe_speed_m_s, tool_speed_m_s), motion.probe_accel_m_s2, joints)
        retract = move_time(p_indent[k], p_approach[k], q_indent[k], q_approach[k],
                            min(RETRACT_SPEED_M_S, tool_speed_m_s), motion.probe_accel_m_s2, joints)
        dur = move_in + ZERO_S + descend + motion.dwell_s + retract
        tm.move_in_s.append(move_in)
        tm.zero_s.append(ZERO_S)
        tm.descend_s.append(descend)
        tm.dwell_s.append(float(motion.dwell_s))
        tm.retract_s.append(retract)
        tm.t_start_s.append(t)
        tm.duration_s.append(dur)
        t += dur
    tm.total_s = t
    return tm
