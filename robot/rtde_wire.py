"""RTDE on the controller's side: message framing, variable types, recipes, one client session; and the sockets.

Written from Universal Robots' published RTDE guide and checked against what the installed ur_rtde client
(1.6.5) sends and expects; see robot/simcontroller.py. Protocol version 2 only (what ur_rtde negotiates).
Every message: big-endian ``uint16 size`` (header included) + ``uint8 type`` + payload.

ur_rtde's ports are fixed (29999, 30003, 30004), so ``loopback_candidates`` finds a loopback address whose ports
are free: Linux routes all of 127/8 to lo, so each controller can take its own 127.a.b.1.
"""
from __future__ import annotations

import logging
import os
import random
import re
import socket
import struct
import threading
import time

log = logging.getLogger("simcontroller.rtde")

HEADER = struct.Struct(">HB")
CONTROLLER_PORTS = (29999, 30003, 30004)      # dashboard, script, RTDE: fixed in ur_rtde

REQUEST_PROTOCOL_VERSION = ord("V")     # 86
GET_URCONTROL_VERSION = ord("v")        # 118
TEXT_MESSAGE = ord("M")                 # 77
DATA_PACKAGE = ord("U")                 # 85
CONTROL_PACKAGE_SETUP_OUTPUTS = ord("O")  # 79
CONTROL_PACKAGE_SETUP_INPUTS = ord("I")   # 73
CONTROL_PACKAGE_START = ord("S")        # 83
CONTROL_PACKAGE_PAUSE = ord("P")        # 80

# RTDE type name -> struct format (big-endian, no padding)
TYPE_FORMATS = {
    "BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
    "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I",
}

_V6D = ("target_q target_qd target_qdd target_current target_moment actual_q actual_qd actual_current "
        "joint_control_output actual_TCP_pose actual_TCP_speed actual_TCP_force target_TCP_pose target_TCP_speed "
        "joint_temperatures actual_joint_voltage ft_raw_wrench payload_inertia actual_current_as_torque "
        "actual_current_window target_current_window external_force_torque")
_DOUBLE = ("timestamp actual_execution_time speed_scaling target_speed_fraction actual_momentum actual_main_voltage "
           "actual_robot_voltage actual_robot_current standard_analog_input0 standard_analog_input1 "
           "standard_analog_output0 standard_analog_output1 io_current euromap67_24V_voltage "
           "euromap67_24V_current tool_analog_input0 tool_analog_input1 tool_output_current tool_temperature "
           "tcp_force_scalar payload joint_position_deviation_ratio collision_detection_ratio "
           "speed_slider_fraction standard_analog_output_0 standard_analog_output_1")
_UINT32 = ("runtime_state robot_status_bits safety_status_bits analog_io_types euromap67_input_bits "
           "euromap67_output_bits tool_mode tool_analog_input_types output_bit_registers0_to_31 "
           "output_bit_registers32_to_63 input_bit_registers0_to_31 input_bit_registers32_to_63 "
           "script_control_line time_scale_source speed_slider_mask")
_INT32 = "robot_mode safety_mode safety_status tool_output_voltage"
_UINT8 = ("tool_output_mode tool_digital_output0_mode tool_digital_output1_mode standard_digital_output_mask "
          "standard_digital_output configurable_digital_output_mask configurable_digital_output "
          "tool_digital_output_mask tool_digital_output standard_analog_output_mask standard_analog_output_type")

FIELD_TYPES: dict[str, str] = {}
for _names, _t in ((_V6D, "VECTOR6D"), (_DOUBLE, "DOUBLE"), (_UINT32, "UINT32"), (_INT32, "INT32"),
                   (_UINT8, "UINT8")):
    FIELD_TYPES.update({n: _t for n in _names.split()})
FIELD_TYPES.update({"actual_digital_input_bits": "UINT64", "actual_digital_output_bits": "UINT64",
                    "joint_mode": "VECTOR6INT32", "actual_tool_accelerometer": "VECTOR3D",
                    "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D", "payload_cog": "VECTOR3D"})

_REG = re.compile(r"^(input|output)_(int|double|bit)_register_(\d+)$")


