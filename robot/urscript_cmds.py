"""The behaviour of ur_rtde's control script (scripts/rtde_control.script), as the simulated controller runs it.

ur_rtde uploads a URScript program over port 30003. It loops once per controller cycle: read the command id in
``input_int_register_0`` (arguments in ``input_double_register_0..`` and ``input_int_register_1..``), run it, and
answer in ``output_int_register_0``: 1 = ready for a command, 2 = done with the command. Asynchronous moves run in
a thread and report in ``output_int_register_2`` (op id, write count, running bit, progress). We do not execute
URScript; we execute the same register protocol with the same command ids against the physical arm model.

Command ids and semantics were read from ur_rtde 1.6.5's script (the installed client is the authority).

Also here: the machine the program runs on -- ``ArmPort`` (what the program needs from robot.sim's ArmModel).
Fault injection is robot.simfaults.
"""
from __future__ import annotations

import logging
import re

import numpy as np

from core import ur5e

log = logging.getLogger("simcontroller.script")

# command ids (rtde_control.script, ur_rtde 1.6.x)
MOVEJ, MOVEJ_IK, MOVEL, MOVEL_FK = 1, 2, 3, 4
FORCE_MODE, FORCE_MODE_STOP, ZERO_FT_SENSOR = 6, 7, 8
SPEEDJ, SPEEDL, SERVOJ, SERVOC, SPEED_STOP, SERVO_STOP = 9, 10, 11, 12, 15, 16
SET_PAYLOAD, SET_TCP, GET_STEPTIME, PROTECTIVE_STOP = 17, 29, 26, 31
STOPL, STOPJ, SET_WATCHDOG, IS_POSE_WITHIN_SAFETY_LIMITS = 33, 34, 35, 36
GET_TCP_OFFSET, GET_FK_DEFAULT, GET_FK_ARGS, MOVE_PATH = 40, 43, 44, 45
FT_RTDE_INPUT_ENABLE, SET_TARGET_PAYLOAD = 56, 65
STOP_SCRIPT = 255
# ids the script handles as real-time commands: processed every cycle, answered with "ready"
REALTIME = {24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71}

READY, DONE = 1, 2
_PATH_RE = re.compile(r"(movej|movel|movep)\((p?)\[([^\]]*)\],a=([-+0-9.eE]+),v=([-+0-9.eE]+),r=([-+0-9.eE]+)\)")
# ur_rtde injects the register offset right after a marker comment: "reg_offset_int = # int register offset\n24"
_OFFSET_RE = re.compile(r"reg_offset_int\s*=\s*(?:#[^\n]*\n)?\s*(\d+)")


def split_programs(buf: str) -> tuple[list[str], str]:
    """Complete programs (``def name():`` ... ``end`` at column 0) in what arrived on the script port, and the rest.
    A bare line outside a program (a single script command) is dropped with a warning."""
    programs = []
    while True:
        lines = buf.split("\n")
        start = next((i for i, ln in enumerate(lines) if ln.startswith(("def ", "sec "))), None)
        if start is None:
            if buf.endswith("\n") and buf.strip():
                log.warning("script port: ignoring a bare script line: %r", buf.strip()[:80])
                buf = ""
            return programs, buf
        end = next((i for i in range(start + 1, len(lines)) if lines[i].rstrip() == "end"), None)
        if end is None:
            return programs, buf
        programs.append("\n".join(lines[start:end + 1]))
        buf = "\n".join(lines[end + 1:])


class ScriptError(RuntimeError):
    """A runtime error of the control program: the controller stops the program (the client sees it stop)."""


