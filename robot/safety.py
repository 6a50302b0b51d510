"""Safety guards for probing: hard caps, plan validation, and a guarded control interface.

Every motion command the driver sends goes through ``GuardedControl``, which checks it *before* forwarding it to
ur_rtde (or the simulated arm) and raises ``SafetyViolation`` instead of sending anything unsafe:

* only ``moveL`` moves (straight lines): with a convex workspace box, a segment whose end points lie in the box
  stays in it, so checking targets checks whole paths (``moveJ``, ``speedL``, ``servoL``, ``forceMode`` and
  ``moveUntilContact`` -- which has no distance limit -- are refused);
* every target is finite and its TCP position lies in the workspace box (the plan's box, clamped to a hard box);
* a target below the undeformed tissue surface (inside its footprint) lies no deeper than the depth limit (itself
  clamped below the tip radius: deeper, the contact model does not hold and the tissue wraps the tip), is
  approached at probe speed (<= ``HARD_PROBE_SPEED_M_S``) with the tool axis within 10 deg of the inward normal;
* speeds and accelerations never exceed the plan's caps, themselves clamped to hard caps;
* ``setTcp``/``setPayload`` arguments are plausible.

The force limit is enforced by the driver's force monitor, whose threshold is ``SafetyLimits.force_limit_n`` (the
plan's limit, clamped to ``HARD_FORCE_LIMIT_N``); no other force threshold can exceed it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core import ur5e
from core.contracts import (  # noqa: F401  (re-exported: the driver's hard caps are core's)
    DEFAULT_TIP_RADIUS_M,
    HARD_ACCEL_M_S2,
    HARD_DEPTH_LIMIT_M,
    HARD_FORCE_LIMIT_N,
    HARD_PROBE_SPEED_M_S,
    HARD_TOOL_SPEED_M_S,
    MAX_APPROACH_HEIGHT_M,
    MAX_FORCE_EXPONENT,
    MIN_APPROACH_HEIGHT_M,
    MIN_FORCE_EXPONENT,
    NOISE_SAMPLE_S,
    RETRACT_SPEED_M_S,
    ZERO_SETTLE_S,
)

HARD_BOX_MIN_M = (-0.85, -0.85, -0.2)
HARD_BOX_MAX_M = (0.85, 0.85, 1.0)
MAX_TCP_OFFSET_M = 0.3
MAX_PAYLOAD_KG = 5.0
MAX_TILT_RAD = math.radians(10.0)
POSE_TOL_M = 5e-4                  # plan poses must match x_m/depth_m/approach height to this


class SafetyViolation(Exception):
    """A command or plan that would break a safety limit; nothing was sent."""


@dataclass(frozen=True)
class SafetyLimits:
    box_min: tuple
    box_max: tuple
    force_limit_n: float
    depth_limit_m: float
    tool_speed_m_s: float
    probe_speed_m_s: float
    accel_m_s2: float
    tissue_pose_base: tuple
    width_m: float
    tip_radius_m: float = DEFAULT_TIP_RADIUS_M
    length_m: float = 0.0                  # a 3D block's extent along tissue y; 0: a 2D section (probes at y = 0)

    @staticmethod
    def from_plan(plan) -> "SafetyLimits":
        lim, mo = plan.limits, plan.motion
        lo = tuple(max(a, b) for a, b in zip(lim.workspace_min_m, HARD_BOX_MIN_M))
        hi = tuple(min(a, b) for a, b in zip(lim.workspace_max_m, HARD_BOX_MAX_M))
        # Plan.check requires the width; a plan built in code without it gets the conservative reading: the depth
        # limit then applies at every x, not only over a guessed tissue
        tissue = plan.scene.get("tissue", {}) if isinstance(plan.scene, dict) else {}
        width = float(tissue.get("width_m", math.inf)) if isinstance(tissue, dict) else math.inf
        length = tissue.get("length_m") if isinstance(tissue, dict) else None
        length = float(length) if isinstance(length, (int, float)) and not isinstance(length, bool) else 0.0
        tip = _tip_radius(plan)
        return SafetyLimits(
            box_min=lo, box_max=hi,
            force_limit_n=min(lim.force_limit_n, HARD_FORCE_LIMIT_N),
            # strictly below the tip radius (a depth equal to it is refused too)
            depth_limit_m=min(lim.depth_limit_m, HARD_DEPTH_LIMIT_M, tip * (1 - 1e-9)),
            tool_speed_m_s=min(lim.max_tool_speed_m_s, HARD_TOOL_SPEED_M_S),
            probe_speed_m_s=min(mo.probe_speed_m_s, lim.max_tool_speed_m_s, HARD_PROBE_SPEED_M_S),
            accel_m_s2=min(max(mo.approach_accel_m_s2, mo.probe_accel_m_s2), HARD_ACCEL_M_S2),
            tissue_pose_base=tuple(plan.frames.tissue_pose_base), width_m=width, tip_radius_m=tip,
            length_m=length if math.isfinite(length) and length > 0 else 0.0)


def _tip_radius(plan) -> float:
    """The tip radius from the plan's scene; the smallest plausible value when it is missing or not a number."""
    ind = plan.scene.get("indenter", {}) if isinstance(plan.scene, dict) else {}
    r = ind.get("radius_m", DEFAULT_TIP_RADIUS_M) if isinstance(ind, dict) else None
    ok = isinstance(r, (int, float)) and not isinstance(r, bool) and math.isfinite(r) and r > 0
    return float(r) if ok else 0.0