def field_type(name: str) -> str | None:
    """RTDE type of a variable name, or None (the controller answers NOT_FOUND)."""
    m = _REG.match(name)
    if m:
        kind, idx = m.group(2), int(m.group(3))
        if kind == "bit":
            return "BOOL" if 64 <= idx <= 127 else None
        if idx > 47:
            return None
        return "INT32" if kind == "int" else "DOUBLE"
    return FIELD_TYPES.get(name)


class Recipe:
    """A set of named variables with a fixed binary layout."""

    def __init__(self, recipe_id: int, names: list[str], frequency_hz: float = 0.0):
        self.id = recipe_id
        self.names = names
        self.types = [field_type(n) or "NOT_FOUND" for n in names]
        self.frequency_hz = frequency_hz
        self.valid = "NOT_FOUND" not in self.types
        self.struct = struct.Struct(">B" + "".join(TYPE_FORMATS[t] for t in self.types)) if self.valid else None

    def types_reply(self) -> bytes:
        return bytes([self.id]) + ",".join(self.types).encode()

    def pack(self, values: dict) -> bytes:
        flat: list = []
        for name, t in zip(self.names, self.types):
            v = values.get(name)
            if t.startswith("VECTOR"):
                flat.extend(v if v is not None else [0] * int(TYPE_FORMATS[t][0]))
            elif v is None:
                flat.append(0)
            else:
                flat.append(v)
        return self.struct.pack(self.id, *flat)

    def unpack(self, payload: bytes) -> dict:
        """Decode a data package payload (recipe id byte included) into {name: value}."""
        vals = self.struct.unpack(payload[: self.struct.size])
        out, i = {}, 1
        for name, t in zip(self.names, self.types):
            n = int(TYPE_FORMATS[t][0]) if TYPE_FORMATS[t][0].isdigit() else 1
            out[name] = list(vals[i:i + n]) if n > 1 else vals[i]
            i += n
        return out


def parse_names(payload: bytes) -> list[str]:
    return [n for n in payload.decode("ascii", "replace").strip().split(",") if n]


def frame(msg_type: int, payload: bytes = b"") -> bytes:
    return HEADER.pack(HEADER.size + len(payload), msg_type) + payload


def recv_exact(sock, n: int) -> bytes:
    """``n`` bytes from anything with ``recv`` (a socket, a ``Conn``)."""
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("peer closed")
        buf += chunk
    return bytes(buf)


def read_message(sock) -> tuple[int, bytes]:
    size, msg_type = HEADER.unpack(recv_exact(sock, HEADER.size))
    if size < HEADER.size:
        raise ConnectionError(f"bad RTDE header size {size}")
    return msg_type, recv_exact(sock, size - HEADER.size)


class Conn:
    """A client socket; writes from several threads go through one lock."""

    def __init__(self, sock, kind, gate: threading.Event | None = None):
        self.sock, self.kind, self.lock = sock, kind, threading.Lock()
        self.started, self.out_recipes, self.in_recipes, self.closed = False, [], {}, False
        self.gate = gate            # cleared: nothing is read (a network partition); the bytes wait in the kernel

    def recv(self, n: int) -> bytes:
        """``sock.recv``, held while the gate is closed."""
        self._hold()
        data = self.sock.recv(n)
        self._hold()                # what arrived during a partition passes only when it heals
        return data

    def _hold(self) -> None:
        while self.gate is not None and not self.gate.wait(0.2):
            if self.closed:
                raise ConnectionError("closed")

    def lines(self):
        """Text lines from the client (the dashboard protocol), held while the gate is closed."""
        buf = b""
        while True:
            data = self.recv(4096)
            if not data:
                return
            buf += data
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                yield line.decode("utf-8", "replace")

    def send(self, data: bytes) -> bool:
        with self.lock:
            if self.closed:
                return False
            try:
                self.sock.sendall(data)
                return True
            except OSError:
                self._close()
                return False

    def _close(self):
        self.closed = True
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()

    def close(self):
        with self.lock:
            if not self.closed:
                self._close()


