"""The in-memory simulated arm: ``ArmModel`` (physics) and the ur_rtde-shaped facades over it.

``ArmModel`` is independent of the RTDE facade, so the simulated controller (robot/simcontroller.py) can drive the
same physics. It holds the TRUE tissue (a ``force_model(x_m, depth_m) -> force_n`` built from the true scene);
the driver only ever sees the plan. Time is simulated: ``step()`` advances one controller period (2 ms); the
facades step on ``waitPeriod`` and inside blocking moves, so a plan runs in seconds of wall time.

Contact physics: the tip (TCP) is expressed in the tissue frame (planfile.py): x along the section, z the outward
normal. Below the undeformed surface (depth = -z > 0, 0 <= x <= width) the tissue pushes the tip outward along +z
with ``force_model(x, depth)``. The wrench reported is the external force ON the tool in the base frame (pressing
into tissue gives a force along the tissue's outward normal), plus the sensor model, delayed by ``latency_s``.

The force model is cached on a grid (robot/simforce.py's ``CachedForce``; ``standin_force_model`` is there too).
"""
from __future__ import annotations

import copy
import datetime
import math
import weakref
from collections import deque
from dataclasses import dataclass

import numpy as np

from core import ur5e
from core.arrays import first_true
from robot.sensor import Sensor
from robot.simforce import CachedForce

PROGRAM_STOP_DECEL_M_S2 = 4.0     # a stopped program brakes a running move (a controlled stop)


class _Motion:
    """A point moving along a path of length L with a trapezoidal speed profile (v, a); stoppable, stallable."""

    def __init__(self, L, v, a, interp):
        self.L, self.v, self.a, self.interp = L, v, a, interp
        self.s, self.sdot, self.a_stop, self.stalled = 0.0, 0.0, None, False
        self.k = 0                # steps taken
        self.plan = None          # the uninterrupted run's s, sdot, T_tcp and pose (rows) after each step

    def step(self, dt):
        self.k += 1
        if self.a_stop is not None:
            self.sdot = max(0.0, self.sdot - self.a_stop * dt)
        elif self.stalled:
            self.sdot = 0.0
        else:
            rem = max(self.L - self.s, 0.0)
            self.sdot = min(self.v, self.sdot + self.a * dt, math.sqrt(2 * self.a * rem))
        self.s = min(self.L, self.s + self.sdot * dt)
        if self.s >= self.L - 1e-12 and self.a_stop is None:
            self.s = self.L
            return True
        return self.a_stop is not None and self.sdot == 0.0

    @property
    def progress(self):
        return self.s / self.L if self.L > 0 else 1.0

    def tape_pose(self, i: int) -> tuple[np.ndarray, list[float]]:
        """(T_tcp, pose) after the uninterrupted run's step ``i`` (from ``plan``)."""
        return self.plan[2][i], self.plan[3][i].tolist()

    def uninterrupted(self, dt: float, max_steps: int = 1_000_000) -> tuple[list[float], list[float], list[float]]:
        """(progress, s, sdot) after each step of ``dt`` from now to the end if nothing stops, stalls or replaces
        the motion: ``step``'s arithmetic, so the values are the ones ``progress``, ``s`` and ``sdot`` will take
        (exactly)."""
        # (min and max written out as CPython evaluates them, the products formed as step() forms them: the same
        # floats, at half the cost of the builtins in this loop of up to thousands of steps per move)
        L, v, a = self.L, self.v, self.a
        a_dt, two_a, end, sqrt = a * dt, 2 * a, L - 1e-12, math.sqrt
        s, sdot, out, ss, vs = self.s, self.sdot, [], [], []
        for _ in range(max_steps):
            rem = L - s
            if 0.0 > rem:
                rem = 0.0
            u = sdot + a_dt
            sdot = v
            if u < sdot:
                sdot = u
            u = sqrt(two_a * rem)
            if u < sdot:
                sdot = u
            u = s + sdot * dt
            s = u if u < L else L
            vs.append(sdot)
            if s >= end:
                out.append(1.0)
                ss.append(L)
                break
            out.append(s / L)
            ss.append(s)
        return out, ss, vs