class TissueFrame:
    """Base <-> tissue frame (planfile.py): x along the section, z the outward normal; depth = -z."""

    def __init__(self, tissue_pose_base):
        T = ur5e.pose_to_T(tissue_pose_base)
        self.R, self.o = T[:3, :3], T[:3, 3]
        self.normal = self.R[:, 2].copy()
        self._rows = tuple(tuple(T[i, :].tolist()) for i in range(3))     # (R[i, :], o[i]) as Python floats

    def local(self, p) -> np.ndarray:
        return self.R.T @ (np.asarray(p[:3], dtype=float) - self.o)

    def x_depth(self, pose) -> tuple[float, float]:
        p = self.local(pose)
        return float(p[0]), float(-p[2])

    def xy_depth(self, pose) -> tuple[float, float, float]:
        """(x_m, y_m, depth_m) of a pose's position in the tissue frame: written out element by element, the same
        operations as ``xy_depth_many``, so the two agree exactly."""
        (r00, r01, r02, o0), (r10, r11, r12, o1), (r20, r21, r22, o2) = self._rows
        dx, dy, dz = float(pose[0]) - o0, float(pose[1]) - o1, float(pose[2]) - o2
        return r00 * dx + r10 * dy + r20 * dz, r01 * dx + r11 * dy + r21 * dz, -(r02 * dx + r12 * dy + r22 * dz)

    def xy_depth_many(self, P: np.ndarray):
        """``xy_depth`` of many positions (rows of ``P``, x y z first): arrays x_m, y_m, depth_m."""
        (r00, r01, r02, o0), (r10, r11, r12, o1), (r20, r21, r22, o2) = self._rows
        dx, dy, dz = P[:, 0] - o0, P[:, 1] - o1, P[:, 2] - o2
        return r00 * dx + r10 * dy + r20 * dz, r01 * dx + r11 * dy + r21 * dz, -(r02 * dx + r12 * dy + r22 * dz)

    def tilt(self, pose) -> float:
        """Angle between the tool z axis and the inward normal (rad)."""
        z = ur5e.rotvec_to_matrix(pose[3:6])[:, 2]
        return math.acos(max(-1.0, min(1.0, float(-z @ self.normal))))


def _finite(v, n) -> bool:
    try:
        return len(v) == n and all(isinstance(a, (int, float)) and math.isfinite(a) for a in v)
    except TypeError:
        return False