def serve_rtde(c: "Conn", ctl) -> None:
    """One RTDE client session. ``ctl`` (the controller) holds ``lock``, ``receive_inputs(values)`` (input updates),
    ``input_owner`` (which connection set up which input) and ``controller_version``. Data packages go out from
    the controller's cycle to every started connection's output recipes (``Recipe.decimation``)."""
    while True:
        mtype, payload = read_message(c)
        if mtype == DATA_PACKAGE:
            r = c.in_recipes.get(payload[0]) if payload else None
            if r is None:
                log.warning("rtde: data package for unknown input recipe %s", payload[:1])
                continue
            try:
                values = r.unpack(payload)
            except struct.error:
                log.warning("rtde: data package of %d bytes does not fit input recipe %d (%d bytes)",
                            len(payload), r.id, r.struct.size)
                continue
            with ctl.lock:
                ctl.receive_inputs(values)
        elif mtype == REQUEST_PROTOCOL_VERSION:
            (version,) = struct.unpack(">H", payload[:2])
            c.send(frame(mtype, bytes([1 if version == 2 else 0])))
        elif mtype == GET_URCONTROL_VERSION:
            c.send(frame(mtype, struct.pack(">IIII", *ctl.controller_version)))
        elif mtype == CONTROL_PACKAGE_SETUP_OUTPUTS:
            (freq,) = struct.unpack(">d", payload[:8])
            r = Recipe(len(c.out_recipes) + 1, parse_names(payload[8:]), freq)
            ok = r.valid and 0 < freq <= 500
            if ok:
                r.decimation = max(1, round(500.0 / freq))
                c.out_recipes.append(r)
            log.info("rtde: output recipe %d at %g Hz: %s", r.id, freq, ",".join(r.names))
            c.send(frame(mtype, bytes([r.id if ok else 0]) + r.types_reply()[1:]))
        elif mtype == CONTROL_PACKAGE_SETUP_INPUTS:
            _setup_inputs(c, ctl, parse_names(payload))
        elif mtype == CONTROL_PACKAGE_START:
            with c.lock:    # the reply goes out before the first data package
                c.sock.sendall(frame(mtype, b"\x01"))
                c.started = True
        elif mtype == CONTROL_PACKAGE_PAUSE:
            with c.lock:
                c.started = False
                c.sock.sendall(frame(mtype, b"\x01"))
        else:
            log.warning("rtde: unknown message type %d", mtype)


def _setup_inputs(c: "Conn", ctl, names):
    r = Recipe(len(c.in_recipes) + 1, names)
    with ctl.lock:
        in_use = [n for n in names if ctl.input_owner.get(n, c) is not c]
        if in_use:
            r.types = ["IN_USE" if n in in_use else t for n, t in zip(names, r.types)]
        elif r.valid:
            for n in names:
                ctl.input_owner[n] = c
    ok = r.valid and not in_use
    if ok:
        c.in_recipes[r.id] = r
    else:
        log.warning("rtde: input recipe refused: %s", ",".join(f"{n}:{t}" for n, t in zip(names, r.types)))
    c.send(frame(CONTROL_PACKAGE_SETUP_INPUTS, bytes([r.id if ok else 0]) + ",".join(r.types).encode()))


def _ports_free(host: str) -> bool:
    socks: list[socket.socket] = []
    try:
        for port in CONTROLLER_PORTS:
            s = socket.socket()
            socks.append(s)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, port))
        return True
    except OSError:
        return False
    finally:
        for s in socks:
            s.close()


def loopback_candidates(n: int = 6) -> list[str]:
    """Loopback addresses to try for a controller of our own: Linux routes all of 127/8 to lo, so a run can take
    127.a.b.1 with ur_rtde's fixed ports while another run (or URSim) holds 127.0.0.1. 127.0.0.1 comes last."""
    rnd = random.Random(os.getpid() ^ time.monotonic_ns())
    hosts = [f"127.{rnd.randrange(1, 255)}.{rnd.randrange(0, 256)}.1" for _ in range(n)]
    return [h for h in hosts if _ports_free(h)] + ["127.0.0.1"]