class ControlScript:
    """One run of the uploaded control program. ``tick()`` is one controller cycle (2 ms on an e-Series)."""

    def __init__(self, arm, script_text: str, outputs: dict):
        self.arm = arm
        self.out = outputs                   # shared output registers: name -> value
        log.debug("program text begins: %r", script_text[:400])
        m = _OFFSET_RE.search(script_text)
        self.off = int(m.group(1)) if m else 0
        self.path = [(kind, bool(p), [float(v) for v in vals.split(",")], float(a), float(v), float(r))
                     for kind, p, vals, a, v, r in _PATH_RE.findall(script_text)]
        self.running = True
        self.executing = False
        self.blocked_until = None            # predicate: the main thread is inside a blocking command
        self.async_kind = None               # "move" | "stop" | "path" | None: what the async thread is doing
        self.async_path = None               # remaining path entries of a move_path
        self.path_index = 0
        self.async_op_id = 0
        self.async_wr_count = 0
        self.watchdog_hz = 0.0               # the controller's RTDE watchdog (SimController._watchdog enforces it)
        self.watchdog_var = f"input_int_register_{self.off}"
        self.watchdog_since = None
        self._reset_async_progress()
        self._w_int(0, READY)
        log.info("control script started (%d bytes, register offset %d, %d path entries)",
                 len(script_text), self.off, len(self.path))

    # ---- registers -------------------------------------------------------------------------------------------
    def _w_int(self, i, v):
        self.out[f"output_int_register_{i + self.off}"] = int(v)

    def _w_double(self, i, v):
        self.out[f"output_double_register_{i + self.off}"] = float(v)

    def _r_int(self, inputs, i):
        return int(inputs.get(f"input_int_register_{i + self.off}", 0))

    def _r_double(self, inputs, i):
        return float(inputs.get(f"input_double_register_{i + self.off}", 0.0))

    def _r_vec(self, inputs, i):
        return [self._r_double(inputs, i + k) for k in range(6)]

    def _write_async_progress(self, value: int):
        self.async_wr_count = (self.async_wr_count + 1) % 128
        if value == 0:
            self.async_op_id = (self.async_op_id + 1) % 128
        reg = self.async_wr_count * 65536 + self.async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self._w_int(2, reg)

    def _reset_async_progress(self):
        self._write_async_progress(-1)

    # ---- the main loop ---------------------------------------------------------------------------------------
    def tick(self, inputs: dict) -> None:
        if not self.running:
            return
        self._service_async()
        if self.blocked_until is not None:
            if not self.blocked_until():
                return
            self.blocked_until = None
            self._w_int(0, DONE)
            return
        cmd = self._r_int(inputs, 0)
        if cmd in REALTIME:
            self._process(cmd, inputs)
            if self.running:
                self._w_int(0, READY)
        elif cmd == 0:
            self.executing = False
            self._w_int(0, READY)
        else:
            if not self.executing:
                self._process(cmd, inputs)
            self.executing = True

    def stop(self):
        """The program ends (stop script, dashboard stop, protective stop, runtime error)."""
        self.running = False
        self.blocked_until = None

    def _service_async(self):
        if self.async_kind is None or self.arm.is_moving:
            return
        if self.async_kind == "path" and self.async_path:
            self.path_index += 1
            self._write_async_progress(self.path_index)      # the script's signal_async_progress(i)
            self._start_path_entry(self.async_path.pop(0))
            return
        self.async_kind = None
        self._write_async_progress(-1)

    def _stop_async_move(self):
        if self.async_kind in ("move", "path"):
            self.async_kind = None
            self.async_path = None
            self._write_async_progress(-1)

    def _start_path_entry(self, entry):
        kind, is_pose, vals, a, v, _blend = entry     # blends are not modelled: each entry stops at its target
        if kind == "movej":
            self.arm.move_joint(self.arm.inverse_kinematics(vals) if is_pose else vals, v, a)
        elif is_pose:
            self.arm.move_linear(vals, v, a)
        else:
            self.arm.move_linear_fk(vals, v, a)

    def _done(self):
        self._w_int(0, DONE)

    def _block_while_moving(self):
        self.blocked_until = lambda: not self.arm.is_moving

    def _move(self, cmd, inputs):
        target = self._r_vec(inputs, 0)
        v, a, is_async = self._r_double(inputs, 6), self._r_double(inputs, 7), self._r_int(inputs, 1) == 1
        self._stop_async_move()
        if cmd == MOVEJ:
            self.arm.move_joint(target, v, a)
        elif cmd == MOVEJ_IK:
            self.arm.move_joint(self.arm.inverse_kinematics(target), v, a)
        elif cmd == MOVEL:
            self.arm.move_linear(target, v, a)
        else:
            self.arm.move_linear_fk(target, v, a)
        if is_async:
            self.async_kind = "move"
            self._write_async_progress(0)
            self._done()
        else:
            self._block_while_moving()

    def _process(self, cmd: int, inputs: dict) -> None:
        if cmd not in REALTIME:
            log.debug("command %d", cmd)
        try:
            self._dispatch(cmd, inputs)
        except ScriptError as e:
            log.error("control program runtime error: %s", e)
            self.stop()

    def _dispatch(self, cmd: int, inputs: dict) -> None:
        arm = self.arm
        if cmd in (MOVEJ, MOVEJ_IK, MOVEL, MOVEL_FK):
            self._move(cmd, inputs)
        elif cmd in (STOPL, STOPJ):
            decel, is_async = self._r_double(inputs, 0), self._r_int(inputs, 1) == 1
            self._stop_async_move()
            arm.stop(decel, linear=(cmd == STOPL))
            if is_async:
                self.async_kind = "stop"
                self._write_async_progress(0)
                self._done()
            else:
                self._block_while_moving()
        elif cmd == ZERO_FT_SENSOR:
            arm.zero_ft_sensor()
            self._done()
        elif cmd == SET_TCP:
            arm.set_tcp(self._r_vec(inputs, 0))
            self._done()
        elif cmd in (SET_PAYLOAD, SET_TARGET_PAYLOAD):
            arm.set_payload(self._r_double(inputs, 0), [self._r_double(inputs, k) for k in (1, 2, 3)])
            self._done()
        elif cmd == SPEEDL:
            arm.speed_linear(self._r_vec(inputs, 0), self._r_double(inputs, 6), self._r_double(inputs, 7))
        elif cmd == SPEED_STOP:
            arm.stop(self._r_double(inputs, 0), linear=True)
            self._block_while_moving()
        elif cmd == GET_STEPTIME:
            self._w_double(0, 0.002)
        elif cmd == PROTECTIVE_STOP:
            arm.request_protective_stop("triggerProtectiveStop() from the client")
            self._done()
        elif cmd == SET_WATCHDOG:        # rtde_set_watchdog("input_int_register_<off>", hz, "stop")
            self.watchdog_hz = self._r_double(inputs, 0)
            self.watchdog_since = None       # the controller stamps it (SimController._watchdog)
            log.info("RTDE watchdog on %s at %g Hz (the program stops without an update for %.0f ms)",
                     self.watchdog_var, self.watchdog_hz, 1e3 / self.watchdog_hz if self.watchdog_hz > 0 else 0)
            self._done()
        elif cmd == IS_POSE_WITHIN_SAFETY_LIMITS:
            self._w_int(1, 1 if arm.is_pose_reachable(self._r_vec(inputs, 0)) else 0)
            self._done()
        elif cmd == GET_TCP_OFFSET:
            for k, v in enumerate(arm.tcp_offset):
                self._w_double(k, v)
            self._done()
        elif cmd in (GET_FK_DEFAULT, GET_FK_ARGS):
            q = self._r_vec(inputs, 0) if cmd == GET_FK_ARGS else None
            for k, v in enumerate(arm.forward_kinematics(q)):
                self._w_double(k, v)
            self._done()
        elif cmd == MOVE_PATH:
            self._stop_async_move()
            if not self.path:
                raise ScriptError("move_path without an injected path")
            entries = list(self.path)
            self._start_path_entry(entries.pop(0))
            self.async_kind, self.async_path, self.path_index = "path", entries, 0
            self._write_async_progress(0)
            if self._r_int(inputs, 1) == 1:
                self._done()
            else:
                self.blocked_until = lambda: self.async_kind is None
        elif cmd == FT_RTDE_INPUT_ENABLE:
            self._done()
        elif cmd == STOP_SCRIPT:
            log.info("control program: received stop script")
            self.stop()
        else:
            raise ScriptError(f"command id {cmd} is not supported by the simulated controller")