def check_pose(lim: SafetyLimits, tf: TissueFrame, pose, speed: float, accel: float) -> None:
    """Raise SafetyViolation unless a moveL to ``pose`` at ``speed``/``accel`` is safe."""
    if not _finite(pose, 6):
        raise SafetyViolation(f"pose {pose!r} is not 6 finite numbers")
    if not (isinstance(speed, (int, float)) and 0 < speed <= lim.tool_speed_m_s + 1e-12):
        raise SafetyViolation(f"speed {speed!r} m/s outside (0, {lim.tool_speed_m_s}]")
    if not (isinstance(accel, (int, float)) and 0 < accel <= lim.accel_m_s2 + 1e-12):
        raise SafetyViolation(f"acceleration {accel!r} m/s^2 outside (0, {lim.accel_m_s2}]")
    for k in range(3):
        if not (lim.box_min[k] <= pose[k] <= lim.box_max[k]):
            raise SafetyViolation(f"target {[round(v, 4) for v in pose[:3]]} m leaves the workspace box "
                                  f"{list(lim.box_min)}..{list(lim.box_max)}")
    x, depth = tf.x_depth(pose)
    if depth > 0 and -1e-3 <= x <= lim.width_m + 1e-3:
        if depth > lim.depth_limit_m + 1e-9:
            raise SafetyViolation(f"target {depth * 1e3:.2f} mm below the surface exceeds the depth limit "
                                  f"{lim.depth_limit_m * 1e3:.2f} mm")
        if speed > lim.probe_speed_m_s + 1e-12:
            raise SafetyViolation(f"speed {speed} m/s into tissue exceeds the probe speed {lim.probe_speed_m_s}")
        if tf.tilt(pose) > MAX_TILT_RAD:
            raise SafetyViolation(f"tool axis {math.degrees(tf.tilt(pose)):.1f} deg off the inward normal")


def check_plan(plan) -> tuple[list[str], dict[int, str]]:
    """(plan-wide problems, {probe index: problem}) -- empty when the plan is safe to execute as written."""
    lim, tf, mo = SafetyLimits.from_plan(plan), TissueFrame(plan.frames.tissue_pose_base), plan.motion
    problems, bad = [], {}
    L = plan.limits
    if L.force_limit_n > HARD_FORCE_LIMIT_N:
        problems.append(f"force_limit_n {L.force_limit_n} N exceeds the hard cap {HARD_FORCE_LIMIT_N} N")
    if L.depth_limit_m > HARD_DEPTH_LIMIT_M:
        problems.append(f"depth_limit_m {L.depth_limit_m} exceeds the hard cap {HARD_DEPTH_LIMIT_M} m")
    if L.depth_limit_m >= lim.tip_radius_m:
        problems.append(f"depth_limit_m {L.depth_limit_m} m is not below the tip radius {lim.tip_radius_m} m "
                        f"(scene.indenter.radius_m)")
    if not (0 < mo.probe_speed_m_s <= lim.probe_speed_m_s):
        problems.append(f"motion.probe_speed_m_s {mo.probe_speed_m_s} outside (0, {lim.probe_speed_m_s}]")
    if not (0 < mo.approach_speed_m_s <= lim.tool_speed_m_s):
        problems.append(f"motion.approach_speed_m_s {mo.approach_speed_m_s} outside (0, {lim.tool_speed_m_s}]")
    for name in ("approach_accel_m_s2", "probe_accel_m_s2"):
        v = getattr(mo, name)
        if not (0 < v <= HARD_ACCEL_M_S2):
            problems.append(f"motion.{name} {v} outside (0, {HARD_ACCEL_M_S2}]")
    if not (0 < mo.contact_threshold_n < lim.force_limit_n):
        problems.append(f"motion.contact_threshold_n {mo.contact_threshold_n} outside (0, force limit)")
    if not (MIN_APPROACH_HEIGHT_M <= mo.approach_height_m <= MAX_APPROACH_HEIGHT_M):
        problems.append(f"motion.approach_height_m {mo.approach_height_m} outside [{MIN_APPROACH_HEIGHT_M:g}, "
                        f"{MAX_APPROACH_HEIGHT_M:g}] m")
    if not (0 <= mo.dwell_s <= 10):
        problems.append(f"motion.dwell_s {mo.dwell_s} outside [0, 10] s")
    off = plan.frames.tcp_offset
    if math.dist(off[:3], (0, 0, 0)) > MAX_TCP_OFFSET_M:
        problems.append(f"frames.tcp_offset {off} longer than {MAX_TCP_OFFSET_M} m")
    if not off[2] > 0:
        problems.append(f"frames.tcp_offset {off}: z must be positive (the tip beyond the flange)")
    seen = set()
    for p in plan.probes:
        why = None
        if p.index in seen:
            why = "duplicate index"
        elif not (0 <= p.x_m <= lim.width_m):
            why = f"x_m {p.x_m} outside the tissue [0, {lim.width_m}]"
        elif not (0 <= p.y_m <= lim.length_m):
            why = f"y_m {p.y_m} outside the tissue [0, {lim.length_m}]"
        elif not (0 < p.depth_m < lim.tip_radius_m):
            why = f"depth_m {p.depth_m} outside (0, tip radius {lim.tip_radius_m}) m"
        elif not (0 < p.depth_m <= lim.depth_limit_m):
            why = f"depth_m {p.depth_m} outside (0, depth limit {lim.depth_limit_m}]"
        elif not (0 <= p.predicted_force_n <= lim.force_limit_n):
            why = f"predicted_force_n {p.predicted_force_n} outside [0, force limit {lim.force_limit_n}]"
        elif p.force_exponent is not None and (not isinstance(p.force_exponent, (int, float))
                                               or isinstance(p.force_exponent, bool)
                                               or not MIN_FORCE_EXPONENT <= p.force_exponent <= MAX_FORCE_EXPONENT):
            why = (f"force_exponent {p.force_exponent} outside [{MIN_FORCE_EXPONENT:g}, {MAX_FORCE_EXPONENT:g}] "
                   f"(or null)")
        else:
            for name, pose, want in (("approach_pose", p.approach_pose, -mo.approach_height_m),
                                     ("indent_pose", p.indent_pose, p.depth_m)):
                x, y, d = tf.xy_depth(pose)
                off = max(abs(x - p.x_m), abs(d - want), abs(y - p.y_m))
                if off > POSE_TOL_M or tf.tilt(pose) > MAX_TILT_RAD:
                    why = (f"{name} does not match x_m/y_m/depth_m/approach height in the tissue frame given by "
                           f"frames.tissue_pose_base and frames.tcp_offset (off by {off:.3g} m, tilted "
                           f"{tf.tilt(pose):.3g} rad; frames edited after planning? plan again)")
                    break
                try:
                    check_pose(lim, tf, pose, mo.probe_speed_m_s, min(mo.probe_accel_m_s2, lim.accel_m_s2))
                except SafetyViolation as e:
                    why = f"{name}: {e}"
                    break
            if why is None:
                why = _joints_disagree(p, plan.frames.tcp_offset) or _arm_not_clear(p, lim, tf)
        seen.add(p.index)
        if why:
            bad[p.index] = why
    return problems, bad