def _linear_tape(T0, T1, rel, us: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """A linear move's poses at the progress values ``us`` of its uninterrupted run, computed at once: (the T_tcp of
    each step, the pose of each step as rows) -- what ``move_linear``'s interp and ``ArmModel._pose`` compute per
    step, to round-off (the positions exactly; ``rel`` None: the orientation stays T0's, and T1's at the end, so
    each one's rotation vector is computed once: the same floats as row by row)."""
    u = np.asarray(us, dtype=float)
    T = np.zeros((len(u), 4, 4))
    T[:, 3, 3] = 1.0
    T[:, :3, 3] = T0[:3, 3] + u[:, None] * (T1[:3, 3] - T0[:3, 3])
    end = u >= 1
    if rel is None:
        T[:, :3, :3] = T0[:3, :3]
        T[end, :3, :3] = T1[:3, :3]
        r0, r1 = ur5e.matrices_to_rotvecs(np.stack([T0[:3, :3], T1[:3, :3]]))
        rv = np.where(end[:, None], r1, r0)
    else:
        T[:, :3, :3] = T0[:3, :3] @ ur5e.rotvecs_to_matrices(u[:, None] * rel)
        T[end, :3, :3] = T1[:3, :3]
        rv = ur5e.matrices_to_rotvecs(T[:, :3, :3])
    return T, np.concatenate([T[:, :3, 3], rv], axis=1)


class ArmModel:
    """A UR5e-like arm touching the true tissue. All units SI; poses are ur_rtde poses in the base frame.

    Parameters: ``force_model`` (x_m, depth_m) -> N for the TRUE scene; ``tissue_pose_base`` and ``width_m`` place
    the tissue; ``sensor`` a preset name or Sensor; ``q0`` start joints; ``latency_s`` delay of readings;
    ``safety_force_n`` contact force that triggers a protective stop (the controller's own limit);
    ``surface_height_m(x_m)`` how far the TRUE surface lies above the nominal one (robot.truth: registration error;
    None: on it); ``surface_tilt_rad`` the TRUE surface's tilt from the nominal one, rising along the tissue frame's
    x (robot.truth passes the same plane's): the tissue pushes the tip along its own outward normal (frictionless
    contact: no traction along the surface), so the wrench has F sin(tilt) across the nominal normal and F cos(tilt)
    along it; ``relaxation`` a robot.truth.Relaxation (None: elastic tissue). ``length_m``: a 3D block's extent
    along the tissue frame's y (``force_model(x_m, y_m, depth_m)``, contact over 0 <= y <= length); None: a 2D
    section (``force_model(x_m, depth_m)``, the same force at every y).
    """

    def __init__(self, force_model=None, tissue_pose_base=(0.35, -0.035, 0.05, 0, 0, 0), width_m=0.07,
                 sensor="nano17", seed=0, q0=None, tcp_offset=(0, 0, 0, 0, 0, 0), period_s=0.002,
                 latency_s=0.002, safety_force_n=30.0, cache=True, tool_offset=None, surface_height_m=None,
                 relaxation=None, length_m: float | None = None, tape: bool = True, surface_tilt_rad: float = 0.0):
        self.length_m = length_m
        self.tape = tape                  # linear moves precompute their poses (vectorised; the same to round-off)
        self._tape_pose = None            # (T_tcp, pose) of the tape's current step
        f = force_model or ((lambda x, y, d: 0.0) if length_m is not None else (lambda x, d: 0.0))
        self.surface_height_m = surface_height_m
        self.relaxation = relaxation
        if cache:
            self.force_model = CachedForce(f, three_d=length_m is not None)
        else:
            self.force_model = (lambda x, d, y=0.0: f(x, y, d)) if length_m is not None else f
        self.T_tissue = ur5e.pose_to_T(tissue_pose_base)
        self.n_base = self.T_tissue[:3, 2].copy()
        # the direction of the tissue's force on the tip: the TRUE surface's outward normal, in the base frame
        self.push_base = (math.cos(surface_tilt_rad) * self.n_base - math.sin(surface_tilt_rad) * self.T_tissue[:3, 0]
                          if surface_tilt_rad else self.n_base)
        self.width_m = width_m
        self.sensor = sensor if isinstance(sensor, Sensor) else Sensor(sensor, seed=seed)
        # a truth condition's bias and drift along the tissue normal, in any sensor on the arm (robot.simarm adds them
        # to the wrist sensor's model; a simulated external box adds them in its own frame: robot.simnetft)
        self.normal_bias_n, self.normal_drift_n_per_s = 0.0, 0.0
        self.period_s, self.safety_force_n = period_s, safety_force_n
        self.t_s = 0.0
        self.q = np.array(ur5e.Q_HOME if q0 is None else q0, dtype=float)
        self.tcp_offset = list(tcp_offset)          # the TCP the program set (what poses are reported for)
        # the probe's tip as mounted on the flange: the physics (contact) is at the tip whatever TCP is set
        self.tool_offset = list(tcp_offset if tool_offset is None else tool_offset)
        self._T_tool = ur5e.pose_to_T(self.tool_offset)
        self._set_tip()
        # the tissue frame as rows (R[0, :], o[0]), ... of Python floats: tip_xyz's arithmetic
        self._frame = tuple(tuple(self.T_tissue[i, :].tolist()) for i in range(3))
        self._rotvec_key, self._rotvec = None, None     # the last rotation reported and its rotation vector
        self.T_tcp = ur5e.fk_flange(self.q) @ ur5e.pose_to_T(self.tcp_offset)
        self._q_stale = False
        self.motion: _Motion | None = None
        self.motion_kind = None
        self.motions_ended = 0            # count of finished/stopped motions (async progress toggles -1/-2)
        self.protective_stopped = False
        self.program_running = True       # ur_rtde's control script on the controller
        self.watchdog_hz = 0.0            # rtde_set_watchdog: the program stops when inputs stop for 1/hz
        self.last_input_s = 0.0
        self.watchdog_fired_s = None
        self.start_program_at_s = None    # a re-uploaded program starts running then
        self.connected = True
        self.reconnectable = True
        self.payload = (0.0, [0.0, 0.0, 0.0])
        self.faults: list[dict] = []
        self._spike_until, self._spike_n, self._nan_until = -1.0, 0.0, -1.0
        self._side_until, self._side = -1.0, np.zeros(3)     # a side push: its end (s) and force (N, base frame)
        self.max_contact_force_n = 0.0
        self.control = None               # a weak reference to the control facade over this arm, if any
        self.on_step: list = []           # called after every step (a simulated external sensor samples there)
        self.stops_s: list = []
        n_lat = max(0, int(round(latency_s / period_s)))
        self.samples: deque = deque(maxlen=n_lat + 1)
        self._sample()

    # ---- state -------------------------------------------------------------------------------------------
    @property
    def tcp_pose(self) -> list[float]:
        return ur5e.T_to_pose(self.T_tcp)

    @property
    def q_is_current(self) -> bool:
        """True when ``q`` matches the TCP pose without an IK solve (``joints()`` is then cheap); False during a
        linear move, where ``joints()`` solves IK (~0.5 ms)."""
        return not self._q_stale

    def joints(self) -> np.ndarray:
        if self._q_stale:
            q = ur5e.ik(ur5e.T_to_pose(self.T_tcp), self.q, self.tcp_offset)
            if q is not None:
                self.q = q
            self._q_stale = False
        return self.q.copy()

    def tip_xyz(self) -> tuple[float, float, float]:
        """(x_m, y_m, depth_m) of the probe's physical tip (``tool_offset``) in the tissue frame; depth > 0 below the
        undeformed surface. Written out element by element (Python floats), the same operations in the same order
        as ``_tips_xyz`` on many poses at once, so the two agree exactly."""
        t = self.T_tcp[:3, :].ravel().tolist()
        if self._tip_c is None:
            px, py, pz = t[3], t[7], t[11]
        else:
            c0, c1, c2 = self._tip_c
            px = t[0] * c0 + t[1] * c1 + t[2] * c2 + t[3]
            py = t[4] * c0 + t[5] * c1 + t[6] * c2 + t[7]
            pz = t[8] * c0 + t[9] * c1 + t[10] * c2 + t[11]
        (r00, r01, r02, o0), (r10, r11, r12, o1), (r20, r21, r22, o2) = self._frame
        dx, dy, dz = px - o0, py - o1, pz - o2
        return (r00 * dx + r10 * dy + r20 * dz, r01 * dx + r11 * dy + r21 * dz,
                -(r02 * dx + r12 * dy + r22 * dz))

    def _tips_xyz(self, T: np.ndarray):
        """``tip_xyz`` for a stack of TCP transforms ``T`` (n, 4, 4): arrays x, y, depth."""
        if self._tip_c is None:
            px, py, pz = T[:, 0, 3], T[:, 1, 3], T[:, 2, 3]
        else:
            c0, c1, c2 = self._tip_c
            px = T[:, 0, 0] * c0 + T[:, 0, 1] * c1 + T[:, 0, 2] * c2 + T[:, 0, 3]
            py = T[:, 1, 0] * c0 + T[:, 1, 1] * c1 + T[:, 1, 2] * c2 + T[:, 1, 3]
            pz = T[:, 2, 0] * c0 + T[:, 2, 1] * c1 + T[:, 2, 2] * c2 + T[:, 2, 3]
        (r00, r01, r02, o0), (r10, r11, r12, o1), (r20, r21, r22, o2) = self._frame
        dx, dy, dz = px - o0, py - o1, pz - o2
        return (r00 * dx + r10 * dy + r20 * dz, r01 * dx + r11 * dy + r21 * dz,
                -(r02 * dx + r12 * dy + r22 * dz))

    def _set_tip(self) -> None:
        """The tip's position in the TCP frame (None: the tip is the TCP), from the TCP and the tool offsets."""
        tcp_inv = np.linalg.inv(ur5e.pose_to_T(self.tcp_offset))
        self._tip_c = None if self.tool_offset == self.tcp_offset else tuple((tcp_inv @ self._T_tool)[:3, 3].tolist())

    def tip_in_tissue(self) -> tuple[float, float]:
        """(x_m, depth_m) of the probe's physical tip in the tissue frame (``tip_xyz`` without y)."""
        x, _, d = self.tip_xyz()
        return x, d

    def elastic_force_n(self) -> float:
        """The tissue's elastic force at the tip now (the indentation below the TRUE surface)."""
        return self._elastic_at(*self.tip_xyz())[0]

    def _elastic_at(self, x: float, y: float, d: float, count: bool = True) -> tuple[float, float | None]:
        """(the elastic force with the tip at tissue-frame ``x``, ``y``, ``d``, the depth when the force model
        extrapolated beyond its range, else None); ``count`` False: not counted in the model's range report (a
        look ahead)."""
        if self.surface_height_m is not None:
            d += self.surface_height_m(x)
        if d <= 0 or not (-1e-6 <= x <= self.width_m + 1e-6):   # 1 um: round-off at the edges is not a jump
            return 0.0, None
        x = min(max(x, 0.0), self.width_m)
        if self.length_m is not None:
            if not (-1e-6 <= y <= self.length_m + 1e-6):
                return 0.0, None
            y = min(max(y, 0.0), self.length_m)
        else:
            y = 0.0
        fm = self.force_model
        if isinstance(fm, CachedForce):
            f, beyond = fm.look(x, d, y)
            if count and beyond:
                fm.count_beyond(d)
            return f, (d if beyond else None)
        return float(fm(x, d) if self.length_m is None else fm(x, d, y)), None

    def contact_force_n(self) -> float:
        fe = self.elastic_force_n()
        return fe if self.relaxation is None else self.relaxation.force(fe)

    def true_wrench(self, fc: float | None = None) -> np.ndarray:
        """The wrench on the tip now (``fc``: the contact force, when already computed)."""
        w = np.zeros(6)
        w[:3] = (self.contact_force_n() if fc is None else fc) * self.push_base
        if self.t_s < self._side_until:     # a side push: on the tool, so every sensor on it feels it
            w[:3] += self._side
        return w

    @property
    def is_moving(self) -> bool:
        return self.motion is not None

    # ---- commands ----------------------------------------------------------------------------------------
    def set_tcp(self, offset) -> None:
        flange = self.T_tcp @ np.linalg.inv(ur5e.pose_to_T(self.tcp_offset))
        self.tcp_offset = list(offset)
        self._set_tip()
        self.T_tcp = flange @ ur5e.pose_to_T(self.tcp_offset)

    def move_linear(self, pose, speed, accel) -> None:
        T0, T1 = self.T_tcp.copy(), ur5e.pose_to_T(pose)
        dist = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
        L = max(dist, 0.1 * ur5e.rotation_angle(T0[:3, :3], T1[:3, :3]))
        rel = ur5e.matrix_to_rotvec(T0[:3, :3].T @ T1[:3, :3])       # ur5e.slerp_matrix's, made once per move
        turns = float(np.linalg.norm(rel)) >= 1e-12                  # below, rotvec_to_matrix(u rel) is I
        tape: dict = {}                  # progress -> the step's index in the tape

        def interp(u):
            i = tape.get(u)
            if i is not None:
                hit = m.tape_pose(i)
                self.T_tcp, self._q_stale = hit[0], True
                self._tape_pose = hit
                return
            T = np.eye(4)
            T[:3, 3] = T0[:3, 3] + u * (T1[:3, 3] - T0[:3, 3])
            if u >= 1:
                T[:3, :3] = T1[:3, :3]
            else:
                T[:3, :3] = T0[:3, :3] @ ur5e.rotvec_to_matrix(u * rel) if turns else T0[:3, :3]
            self.T_tcp, self._q_stale = T, True
        m = _Motion(L, speed, accel, interp)
        if self.tape:
            us, ss, vs = m.uninterrupted(self.period_s)
            Ts, P = _linear_tape(T0, T1, rel if turns else None, us)
            tape.update(zip(us, range(len(us))))
            m.plan = (ss, vs, Ts, P)
        self._start(m, "linear")

    def move_joint(self, q, speed, accel) -> None:
        q0, q1 = self.joints(), np.asarray(q, dtype=float)
        L = float(np.max(np.abs(q1 - q0)))

        def interp(u):
            self.q = q0 + u * (q1 - q0)
            self.T_tcp, self._q_stale = ur5e.fk_flange(self.q) @ ur5e.pose_to_T(self.tcp_offset), False
        self._start(_Motion(L, speed, accel, interp), "joint")

    def _start(self, m, kind):
        if self.motion is not None:
            self.motions_ended += 1          # a new command replaces the running one
        self.motion, self.motion_kind = m, kind
        if m.L <= 0:
            m.interp(1.0)
            self.motion = None
            self.motions_ended += 1

    def stop(self, decel: float) -> None:
        self.stops_s.append(self.t_s)    # when each stop was commanded (reaction-time measurements)
        if self.motion is not None:
            self.motion.a_stop = float(decel)

    def input_update(self) -> None:
        """An RTDE input package from the client arrived (every command and every kickWatchdog send one)."""
        self.last_input_s = self.t_s

    def stop_program(self) -> None:
        """The control program ends (the controller removes its watchdogs); a running motion stops."""
        self.program_running, self.watchdog_hz = False, 0.0
        self.stop(PROGRAM_STOP_DECEL_M_S2)

    def zero_sensor(self) -> None:
        self.sensor.zero(self.true_wrench(), self.t_s)

    # ---- faults ------------------------------------------------------------------------------------------
    def inject(self, kind, at_s=None, when=None, duration_s=0.0, magnitude_n=0.0, reconnectable=False):
        """Schedule a fault: at simulated time ``at_s`` or when ``when(arm)`` first holds. Kinds:
        protective_stop, disconnect, force_spike (magnitude_n along the normal for duration_s), side_push
        (magnitude_n across the normal, along the tissue frame's x as far as it is across, for duration_s), nan
        (readings NaN for duration_s), stall (the current motion freezes until stopped or replaced)."""
        if kind not in ("protective_stop", "disconnect", "force_spike", "side_push", "nan", "stall"):
            raise ValueError(f"unknown fault {kind!r}")
        self.faults.append(dict(kind=kind, at_s=at_s, when=when, duration_s=duration_s, magnitude_n=magnitude_n,
                                reconnectable=reconnectable, fired_s=None))

    def _fire(self, f):
        f["fired_s"] = self.t_s
        k = f["kind"]
        if k == "protective_stop":
            self.trigger_protective_stop()
        elif k == "disconnect":
            self.connected, self.reconnectable = False, f["reconnectable"]
        elif k == "force_spike":
            self._spike_until, self._spike_n = self.t_s + max(f["duration_s"], self.period_s), f["magnitude_n"]
        elif k == "side_push":
            across = self.T_tissue[:3, 0] - float(self.T_tissue[:3, 0] @ self.n_base) * self.n_base
            self._side_until = self.t_s + max(f["duration_s"], self.period_s)
            self._side = f["magnitude_n"] * across / np.linalg.norm(across)
        elif k == "nan":
            self._nan_until = self.t_s + max(f["duration_s"], self.period_s)
        elif k == "stall" and self.motion is not None:
            self.motion.stalled = True

    def trigger_protective_stop(self) -> None:
        self.protective_stopped = True
        if self.motion is not None:
            self.motion = None  # halts at once (the real arm brakes within a few ms)
            self.motions_ended += 1

    def clear_protective_stop(self) -> None:
        """What the operator does on the pendant after a protective stop."""
        self.protective_stopped = False

    # ---- time ----------------------------------------------------------------------------------------------
    def step(self, dt: float | None = None) -> None:
        dt = self.period_s if dt is None else dt
        self.t_s += dt
        if self.start_program_at_s is not None and self.t_s >= self.start_program_at_s:
            self.program_running, self.start_program_at_s = True, None
            self.last_input_s = self.t_s
        if self.watchdog_hz > 0 and self.program_running and self.t_s - self.last_input_s > 1.0 / self.watchdog_hz:
            self.watchdog_fired_s = self.t_s
            self.stop_program()
        if self.motion is not None and not self.protective_stopped:
            done = self.motion.step(dt)
            self.motion.interp(self.motion.progress)
            if done:
                self.motion = None
                self.motions_ended += 1
        if self.relaxation is not None:
            self.relaxation.step(self.elastic_force_n(), dt)
        for f in self.faults:
            if f["fired_s"] is None and ((f["at_s"] is not None and self.t_s >= f["at_s"])
                                         or (f["when"] is not None and f["when"](self))):
                self._fire(f)
        fc = self.contact_force_n()
        self.max_contact_force_n = max(self.max_contact_force_n, fc)
        if fc > self.safety_force_n and not self.protective_stopped:
            self.trigger_protective_stop()
        self._sample(fc)
        for fn in self.on_step:
            fn()

    def _pose(self) -> list[float]:
        """ur5e.T_to_pose(T_tcp): from a linear move's tape, or with the rotation vector reused while the
        orientation stays the same (the arm at rest: zeroing, dwells, waits)."""
        if self._tape_pose is not None and self._tape_pose[0] is self.T_tcp:
            return self._tape_pose[1]
        R = self.T_tcp[:3, :3]
        key = R.tobytes()
        if key != self._rotvec_key:
            self._rotvec_key, self._rotvec = key, ur5e.matrix_to_rotvec(R)
        return [float(v) for v in (*self.T_tcp[:3, 3], *self._rotvec)]

    def _sample(self, fc: float | None = None) -> None:
        """A reading now; ``fc``: the contact force already computed this step."""
        w = self.sensor.read(self.true_wrench(fc), self.t_s)
        if self.t_s < self._spike_until:
            w[:3] += self._spike_n * self.n_base
        if self.t_s < self._nan_until:
            w[:] = np.nan
        self.samples.append((self.t_s, self._pose(), w))

    def reading(self):
        """(timestamp_s, tcp_pose, wrench) as the controller reports it now (``latency_s`` old)."""
        return self.samples[0]

    # ---- looking ahead: many periods at once where nothing but the motion and the tissue acts ---------------
    def look_ahead(self, n: int, kicks: bool) -> "Lookahead | None":
        """The next ``n`` periods computed at once, as ``n`` calls of ``step`` would compute them, if no command
        but a watchdog kick per period (``kicks``) reaches the controller meanwhile: readings of the states now
        and after each of the first steps, the motion's progress at each. None where stepping one period at a time
        is needed: a fault scheduled or acting, a hook on the steps (an external sensor), the link or the program
        down, a protective stop, a motion stopping, stalled, turning joints or without its tape, the watchdog
        unfed. The force stays below the protective stop's threshold over the periods returned (fewer than ``n``
        when it would not). Nothing changes until ``Lookahead.commit(k)``."""
        m = self.motion
        if (n < 1 or not self.connected or not self.program_running or self.start_program_at_s is not None
                or self.protective_stopped or self.on_step or any(f["fired_s"] is None for f in self.faults)
                or self.t_s < self._spike_until or self.t_s < self._nan_until or self.t_s < self._side_until
                or len(self.samples) != self.samples.maxlen
                or (self.watchdog_hz > 0 and not (kicks and 1.0 / self.watchdog_hz > 1.5 * self.period_s))
                or (m is not None and (m.plan is None or m.stalled or m.a_stop is not None or m.k >= len(m.plan[0])))):
            return None
        dt = self.period_s
        t = np.cumsum(np.concatenate([[self.t_s], np.full(n, dt)]))[1:]     # t_s += dt, n times
        if m is not None:
            ss, vs, Ts, P = m.plan
            idx = np.minimum(np.arange(m.k, m.k + n), len(ss) - 1)
            pose = P[idx]
            x, y, d = self._tips_xyz(Ts[idx])
        else:
            pose = np.tile(np.asarray(self._pose(), dtype=float), (n, 1))
            x, y, d = (np.full(n, v) for v in self.tip_xyz())
        fe, beyond = self._elastic_many(x, y, d)
        if len(fe) < n:                 # the force model failed at period len(fe): stepping says how
            if len(fe) == 0:
                return None
            n = len(fe)
            t, pose = t[:n], pose[:n]
        relax = []
        if self.relaxation is not None:
            r = copy.copy(self.relaxation)
            fc = []
            for f in fe.tolist():
                r.step(f, dt)
                fc.append(r.force(f))
                relax.append((r.h, r.fe))
            fc = np.array(fc)
        else:
            fc = fe
        stop = first_true(fc > self.safety_force_n, n)
        if stop == 0:
            return None
        n = stop
        tw = np.zeros((n, 6))
        tw[:, :3] = fc[:n, None] * self.push_base
        w = self.sensor.read_many(tw, t[:n], self.sensor.normals_ahead(n) if self.sensor._noisy else None)
        old = list(self.samples)                                    # the readings in flight: states 0, 1, ...
        seen_t = np.concatenate([[o[0] for o in old], t[:n]])[:n]
        seen_pose = np.concatenate([np.array([o[1] for o in old], dtype=float), pose[:n]])[:n]
        seen_w = np.concatenate([np.array([o[2] for o in old], dtype=float), w])[:n]
        ended = self.motions_ended
        if m is None:
            prog = [-1 - ended % 2] * n
        else:
            left = len(ss) - m.k                                    # the step that ends the motion
            k = max(min(n, left) - 1, 0)        # periods 1..k read the tape's progress, int(1000 * s / L) as step()'s
            mid = (1000 * (np.array(ss[m.k:m.k + k], dtype=float) / m.L)).astype(np.int64).tolist()
            prog = [int(1000 * m.progress)] + mid + [-1 - (ended + 1) % 2] * (n - 1 - k)
        return Lookahead(self, self.t_s, kicks, n, t, (seen_t, seen_pose, seen_w), prog, (pose[:n], w), fc[:n],
                         beyond[:n], relax)

    def _elastic_many(self, x: np.ndarray, y: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``_elastic_at`` at many tip positions, not counted: (forces, the depth where the force model extrapolated
        beyond its range, else NaN). Element by element the same operations. Shorter when the force model fails
        (raises) at a position: up to it."""
        if isinstance(self.force_model, CachedForce):
            try:
                return self._elastic_vectorised(x, y, d)
            except Exception:           # noqa: BLE001 -- one at a time, up to the period whose force fails
                pass
        fe, beyond = np.zeros(len(x)), np.full(len(x), np.nan)
        for j, (a, b, c) in enumerate(zip(x.tolist(), y.tolist(), d.tolist())):
            try:
                f, bey = self._elastic_at(a, b, c, count=False)
            except Exception:           # noqa: BLE001 -- step() meets it there, and says what it is
                return fe[:j], beyond[:j]
            fe[j], beyond[j] = f, (np.nan if bey is None else bey)
        return fe, beyond

    def _elastic_vectorised(self, x: np.ndarray, y: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``_elastic_many`` over a CachedForce, at once."""
        if not (np.isfinite(x).all() and np.isfinite(y).all() and np.isfinite(d).all()):
            raise ValueError("a tip position is not finite")  # one at a time: step() meets it as it does
        n = len(x)
        fm = self.force_model
        if self.surface_height_m is not None:
            d = d + np.array([self.surface_height_m(v) for v in x.tolist()], dtype=float)
            if not np.isfinite(d).all():
                raise ValueError("a surface height is not finite")
        inside = (d > 0) & (x >= -1e-6) & (x <= self.width_m + 1e-6)
        if self.length_m is not None:
            inside &= (y >= -1e-6) & (y <= self.length_m + 1e-6)
        fe, beyond = np.zeros(n), np.full(n, np.nan)
        j = np.flatnonzero(inside)
        if len(j):
            xs = np.minimum(np.maximum(x[j], 0.0), self.width_m)
            ys = np.minimum(np.maximum(y[j], 0.0), self.length_m) if self.length_m is not None else np.zeros(len(j))
            f, b = fm.look_many(xs, d[j], ys)
            fe[j] = f
            beyond[j] = np.where(b, d[j], np.nan)
        return fe, beyond

    def _commit(self, la: "Lookahead", k: int) -> None:
        """Advance ``k`` periods as ``la`` computed them."""
        if la.t0 != self.t_s or not 1 <= k <= la.n:
            raise RuntimeError("a stale look-ahead")
        t_before = self.t_s
        self.t_s = float(la.t[k - 1])
        m = self.motion
        if m is not None:
            ss, vs = m.plan[0], m.plan[1]
            i = m.k + k - 1
            if i >= len(ss) - 1:            # the motion ended
                hit = m.tape_pose(len(ss) - 1)
                self.motion = None
                self.motions_ended += 1
            else:
                hit = m.tape_pose(i)
                m.s, m.sdot, m.k = ss[i], vs[i], m.k + k
            self.T_tcp, self._q_stale, self._tape_pose = hit[0], True, hit
        if la.relax:
            self.relaxation.h, self.relaxation.fe = la.relax[k - 1]
        self.max_contact_force_n = max(self.max_contact_force_n, float(la.fc[:k].max()))
        for b in la.beyond[:k][np.isfinite(la.beyond[:k])].tolist():
            for _ in range(2 if la.relax else 1):   # step() asks for the elastic force twice with relaxation
                self.force_model.count_beyond(b)
        if self.sensor._noisy:
            self.sensor.skip(k)
        pose, w = la.new
        for j in range(max(0, k - self.samples.maxlen), k):        # the readings left in flight
            self.samples.append((float(la.t[j]), pose[j].tolist(), w[j].copy()))
        if la.kicks:
            self.last_input_s = t_before if k == 1 else float(la.t[k - 2])

    def run_until_still(self, max_s: float = 120.0) -> None:
        t_end = self.t_s + max_s
        while self.motion is not None and not self.protective_stopped and self.t_s < t_end:
            self.step()


@dataclass
class Lookahead:
    """Periods computed ahead by ``ArmModel.look_ahead``: ``seen`` the readings (timestamps_s, tcp poses as rows,
    wrenches as rows) and ``prog[j]`` the asynchronous-progress value (getAsyncOperationProgress) the driver gets in
    the j-th period from now; ``commit(k)`` advances the arm k periods (the first k readings taken)."""
    arm: "ArmModel"
    t0: float                  # the arm's time when looked ahead (a commit checks it)
    kicks: bool                # a watchdog kick in every period
    n: int                     # periods computed
    t: np.ndarray              # the time after each step
    seen: tuple                # (timestamps_s, poses, wrenches): the reading of each period
    prog: list                 # getAsyncOperationProgress in each period
    new: tuple                 # (poses, wrenches) of the samples each step makes
    fc: np.ndarray             # the contact force after each step
    beyond: np.ndarray         # the depth where the force model extrapolated beyond its range, else NaN
    relax: list                # the relaxation's (h, fe) after each step (empty without relaxation)

    def commit(self, k: int) -> None:
        self.arm._commit(self, k)


# ---------------------------------------------------------------------------------------------------------------
# ur_rtde-shaped facades

class _Facade:
    def __init__(self, arm: ArmModel):
        self.arm, self._closed = arm, False

    def _link(self):
        if self._closed or not self.arm.connected:
            raise RuntimeError("RTDE: the connection to the controller is lost")

    def isConnected(self) -> bool:
        return not self._closed and self.arm.connected

    def reconnect(self) -> bool:
        if self.arm.connected or self.arm.reconnectable:
            self.arm.connected, self._closed = True, False
            return True
        return False

    def disconnect(self) -> None:
        self._closed = True


class SimRTDEControl(_Facade):
    """RTDEControlInterface's methods (those the driver uses and a few more) over an ArmModel."""

    def __init__(self, arm: ArmModel):
        super().__init__(arm)
        arm.program_running = True           # like ur_rtde's constructor: the control script is uploaded
        arm.input_update()
        arm.control = weakref.ref(self)

    def _ok(self) -> bool:
        """The link is up (else RuntimeError); the command's input package reaches the controller; it is executed
        unless the arm is protective-stopped or the control program has stopped (ur_rtde then returns False)."""
        self._link()
        self.arm.input_update()
        return not self.arm.protective_stopped and self.arm.program_running

    def reconnect(self) -> bool:
        ok = super().reconnect()
        if ok and not self.arm.program_running:      # ur_rtde's reconnect() uploads the control script again
            self.arm.program_running = True
        return ok

    def setWatchdog(self, min_frequency=10.0) -> bool:
        if not self._ok():
            return False
        self.arm.watchdog_hz = float(min_frequency)
        return True

    def kickWatchdog(self) -> bool:
        return self._ok()

    def reuploadScript(self) -> bool:
        """Like ur_rtde: sends the program and returns; it runs a few periods later."""
        self._link()                          # the script port, not RTDE: no input update
        self.arm.start_program_at_s = self.arm.t_s + 0.01
        return True

    @staticmethod
    def _check_range(speed, accel, vmax, amax):
        if not (0 < speed <= vmax) or not (0 < accel <= amax):
            raise ValueError(f"speed {speed} or acceleration {accel} out of range")

    def moveL(self, pose, speed=0.25, acceleration=1.2, asynchronous=False) -> bool:
        self._check_range(speed, acceleration, 3.0, 150.0)
        if len(pose) != 6 or not all(math.isfinite(v) for v in pose):
            raise ValueError("moveL: a pose has 6 finite entries")
        if not self._ok():
            return False
        self.arm.move_linear(pose, speed, acceleration)
        return asynchronous or self._finish()

    def moveJ(self, q, speed=1.05, acceleration=1.4, asynchronous=False) -> bool:
        self._check_range(speed, acceleration, math.pi, 40.0)
        if not self._ok():
            return False
        self.arm.move_joint(q, speed, acceleration)
        return asynchronous or self._finish()

    def _finish(self) -> bool:
        self.arm.run_until_still()
        for _ in range(self.arm.samples.maxlen):   # returns once the readings show the arm at rest
            self.arm.step()
        self._link()
        return not self.arm.protective_stopped and not self.arm.is_moving

    def stopL(self, a=10.0, asynchronous=False) -> None:
        self._link()
        self.arm.input_update()
        self.arm.stop(a)
        if not asynchronous:
            self.arm.run_until_still(5.0)

    stopJ = stopL

    def speedStop(self, a=10.0) -> bool:
        self.stopL(a)
        return not self.arm.protective_stopped

    def stopScript(self) -> None:
        self._link()
        self.arm.input_update()
        self.arm.stop_program()

    def _do(self, fn) -> bool:
        """Run ``fn`` unless protective-stopped (then False, like ur_rtde)."""
        if not self._ok():
            return False
        return fn() is not False

    def zeroFtSensor(self) -> bool:
        return self._do(self.arm.zero_sensor)

    def setTcp(self, pose) -> bool:
        return self._do(lambda: self.arm.set_tcp(pose))

    def setPayload(self, mass, cog) -> bool:
        return self._do(lambda: 0 <= mass <= 5.0 and setattr(self.arm, "payload", (float(mass), list(cog))))

    def getAsyncOperationProgress(self) -> int:
        self._link()
        m = self.arm.motion   # like ur_rtde: >= 0 while running; < 0 when done, toggling -1/-2 per operation
        return -1 - self.arm.motions_ended % 2 if m is None else int(1000 * m.progress)

    def isSteady(self) -> bool:
        self._link()
        return not self.arm.is_moving

    def isProgramRunning(self) -> bool:
        return self.isConnected() and not self.arm.protective_stopped and self.arm.program_running

    def triggerProtectiveStop(self) -> bool:
        self._link()
        return self.arm.trigger_protective_stop() or True

    def isPoseWithinSafetyLimits(self, pose) -> bool:
        self._link()
        return float(np.linalg.norm(np.asarray(pose[:3]) - [0, 0, ur5e.D[0]])) < 0.85

    def getInverseKinematics(self, x, qnear=(), max_position_error=1e-10, max_orientation_error=1e-10):
        self._link()
        q = ur5e.ik(x, qnear if len(qnear) == 6 else self.arm.joints(), self.arm.tcp_offset)
        return [] if q is None else [float(v) for v in q]

    def initPeriod(self) -> datetime.timedelta:
        return datetime.timedelta(seconds=self.arm.t_s)

    def waitPeriod(self, t_cycle_start) -> None:
        self.arm.step()


class SimRTDEReceive(_Facade):
    """RTDEReceiveInterface's getters over an ArmModel (values delayed by the arm's latency)."""

    def _get(self, fn):
        self._link()
        return fn(self.arm)

    def getTimestamp(self) -> float:
        return self._get(lambda a: float(a.reading()[0]))

    def getActualTCPPose(self) -> list[float]:
        return self._get(lambda a: list(a.reading()[1]))

    def getActualTCPForce(self) -> list[float]:
        return self._get(lambda a: [float(v) for v in a.reading()[2]])

    def getActualQ(self) -> list[float]:
        return self._get(lambda a: [float(v) for v in a.joints()])

    def isProtectiveStopped(self) -> bool:
        return self._get(lambda a: a.protective_stopped)

    def look_ahead(self, n: int, kicks: bool, control) -> Lookahead | None:
        """Not ur_rtde's: the simulator's next ``n`` periods at once (``ArmModel.look_ahead``), or None. Only a
        simulator can know them; the driver uses it to step many quiet periods at once (robot.driver), passing the
        control interface it commands. None unless this receive interface, ``control`` and the arm are exactly
        these classes over one arm (a subclass -- a test's lagging or failing link, an arm with its own step --
        answers otherwise than the look-ahead would compute), or over a closed link."""
        arm = self.arm
        own = arm.control() if arm.control is not None else None
        if (type(self) is not SimRTDEReceive or type(arm) is not ArmModel or type(control) is not SimRTDEControl
                or control is not own or self._closed or control._closed or not arm.connected):
            return None
        return arm.look_ahead(n, kicks)

    def isEmergencyStopped(self) -> bool:
        return self._get(lambda a: False)

    def getSafetyMode(self) -> int:         # 1 normal, 3 protective stop
        return self._get(lambda a: 3 if a.protective_stopped else 1)

    def getRobotMode(self) -> int:          # 7 running
        return self._get(lambda a: 7)

    def getRuntimeState(self) -> int:       # 2 playing, 1 stopped
        return self._get(lambda a: 1 if a.protective_stopped or not a.program_running else 2)


def make_sim(force_model=None, **arm_kwargs):
    """An ArmModel and its (control, receive) facades: ``arm, rtde_c, rtde_r = make_sim(f, ...)``."""
    arm = ArmModel(force_model, **arm_kwargs)
    return arm, SimRTDEControl(arm), SimRTDEReceive(arm)
