"""Where the driver's force comes from: the UR's own wrist sensor over ur_rtde (``RtdeForce``) or an external ATI
Net F/T box over UDP (``NetFtForce``). Both give the wrench ON THE TOOL in the BASE frame (forces N, torques N m
about the TCP), the convention of ur_rtde's getActualTCPForce, so the driver's contact force (its projection on the
tissue normal) means the same with either.

The driver calls ``zero(call)`` in free air (True when zeroed; ``call(fn, *args)`` is its bounded ur_rtde call) and
``wrench(call, tcp_pose)`` once per controller period (None or a non-finite vector is an invalid reading; a
``robot.netft.SensorFault`` is a sensor fault). ``report()`` goes into run.json, ``close()`` ends the session.

An external sensor is invisible to the UR controller: its own force protection sees only the wrist sensor. With
``NetFtForce`` the driver's force limit is the only guard on the contact force (docs/architecture.md).

Frames (``NetFtForce``): the box reports the load on the sensor's tool side in the SENSOR frame, whose pose on the
flange is ``sensor_pose_flange`` (x, y, z, rx, ry, rz; m, rad; from the mounting drawing). With the TCP set to
``tcp_offset`` (the plan's), the sensor in the TCP frame is T_tcp_sensor = inv(T(tcp_offset)) T(sensor_pose_flange),
and at a TCP pose T_base_tcp the force in the base frame is f = R_base_tcp R_tcp_sensor f_s; the torque about the
TCP is R_base_tcp R_tcp_sensor t_s + (R_base_tcp p_tcp_sensor) x f.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from core import ur5e
from robot.netft import NetFtConfig, NetFtReader

ZERO_WINDOW_S = 0.04            # a Net F/T zero is the mean of the records of this much time at rest (the driver
                                # zeroes after a settle wait of the same length)


class ForceSource(Protocol):
    name: str

    def start(self) -> None: ...

    def zero(self, call) -> bool: ...

    def wrench(self, call, tcp_pose): ...

    def report(self) -> dict: ...

    def close(self) -> None: ...


class RtdeForce:
    """The UR's wrist sensor: getActualTCPForce (zeroed, payload-compensated, base frame) and zeroFtSensor."""
    name = "rtde"

    def __init__(self, rtde_c, rtde_r):
        self.c, self.r = rtde_c, rtde_r

    def start(self) -> None:
        pass

    def zero(self, call) -> bool:
        return call(self.c.zeroFtSensor)

    def wrench(self, call, tcp_pose):
        return call(self.r.getActualTCPForce)

    def report(self) -> dict:
        return {"source": self.name}

    def close(self) -> None:
        pass


def _T(pose) -> np.ndarray:
    return ur5e.pose_to_T([float(v) for v in pose])


@dataclass(frozen=True)
class Mount:
    """Where the sensor sits: its pose on the flange and the TCP the driver sets (both x, y, z, rx, ry, rz)."""
    sensor_pose_flange: tuple = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    tcp_offset: tuple = (0.0, 0.0, 0.1, 0.0, 0.0, 0.0)

    def tcp_sensor(self) -> np.ndarray:
        return np.linalg.inv(_T(self.tcp_offset)) @ _T(self.sensor_pose_flange)


def sensor_to_base(wrench_sensor, tcp_pose, T_tcp_sensor: np.ndarray) -> np.ndarray:
    """A sensor-frame wrench (load on the tool) as the base-frame wrench about the TCP (see the module's text)."""
    w = np.asarray(wrench_sensor, dtype=float)
    R_bt = ur5e.rotvec_to_matrix([float(v) for v in tcp_pose[3:6]])
    R = R_bt @ T_tcp_sensor[:3, :3]
    f = R @ w[:3]
    t = R @ w[3:] + np.cross(R_bt @ T_tcp_sensor[:3, 3], f)
    return np.concatenate([f, t])


class NetFtForce:
    """An ATI Net F/T box (robot.netft): zeroed on the host (the mean of ``ZERO_WINDOW_S`` of records at rest, so
    the box's own bias setting is never needed), turned into the base frame with the TCP pose the driver read in the
    same period."""
    name = "netft"

    def __init__(self, cfg: NetFtConfig, mount: Mount, **clock_wait):
        self.reader = NetFtReader(cfg, **clock_wait)          # clock=, wait=: see NetFtReader
        self.mount, self.T_tcp_sensor = mount, mount.tcp_sensor()
        self.offset = np.zeros(6)
        self.zeros = 0
        self.zero_records = 0               # records averaged by the last zero
        self.started = False

    def start(self) -> None:
        """Ask the box to stream (idempotent); SensorFault if it does not."""
        if not self.started:
            self.reader.start()
            self.started = True

    def zero(self, call) -> bool:
        self.reader.latest()                 # drained, and fresh: the records averaged are recent
        mean, n = self.reader.mean(ZERO_WINDOW_S)
        self.offset, self.zero_records = mean, n
        self.zeros += 1
        return n > 0 and bool(np.all(np.isfinite(mean)))

    def wrench(self, call, tcp_pose):
        ws = self.reader.latest() - self.offset
        if not all(math.isfinite(float(v)) for v in tcp_pose[3:6]):
            return None
        return [float(v) for v in sensor_to_base(ws, tcp_pose, self.T_tcp_sensor)]

    def report(self) -> dict:
        c = self.reader.cfg
        return {"source": self.name, "host": c.host, "port": c.port, "zeros": self.zeros, "zero_records": self.zero_records,
                "counts_per_force": c.calibration.counts_per_force, "counts_per_torque": c.calibration.counts_per_torque,
                "sensor_pose_flange": list(self.mount.sensor_pose_flange), "stale_s": c.stale_s, **self.reader.report()}

    def close(self) -> None:
        self.reader.stop()
        self.started = False