class GuardedControl:
    """Wraps an RTDE control interface; every command is checked before it is forwarded. ``sent`` logs them."""

    _PASS = {"stopL", "stopJ", "speedStop", "stopScript", "zeroFtSensor", "getAsyncOperationProgress", "isSteady",
             "isConnected", "reconnect", "isProgramRunning", "initPeriod", "waitPeriod", "disconnect",
             "isPoseWithinSafetyLimits", "triggerProtectiveStop", "reuploadScript"}

    def __init__(self, rtde_c, limits: SafetyLimits):
        self._c, self.limits, self.tf = rtde_c, limits, TissueFrame(limits.tissue_pose_base)
        self.sent: list[tuple] = []

    def moveL(self, pose, speed, acceleration, asynchronous=False):
        pose = [float(v) for v in pose] if _finite(pose, 6) else pose
        check_pose(self.limits, self.tf, pose, speed, acceleration)
        self.sent.append(("moveL", tuple(pose), speed, acceleration))
        return self._c.moveL(pose, speed, acceleration, asynchronous)

    def setTcp(self, pose):
        if not _finite(pose, 6) or math.dist(pose[:3], (0, 0, 0)) > MAX_TCP_OFFSET_M:
            raise SafetyViolation(f"TCP offset {pose!r} implausible")
        self.sent.append(("setTcp", tuple(pose)))
        return self._c.setTcp(list(pose))

    def setPayload(self, mass, cog):
        if not (0 <= mass <= MAX_PAYLOAD_KG) or not _finite(cog, 3):
            raise SafetyViolation(f"payload {mass} kg at {cog} implausible")
        self.sent.append(("setPayload", mass, tuple(cog)))
        return self._c.setPayload(mass, list(cog))

    def setWatchdog(self, min_frequency):
        if not (isinstance(min_frequency, (int, float)) and 1.0 <= min_frequency <= 500.0):
            raise SafetyViolation(f"watchdog frequency {min_frequency!r} Hz outside [1, 500]")
        self.sent.append(("setWatchdog", float(min_frequency)))
        return self._c.setWatchdog(float(min_frequency))

    def kickWatchdog(self):
        return self._c.kickWatchdog()

    def __getattr__(self, name):
        if name in self._PASS:
            return getattr(self._c, name)
        raise SafetyViolation(f"{name} is not allowed through the guarded interface")