class ArmPort:
    """What the control program needs from the arm, over robot.sim.ArmModel."""

    def __init__(self, arm):
        self.arm = arm

    is_moving = property(lambda self: self.arm.is_moving)
    tcp_offset = property(lambda self: list(self.arm.tcp_offset))

    def move_joint(self, q, v, a):
        self.arm.move_joint(q, v, a)

    def move_linear(self, pose, v, a):
        self.arm.move_linear(pose, v, a)

    def move_linear_fk(self, q, v, a):
        self.arm.move_linear(ur5e.fk_pose(q, self.arm.tcp_offset), v, a)

    def inverse_kinematics(self, pose):
        q = ur5e.ik(pose, self.arm.joints(), self.arm.tcp_offset)
        if q is None:
            raise ScriptError(f"get_inverse_kin: no solution for {pose}")
        return q

    def forward_kinematics(self, q=None):
        return ur5e.fk_pose(self.arm.joints() if q is None else q, self.arm.tcp_offset)

    def is_pose_reachable(self, pose):
        if float(np.linalg.norm(np.asarray(pose[:3]) - [0, 0, ur5e.D[0]])) >= 0.85:
            return False
        return ur5e.ik(pose, self.arm.joints(), self.arm.tcp_offset) is not None

    def stop(self, decel, linear=True):
        self.arm.stop(decel)

    def zero_ft_sensor(self):
        self.arm.zero_sensor()

    def set_tcp(self, pose):
        self.arm.set_tcp(pose)

    def set_payload(self, mass, cog):
        self.arm.payload = (float(mass), list(cog))

    def speed_linear(self, xd, a, t):
        raise ScriptError("speedL is not modelled by the simulated arm")

    def request_protective_stop(self, reason):
        log.warning("protective stop: %s", reason)
        self.arm.trigger_protective_stop()
