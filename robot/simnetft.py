"""A simulated ATI Net F/T box on loopback UDP (RDT, robot.rdt): part of the simulator, so it may read the simulated
arm's contact force (the truth); the driver side only ever sees its datagrams.

``SimNetFtBox(arm, host, port)`` binds a UDP socket; ``step()`` -- hooked onto the arm's ``on_step``, so it runs once
per simulated controller period, in simulated time for the in-memory arm and in real time inside the simulated
controller -- answers requests (start real-time streaming, stop) and, while streaming, sends ``records_per_step``
records to whoever asked. A record is the arm's true wrench on the tool, in the SENSOR frame (mounted at
``sensor_pose_flange``; torques about the sensor origin, the force acting at the probe's tip), through a sensor model
(robot.sensor: noise, bias, drift, resolution, clipped at its range; never zeroed: the host zeroes), in counts of
``calibration``. A clipped reading is left for the host to notice (its range check); the simulated box's status word
is 0 unless a fault sets it. Faults: robot.simfaults' ft-* kinds.
"""
from __future__ import annotations

import socket

import numpy as np

from core import ur5e
from robot.netft import NetFtCalibration
from robot.rdt import CMD_START_BUFFERED, CMD_START_REALTIME, CMD_STOP, RDT_PORT, RdtRecord, pack_record, unpack_request
from robot.sensor import Sensor
from robot.simfaults import FaultSpec, trigger

SIM_CALIBRATION = NetFtCalibration(counts_per_force=1_000_000.0, counts_per_torque=1_000_000.0)
# the simulated sensor sits between flange and tool, 25 mm out, turned 90 deg about the tool axis (its cable exit):
# a mounting the force source must undo, so every simulated run exercises the frame transform
SIM_SENSOR_POSE_FLANGE = (0.0, 0.0, 0.025, 0.0, 0.0, 1.5707963267948966)
SPIKE_S = 0.01


class SimNetFtBox:
    def __init__(self, arm, *, host: str = "127.0.0.1", port: int = RDT_PORT, sensor: str = "nano17", seed: int = 0,
                 sensor_pose_flange=SIM_SENSOR_POSE_FLANGE, calibration: NetFtCalibration = SIM_CALIBRATION,
                 records_per_step: int = 1):
        self.arm, self.calibration, self.records_per_step = arm, calibration, int(records_per_step)
        self.sensor = Sensor(sensor, seed=seed + 7919)       # its own noise, independent of the wrist sensor's
        self.T_flange_sensor = ur5e.pose_to_T(list(sensor_pose_flange))
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((host, port))
        except OSError:
            self.sock.close()
            raise
        self.sock.setblocking(False)
        self.client = None
        self.seq = self.ft_seq = 0
        self.status = 0
        self.silent_until = -1.0          # simulated time (inf: for good)
        self.loss = 0.0
        self.spike_until, self.spike_n = -1.0, 0.0
        self.frozen = False
        self.last_counts = None
        self.faults: list = []            # [FaultSpec, when(arm), fired]
        self.rng = np.random.default_rng(seed + 104729)
        self.fired: list = []             # (fault text, simulated time): what the simulated controller logs
        self.sent = 0

    @property
    def address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def inject(self, f: FaultSpec) -> None:
        if not f.on_ft:
            raise ValueError(f"fault {f.text()!r} is not a Net F/T box fault")
        self.faults.append([f, trigger(f), False])

    def close(self) -> None:
        self.sock.close()

    # ---- once per simulated controller period ------------------------------------------------------------------
    def step(self) -> None:
        if self.sock.fileno() < 0:
            return
        self._serve_requests()
        self._fire_faults()
        t = self.arm.t_s
        if self.client is None or t < self.silent_until:
            return
        for _ in range(self.records_per_step):
            if self.client is None:          # gone during this step (its socket closed): stop sending to it
                return
            self._send_record(t)

    def _serve_requests(self) -> None:
        while True:
            try:
                data, addr = self.sock.recvfrom(64)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:          # ICMP unreachable from a client gone: forget it
                self.client = None
                return
            req = unpack_request(data)
            if req is None:
                continue
            if req[0] in (CMD_START_REALTIME, CMD_START_BUFFERED):
                self.client = addr
            elif req[0] == CMD_STOP and addr == self.client:
                self.client = None

    def _fire_faults(self) -> None:
        for item in self.faults:
            f, when, fired = item
            if fired or not when(self.arm):
                continue
            item[2] = True
            self.fired.append((f.text(), self.arm.t_s))
            if f.kind == "ft-silent":
                self.silent_until = self.arm.t_s + f.x if f.x else float("inf")
            elif f.kind == "ft-status":
                self.status = int(f.x) if f.x else 1
            elif f.kind == "ft-loss":
                self.loss = 0.9 if f.x is None else float(f.x)
            elif f.kind == "ft-spike":
                self.spike_until, self.spike_n = self.arm.t_s + SPIKE_S, float(f.x or 0.0)
            elif f.kind == "ft-freeze":
                self.frozen = True

    def wrench_sensor(self, t_s: float) -> np.ndarray:
        """The reading now: the true wrench on the tool in the sensor frame, through the sensor model."""
        arm = self.arm
        w = arm.true_wrench()
        if t_s < self.spike_until:
            w[:3] += self.spike_n * arm.n_base
        T_flange = arm.T_tcp @ np.linalg.inv(ur5e.pose_to_T(arm.tcp_offset))
        T_sensor = T_flange @ self.T_flange_sensor
        p_tip = (T_flange @ ur5e.pose_to_T(arm.tool_offset))[:3, 3]
        R = T_sensor[:3, :3]
        torque = np.cross(p_tip - T_sensor[:3, 3], w[:3])      # the force acts at the tip
        # the truth's sensor bias and drift along the tissue normal (robot.truth), a force reading's error (no
        # torque): this sensor's too, not only the wrist sensor's (before session 38 the box left them out)
        force = w[:3] + (arm.normal_bias_n + arm.normal_drift_n_per_s * t_s) * arm.n_base
        return self.sensor.read(np.concatenate([R.T @ force, R.T @ torque]), t_s)

    def _send_record(self, t_s: float) -> None:
        self.seq += 1
        self.ft_seq += 1
        if self.loss > 0 and self.rng.random() < self.loss:
            return                           # lost on the way: the sequence number is used up
        if not (self.frozen and self.last_counts is not None):
            w = self.wrench_sensor(t_s)
            cal = self.calibration
            counts = np.concatenate([w[:3] * cal.counts_per_force, w[3:] * cal.counts_per_torque])
            self.last_counts = tuple(int(c) for c in np.clip(np.round(counts), -2**31, 2**31 - 1))
        data = pack_record(RdtRecord(self.seq, self.ft_seq, self.status, self.last_counts))
        try:
            self.sock.sendto(data, self.client)
            self.sent += 1
        except OSError:                      # the client's socket is gone
            self.client = None


def attach_box(arm, faults=(), **kw) -> SimNetFtBox:
    """A simulated box sampling ``arm`` after each of its steps, with the ft-* faults among ``faults`` (FaultSpec)."""
    box = SimNetFtBox(arm, **kw)
    for f in faults:
        if f.on_ft:
            box.inject(f)
    arm.on_step.append(box.step)
    return box