def move_time(dist, v, a) -> float:
    return dist / v + v / a


def preflight(plan, done=()) -> dict:
    """What the operator sees before the arm moves: limits, counts, estimated time, problems."""
    lim, mo = SafetyLimits.from_plan(plan), plan.motion
    problems, bad = check_plan(plan)
    todo = [p for p in plan.probes if p.index not in set(done) and p.index not in bad]
    t, prev = 0.0, None
    for p in todo:
        if prev is not None:
            t += move_time(math.dist(prev[:3], p.approach_pose[:3]), mo.approach_speed_m_s, mo.approach_accel_m_s2)
        h = mo.approach_height_m + p.depth_m
        t += (2 * ZERO_SETTLE_S + NOISE_SAMPLE_S + move_time(h, mo.probe_speed_m_s, mo.probe_accel_m_s2) + mo.dwell_s
              + move_time(h, RETRACT_SPEED_M_S, mo.probe_accel_m_s2))      # as planner.timing counts a probe
        prev = p.approach_pose
    return {"workspace_min_m": list(lim.box_min), "workspace_max_m": list(lim.box_max),
            "force_limit_n": lim.force_limit_n, "depth_limit_m": lim.depth_limit_m,
            "probe_speed_m_s": lim.probe_speed_m_s, "n_probes": len(plan.probes), "n_done": len(set(done)),
            "n_to_run": len(todo), "estimated_time_s": round(t, 1), "problems": problems,
            "rejected_probes": {str(k): v for k, v in bad.items()}}


# a probe's joint targets must reach its pose (with the plan's TCP) to this: the planner's agree to about 1e-15 m
# (an independent review's forward kinematics, 51 plans); 1 mm let a tool offset edited by 0.9 mm through, the tip
# then 0.9 mm deeper than the depth limit (session 47's review)
JOINT_TOL_M = 1e-5
JOINT_LIMIT_RAD = 2 * math.pi   # UR5e: every joint within +-360 deg


def _arm_not_clear(p, lim, tf) -> str | None:
    """Why the flange would go into the tissue at a probe's joint targets, or None: a tool offset whose rotation turns
    the flange towards the tissue puts it on the tissue's side of the surface (a session-47 review: a tool rotated
    180 degrees about x was planned with the flange 0.1 m under the surface, and accepted). The arm's other links are
    not checked (no model of where the arm is mounted: the test fixtures' own elbow-down plans put the elbow 0.12 m
    below the base)."""
    for name, q in (("q_approach_rad", p.q_approach_rad), ("q_indent_rad", p.q_indent_rad)):
        depth = tf.xy_depth([*ur5e.fk_flange(q)[:3, 3], 0.0, 0.0, 0.0])[2]
        if depth >= 0.0:
            return (f"{name}: the flange lies {depth:.3g} m inside the tissue's surface (the tool offset's rotation "
                    f"turns the flange towards the tissue?)")
    return None


def _joints_disagree(p, tcp_offset) -> str | None:
    """Why a probe's joint targets (the planner's inverse kinematics) do not reach its poses with the plan's TCP, or
    None. The driver moves by pose, so the joints are not sent; but a plan whose tool offset, tip or poses were
    edited after planning no longer agrees with them (the safety review of session 38: a tool offset edited from
    0.1 m to 0 sent the real tip 0.1 m into the tissue), and a pose with no joint solution cannot be reached."""
    T_tcp = ur5e.pose_to_T(tcp_offset)
    for name, q, pose in (("q_approach_rad", p.q_approach_rad, p.approach_pose),
                          ("q_indent_rad", p.q_indent_rad, p.indent_pose)):
        if len(q) != 6 or not all(abs(v) <= JOINT_LIMIT_RAD for v in q):      # NaN fails too
            return f"{name} {list(q)} is not 6 joints within the UR5e's +-2 pi range"
        T = ur5e.fk_flange(q) @ T_tcp
        P = ur5e.pose_to_T(pose)
        off = float(np.linalg.norm(T[:3, 3] - P[:3, 3]))
        turn = float(np.linalg.norm(T[:3, :3] - P[:3, :3]))
        if not (off <= JOINT_TOL_M and turn <= 10 * JOINT_TOL_M):
            return (f"{name} does not reach its pose with frames.tcp_offset (off by {off:.3g} m; the tool offset, "
                    f"the tip or the poses edited after planning? plan again)")
    return None
