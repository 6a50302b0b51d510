"""A simulated UR e-Series controller on loopback that the real ur_rtde client drives.

Serves the dashboard (29999), RTDE (30004, protocol 2, data at up to 500 Hz in real time) and the script port
(30003: accepts ur_rtde's control program and runs it, see robot/urscript_cmds.py). The physics is robot.sim's
``ArmModel`` (UR5e kinematics, trapezoidal motion, tissue force from fem, sensor model, faults), stepped every 2 ms.

Start it from a shell: ``python -m robot.simcontroller --scene paper --sensor nano17`` (Ctrl-C stops it), or from
Python: ``with robot.simlaunch.start_controller(scene="paper", host="auto") as ctl: ...`` then connect ur_rtde to
``ctl.host`` (a separate process: the ur_rtde binding holds the GIL while it connects, so a controller in the
client's process would deadlock). Faults: ``--inject protective-stop-at-depth-m=0.002``,
``--inject partition-after-probes=1`` etc. (``robot.simfaults``: arm faults and the controller's own -- a partition
with the sockets open, a frozen process, a program stopped from the dashboard, local control), or at run time through
the dashboard commands ``simcontroller protective-stop | drop-connection [refuse] | partition [S] | program-stop |
remote off|on | state`` (a real controller answers those with "could not understand").

"""
from __future__ import annotations

import argparse
import json
import logging
import os
import re
import signal
import socket
import struct
import sys
import threading
import time

import numpy as np

from core.contracts import Frames
from robot import rtde_wire as W
from robot.rdt import RDT_PORT
from robot.rtde_wire import Conn
from robot.sim import PROGRAM_STOP_DECEL_M_S2
from robot.simarm import build_truth_arm
from robot.simfaults import FaultSpec, parse, trigger
from robot.simnetft import SIM_SENSOR_POSE_FLANGE, attach_box
from robot.urscript_cmds import ArmPort, ControlScript, split_programs

log = logging.getLogger("simcontroller")
DASHBOARD_PORT, SCRIPT_PORT, RTDE_PORT = 29999, 30003, 30004
PERIOD_S = 0.002
MAX_CATCH_UP_S = 0.5
Q_EVERY = 4                  # joint angles (IK during linear moves, ~0.5 ms) every 4th cycle: 125 Hz
CONTROLLER_VERSION = (5, 11, 0, 108249)
POLYSCOPE_VERSION = "URSoftware 5.11.0.108249 (Jul 13 2021)"
ROBOT_MODE_RUNNING, SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP = 7, 1, 3
RUNTIME_STOPPED, RUNTIME_PLAYING, RUNTIME_PAUSED = 1, 2, 4
READY_LINE = "SIMCONTROLLER READY"
INSTALLATION_TCP = [0.0] * 6     # the installation's TCP: the flange (ur_rtde's setTcp changes it per program)


class PortsUnavailable(RuntimeError):
    """A controller port is taken on that loopback address (another controller, URSim, a parallel test run)."""


class SimController:
    def __init__(self, arm, host="127.0.0.1", port_offset=0):
        host = "127.0.0.1" if host == "localhost" else host
        if not host.startswith("127.") or len(host.split(".")) != 4:
            raise ValueError(f"the simulated controller binds to a loopback address (127.x.y.z) only, not {host!r}")
        self.arm, self.port = arm, ArmPort(arm)
        self.controller_version = CONTROLLER_VERSION
        self.host = host
        self.ports = {k: p + port_offset for k, p in
                      (("dashboard", DASHBOARD_PORT), ("script", SCRIPT_PORT), ("rtde", RTDE_PORT))}
        self.lock = threading.RLock()
        self.stop_event = threading.Event()
        self.inputs: dict = {}
        self.input_t: dict = {}        # simulated time of each input variable's last update (RTDE watchdogs)
        self.outputs: dict = {}
        self.input_owner: dict = {}
        self.script: ControlScript | None = None
        self.paused = False
        self.pstop_since = None
        self.conns: list[Conn] = []
        self.listeners: dict = {}
        self.threads: list[threading.Thread] = []
        self._prev, self._q, self._qd, self._n = None, None, np.zeros(6), 0
        self.watchdog_fired_s = None
        self.remote = True             # the pendant in remote control (local control refuses network programs)
        self.link = threading.Event()  # cleared during a partition: nothing passes either way, sockets stay open
        self.link.set()
        self.pending: list = []        # controller faults not yet fired: (FaultSpec, when(arm))
        self.overruns = 0              # times the process was held up > MAX_CATCH_UP_S (a very busy machine)
        self.box = None                # the simulated Net F/T box (--netft)
        self._logged = {"box": 0, "stops": 0}
        self.failed = False

    # ---- lifecycle ---------------------------------------------------------------------------------------
    def bind(self) -> None:
        for kind, port in self.ports.items():
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((self.host, port))
            except OSError as e:
                s.close()
                self.close_listeners()
                raise PortsUnavailable(f"cannot bind {self.host}:{port} ({kind}): {e.strerror}") from e
            s.listen(8)
            self.listeners[kind] = s

    def close_listeners(self):
        """Stop listening at once: shutdown() wakes a thread blocked in accept() (close() alone leaves the port
        accepting until that accept() returns)."""
        for s in self.listeners.values():
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()
        self.listeners.clear()

    def start(self) -> None:
        if not self.listeners:
            self.bind()
        for kind, s in self.listeners.items():
            self._spawn(self._accept_loop, kind, s)
        self._spawn(self._tick_loop)

    def _spawn(self, fn, *args):
        t = threading.Thread(target=fn, args=args, daemon=True, name=f"simctl-{fn.__name__}")
        t.start()
        self.threads.append(t)

    def shutdown(self) -> None:
        if self.overruns:
            log.warning("held up more than %.1f s %d times: simulated time is behind real time", MAX_CATCH_UP_S,
                        self.overruns)
        self.stop_event.set()
        self.close_listeners()
        for c in list(self.conns):
            c.close()

    # ---- faults ----------------------------------------------------------------------------------------------
    def protective_stop(self, reason="injected"):
        with self.lock:
            self.port.request_protective_stop(reason)

    def schedule(self, f: FaultSpec) -> None:
        """A controller fault (robot.simfaults.CONTROLLER_FAULTS) to fire when its trigger holds."""
        self.pending.append((f, trigger(f)))

    def _fire_due(self) -> None:
        for item in [it for it in self.pending if it[1](self.arm)]:
            self.pending.remove(item)
            f = item[0]
            log.warning("injected fault %s at t=%.3f s", f.text(), self.arm.t_s)
            if f.kind == "partition":
                self.partition(f.x or 0.0)
            elif f.kind == "program-stop":
                self.stop_program()
            elif f.kind == "remote-off":
                self.set_remote(False, stop=bool(f.x))
            elif f.kind == "freeze":
                self.freeze()

    def partition(self, seconds: float = 0.0) -> None:
        """Nothing passes either way (no data out, nothing read in) with every socket left open; the link heals
        after ``seconds`` (wall time; 0: never). The watchdog sees no inputs and stops the program."""
        log.warning("network partition%s", f" for {seconds:g} s" if seconds > 0 else "")
        self.link.clear()
        if seconds > 0:
            threading.Timer(seconds, self._heal).start()

    def _heal(self) -> None:
        log.warning("partition healed")
        self.link.set()

    def freeze(self) -> None:
        """The controller process stops (SIGSTOP) until it is continued (SIGCONT) or killed."""
        for h in logging.getLogger().handlers:
            h.flush()
        os.kill(os.getpid(), signal.SIGSTOP)

    def stop_program(self) -> None:
        """The program stopped from the dashboard or the pendant: motion stops (category 2), no pause to resume."""
        if self.script is not None:
            self.script.stop()
        self.paused = False
        self.arm.stop(PROGRAM_STOP_DECEL_M_S2)

    def set_remote(self, on: bool, stop: bool = False) -> None:
        self.remote = bool(on)
        log.warning("pendant: %s control", "remote" if on else "local")
        if stop:
            self.stop_program()

    def drop_connections(self, refuse=False):
        """Close every client socket at once (a pulled cable / controller reboot); ``refuse``: keep refusing."""
        log.warning("dropping all connections%s", " and refusing new ones" if refuse else "")
        if refuse:
            self.close_listeners()
        for c in list(self.conns):
            c.close()

    # ---- the controller cycle --------------------------------------------------------------------------------
    def _tick_loop(self):
        try:
            self._run_cycles()
        except Exception:
            log.critical("the controller cycle failed; shutting down", exc_info=True)
            self.failed = True
            self.stop_event.set()

    def _run_cycles(self):
        """Real-time pacing: one 2 ms cycle per period. If the process was held up (a busy machine), the missed
        cycles run back to back (no packets for them), so simulated time stays locked to real time; only beyond
        MAX_CATCH_UP_S is time dropped (counted in ``overruns``)."""
        n, t_next = 0, time.perf_counter()
        while not self.stop_event.is_set():
            behind = int((time.perf_counter() - t_next) / PERIOD_S)
            if behind * PERIOD_S > MAX_CATCH_UP_S:
                self.overruns += 1
                log.info("held up %.0f ms: simulated time drops behind real time", 1e3 * behind * PERIOD_S)
                t_next, behind = time.perf_counter(), 0
            steps = 1 + max(behind, 0)
            with self.lock:
                for _ in range(steps):
                    self._cycle(check_watchdog=steps == 1)
                if steps > 1 and self.script is not None and self.link.is_set():
                    # this process was held up: the client's inputs of that time are still unread in the socket,
                    # so the watchdog's timing restarts (a real controller is never held up). Not during a
                    # partition: no input can be waiting then.
                    self.script.watchdog_since = self.arm.t_s
                values = self._snapshot()
            t_next += steps * PERIOD_S
            n += 1
            for c in list(self.conns) if self.link.is_set() else ():
                if c.kind == "rtde" and c.started:
                    for r in c.out_recipes:
                        if n % r.decimation == 0:
                            c.send(W.frame(W.DATA_PACKAGE, r.pack(values)))
            lag = time.perf_counter() - t_next
            if lag < 0:
                time.sleep(-lag)

    def receive_inputs(self, values: dict) -> None:
        """An RTDE input package (under ``lock``)."""
        self.inputs.update(values)
        self.input_t.update(dict.fromkeys(values, self.arm.t_s))

    def _watchdog(self) -> None:
        """rtde_set_watchdog(var, hz, "stop"): no update of ``var`` for 1/hz stops the program and the motion."""
        sc = self.script
        if sc is None or not sc.running or sc.watchdog_hz <= 0:
            return
        if sc.watchdog_since is None:
            sc.watchdog_since = self.arm.t_s
        last = max(self.input_t.get(sc.watchdog_var, -1.0), sc.watchdog_since)
        if self.arm.t_s - last > 1.0 / sc.watchdog_hz:
            log.warning("RTDE watchdog: no update of %s for %.0f ms at t=%.3f s; program stopped", sc.watchdog_var,
                        1e3 * (self.arm.t_s - last), self.arm.t_s)
            sc.stop()
            self.arm.stop(PROGRAM_STOP_DECEL_M_S2)
            self.watchdog_fired_s = self.arm.t_s

    def _cycle(self, check_watchdog: bool = True):
        arm = self.arm
        arm.step(PERIOD_S)
        if self.pending:
            self._fire_due()
        for f in arm.faults:
            if f["fired_s"] is not None and not f.get("logged"):
                f["logged"] = True
                log.warning("injected fault %s at t=%.3f s", f["kind"], f["fired_s"])
        self._log_events()
        if check_watchdog:
            self._watchdog()
        if not arm.connected:
            self.drop_connections(refuse=not arm.reconnectable)
            arm.connected = True
        if arm.protective_stopped and self.pstop_since is None:
            self.pstop_since = time.monotonic()
            log.warning("PROTECTIVE STOP at t=%.3f s; program paused", arm.t_s)
            if self.script is not None and self.script.running:
                self.script.stop()
                self.paused = True
        if self.script is not None:
            self.script.tick(self.inputs)

    def _log_events(self) -> None:
        """The Net F/T box's faults and every stop commanded, as ``EVENT <what> t=<s>`` lines (controller time):
        ``read_events`` reads them back (reaction-time measurements)."""
        events = []
        if self.box is not None:
            events += [(f"ft-fault {text}", t) for text, t in self.box.fired[self._logged["box"]:]]
            self._logged["box"] = len(self.box.fired)
        events += [("stop", t) for t in self.arm.stops_s[self._logged["stops"]:]]
        self._logged["stops"] = len(self.arm.stops_s)
        for what, t in events:
            log.warning("EVENT %s t=%.4f", what, t)

    def _snapshot(self) -> dict:
        arm = self.arm
        t, pose, wrench = arm.reading()
        self._n += 1
        if self._q is None or self._n % Q_EVERY == 0 or arm.q_is_current:
            q = arm.joints()
            if self._q is not None and t > self._q[0]:
                self._qd = (q - self._q[1]) / (t - self._q[0])
            self._q = (t, q)
        q, qd = self._q[1], self._qd
        t0, p0 = self._prev or (t, pose)
        speed = [(a - b) / (t - t0) if t > t0 else 0.0 for a, b in zip(pose[:3], p0[:3])] + [0.0, 0.0, 0.0]
        self._prev = (t, pose)
        running = self.script is not None and self.script.running
        pstop = arm.protective_stopped
        v = {"timestamp": t, "actual_q": list(q), "target_q": list(q), "actual_qd": list(qd),
             "target_qd": list(qd), "actual_TCP_pose": pose, "target_TCP_pose": pose, "actual_TCP_speed": speed,
             "target_TCP_speed": speed, "actual_TCP_force": [float(x) for x in wrench],
             "ft_raw_wrench": [float(x) for x in wrench], "robot_mode": ROBOT_MODE_RUNNING,
             "joint_mode": [253] * 6, "safety_mode": SAFETY_PROTECTIVE_STOP if pstop else SAFETY_NORMAL,
             "safety_status": SAFETY_PROTECTIVE_STOP if pstop else SAFETY_NORMAL,
             "safety_status_bits": (1 << 2) | (1 << 10) if pstop else 1,
             "robot_status_bits": 1 | (2 if running else 0),
             "runtime_state": RUNTIME_PLAYING if running else (RUNTIME_PAUSED if self.paused else RUNTIME_STOPPED),
             "speed_scaling": 1.0, "target_speed_fraction": 1.0, "actual_execution_time": 0.3,
             "actual_main_voltage": 48.0, "actual_robot_voltage": 48.0, "actual_robot_current": 0.6,
             "actual_joint_voltage": [48.0] * 6, "joint_temperatures": [32.0] * 6, "tool_temperature": 31.0,
             "actual_tool_accelerometer": [0.0, 0.0, 9.81], "payload": arm.payload[0],
             "payload_cog": list(arm.payload[1]), "tcp_force_scalar": float(np.linalg.norm(wrench[:3]))}
        v.update(self.inputs)
        v.update(self.outputs)
        return v

    # ---- sockets ---------------------------------------------------------------------------------------------
    def _accept_loop(self, kind, lsock):
        handler = {"dashboard": self._dashboard, "script": self._script_port,
                   "rtde": lambda c: W.serve_rtde(c, self)}[kind]
        while not self.stop_event.is_set():
            try:
                sock, _ = lsock.accept()
            except OSError:
                return
            if lsock.fileno() < 0:          # closed while we were accepting: refuse
                sock.close()
                return
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, struct.pack("ll", 1, 0))  # a stuck reader
            sock.settimeout(None)                                                          # cannot stall us
            c = Conn(sock, kind, gate=self.link)
            self.conns.append(c)
            log.info("%s: client connected", kind)
            self._spawn(self._serve, handler, c)

    def _serve(self, handler, c):
        try:
            handler(c)
        except (ConnectionError, OSError) as e:
            log.info("%s: connection closed (%s)", c.kind, e)
        except Exception:                       # a bug here must not pass silently
            log.exception("%s: session failed; closing the connection", c.kind)
        finally:
            c.close()
            with self.lock:
                for name in [n for n, o in self.input_owner.items() if o is c]:
                    del self.input_owner[name]
            if c in self.conns:
                self.conns.remove(c)

    def _script_port(self, c: Conn):
        buf = ""
        while True:
            data = c.recv(65536)
            if not data:
                raise ConnectionError("script client closed")
            programs, buf = split_programs(buf + data.decode("utf-8", "replace"))
            for text in programs:
                self._run_program(text)

    def _run_program(self, text: str):
        with self.lock:
            if self.arm.protective_stopped:
                log.error("script port: cannot start a program while protective-stopped")
                return
            if not self.remote:
                log.error("script port: program refused, the robot is in local control")
                return
            if self.script is not None and self.script.running:
                log.info("script port: a new program replaces the running one")
                self.script.stop()
            self.paused = False
            self.arm.set_tcp(INSTALLATION_TCP)   # a new program starts with the installation's TCP (the flange)
            self.script = ControlScript(self.port, text, self.outputs)

    def _dashboard(self, c: Conn):
        c.send(b"Connected: Universal Robots Dashboard Server\n")
        for line in c.lines():
            cmd = line.strip()
            if cmd:
                reply = self._dashboard_reply(cmd)
                log.info("dashboard: %r -> %r", cmd, reply)
                c.send((reply + "\n").encode())
                if cmd == "quit":
                    return
        raise ConnectionError("dashboard client closed")

    _DASHBOARD_FIXED = {
        "polyscopeversion": POLYSCOPE_VERSION, "robotmode": "Robotmode: RUNNING",
        "close popup": "closing popup", "close safety popup": "closing safety popup", "power on": "Powering on",
        "power off": "Powering off", "brake release": "Brake releasing", "get robot model": "UR5",
        "get serial number": "20205500000", "quit": "Disconnected", "get loaded program": "Loaded program: <unnamed>",
        "isprogramsaved": "true <unnamed>", "restart safety": "Restarting safety", "get operational mode": "NONE"}
    _UNLOCK_REFUSED = ("Cannot unlock protective stop until 5s after occurrence. Always inspect cause of protective "
                       "stop before unlocking")

    def _dashboard_reply(self, cmd: str) -> str:
        """The replies of PolyScope 5.11's dashboard server to the commands ur_rtde and an operator use."""
        low, arm = cmd.lower(), self.arm
        with self.lock:
            running = self.script is not None and self.script.running
            if low in self._DASHBOARD_FIXED:
                return self._DASHBOARD_FIXED[low]
            if low == "is in remote control":
                return str(self.remote).lower()
            if low in ("play", "load", "power on", "brake release", "unlock protective stop") and not self.remote:
                return f"Failed to execute: {low} (the robot is in local control)"
            if low in ("safetystatus", "safetymode"):
                return f"Safety{low[6:]}: " + ("PROTECTIVE_STOP" if arm.protective_stopped else "NORMAL")
            if low == "programstate":
                state = "PLAYING" if running else ("PAUSED" if self.paused else "STOPPED")
                return f"{state} rtde_control" if self.script is not None else "STOPPED <unnamed>"
            if low == "running":
                return f"Program running: {str(running).lower()}"
            if low == "stop":
                self.stop_program()
                return "Stopped"
            if low == "pause" and running:
                self.script.stop()
                self.paused = True
                return "Pausing program"
            if low == "play" and self.script is not None and not arm.protective_stopped:
                self.script.running, self.paused = True, False
                return "Starting program"
            if low in ("pause", "play"):
                return f"Failed to execute: {low}"
            if low == "unlock protective stop":
                if arm.protective_stopped:
                    if time.monotonic() - self.pstop_since < 5.0:
                        return self._UNLOCK_REFUSED
                    arm.clear_protective_stop()
                    self.pstop_since = None
                return "Protective stop releasing"
            if low.startswith("addtolog"):
                return "Added log message"
            if low.startswith("simcontroller "):
                return self._sim_command(low.split()[1:])
        log.warning("dashboard: unknown command %r", cmd)
        return f"could not understand: '{cmd}'"

    def _sim_command(self, words) -> str:
        if words[:1] == ["protective-stop"]:
            self.protective_stop("dashboard hook")
            return "simcontroller: protective stop"
        if words[:1] == ["drop-connection"]:
            threading.Timer(0.05, self.drop_connections, kwargs={"refuse": "refuse" in words}).start()
            return "simcontroller: dropping connections"
        if words[:1] == ["time"]:
            return f"simcontroller: t={self.arm.t_s:.3f}"
        if words[:1] == ["partition"]:
            seconds = float(words[1]) if len(words) > 1 else 0.0
            threading.Timer(0.05, self.partition, args=(seconds,)).start()    # after this reply has gone out
            return "simcontroller: partition"
        if words[:1] == ["program-stop"]:
            self.stop_program()
            return "simcontroller: program stopped"
        if words[:1] == ["remote"] and words[1:2] in (["on"], ["off"]):
            self.set_remote(words[1] == "on")
            return f"simcontroller: remote {words[1]}"
        if words[:1] == ["state"]:
            arm, sc = self.arm, self.script
            x, depth = arm.tip_in_tissue()
            return "simcontroller: " + json.dumps({
                "t_s": round(arm.t_s, 4), "moving": arm.is_moving, "program_running": bool(sc and sc.running),
                "protective_stopped": arm.protective_stopped, "remote": self.remote, "tip_x_m": x,
                "tip_depth_m": depth, "watchdog_fired_s": self.watchdog_fired_s,
                "max_contact_force_n": arm.max_contact_force_n})
        return f"could not understand: 'simcontroller {' '.join(words)}'"


def read_events(log_text: str) -> list[tuple[str, float]]:
    """The ``EVENT`` lines of a controller log: (what, controller time s)."""
    out = []
    for m in re.finditer(r"EVENT (.+?) t=([-0-9.]+)", log_text):
        out.append((m.group(1), float(m.group(2))))
    return out


def reaction_times_s(events) -> list[float]:
    """For every Net F/T force spike: controller time from its first record to the next stop commanded."""
    stops = [t for what, t in events if what == "stop"]
    out = []
    for what, t in events:
        if what.startswith("ft-fault ft-spike"):
            after = [s for s in stops if s >= t]
            if after:
                out.append(after[0] - t)
    return out


# ---- CLI (the process launcher is robot/simlaunch.py) ------------------------------------------------------------

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m robot.simcontroller", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", help="TRUE scene: built-in name or TOML (needed with --force fem)")
    ap.add_argument("--sensor", default="nano17", help="sensor preset: nano17 | ur5e-builtin")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tissue-pose", type=lambda s: [float(v) for v in s.split(",")], default=None,
                    help="tissue frame in the base frame x,y,z,rx,ry,rz (default: the plan default)")
    ap.add_argument("--tool", type=lambda s: [float(v) for v in s.split(",")], default=Frames().tcp_offset,
                    help="the probe's tip on the flange x,y,z,rx,ry,rz (m, rad; default the plan default "
                         "0,0,0.1,0,0,0): contact happens there whatever TCP a program sets")
    ap.add_argument("--q0", type=lambda s: [float(v) for v in s.split(",")], default=None,
                    help="start joint angles (rad, 6 comma-separated; default: parked above the tissue)")
    ap.add_argument("--mesh-m", type=float, default=None, help="fem mesh size (coarser: faster start)")
    ap.add_argument("--force", choices=["fem", "standin"], default="fem", help="tissue force: fem or a stand-in")
    ap.add_argument("--inject", action="append", default=[],
                    help="fault (repeatable; robot.simfaults), e.g. protective-stop-at-depth-m=0.002, "
                         "partition-after-probes=1, freeze-at-depth-m=0.0015")
    ap.add_argument("--netft", action="store_true", help="also serve a simulated ATI Net F/T box (UDP, RDT, "
                    f"1 kHz) on the same address, port {RDT_PORT} + --port-offset (robot.simnetft)")
    ap.add_argument("--netft-sensor-pose", type=lambda s: [float(v) for v in s.split(",")],
                    default=list(SIM_SENSOR_POSE_FLANGE), help="the simulated Net F/T sensor's pose on the flange "
                    "x,y,z,rx,ry,rz (m, rad)")
    ap.add_argument("--host", default="127.0.0.1", help="loopback address to bind (127.x.x.x only)")
    ap.add_argument("--port-offset", type=int, default=0, help="add to every port (ur_rtde itself needs 0)")
    ap.add_argument("--log-level", default="INFO")
    ap.add_argument("--exit-on-stdin-eof", action="store_true", help="stop when the parent closes stdin")
    a = ap.parse_args(argv)
    if a.force == "fem" and not a.scene:
        ap.error("--scene: the TRUE scene is needed with --force fem (a built-in name or a TOML file)")
    logging.basicConfig(level=a.log_level.upper(), stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        ctl = SimController(None, host=a.host, port_offset=a.port_offset)
    except ValueError as e:
        ap.error(str(e))
    try:
        ctl.bind()                        # fail fast, before building the physics
    except PortsUnavailable as e:
        print(f"SIMCONTROLLER PORTS UNAVAILABLE: {e}", flush=True)
        return 3
    t0 = time.perf_counter()
    try:
        faults = [parse(spec) for spec in a.inject]
    except ValueError as e:
        ap.error(f"--inject: {e}")
    ctl.arm = build_truth_arm(a.scene, force=a.force, sensor=a.sensor, seed=a.seed, tissue_pose=a.tissue_pose,
                              q0=a.q0, mesh_m=a.mesh_m, inject=a.inject, tool_offset=a.tool)
    # gmsh.initialize (a mesh built here: a cold cache) sets SIGPIPE back to its default, which ends the process on
    # a data packet sent as a client vanishes; a controller outlives its clients (a failed send closes that one)
    signal.signal(signal.SIGPIPE, signal.SIG_IGN)
    for f in faults:
        if f.on_controller:
            ctl.schedule(f)
    ctl.port = ArmPort(ctl.arm)
    box = None
    if a.netft:                       # stepped with the arm: 2 records per 2 ms cycle, in real time
        try:
            box = ctl.box = attach_box(ctl.arm, faults=faults, host=a.host, port=RDT_PORT + a.port_offset,
                                       sensor=a.sensor, seed=a.seed, sensor_pose_flange=a.netft_sensor_pose,
                                       records_per_step=2)
        except OSError as e:
            ctl.close_listeners()
            print(f"SIMCONTROLLER PORTS UNAVAILABLE: cannot bind {a.host}:{RDT_PORT + a.port_offset} (Net F/T, "
                  f"UDP): {e.strerror}", flush=True)
            return 3
    elif any(f.on_ft for f in faults):
        ap.error("--inject: an ft-* fault needs --netft")
    log.info("physics ready in %.1f s (scene %s, sensor %s)", time.perf_counter() - t0, a.scene, a.sensor)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    if a.exit_on_stdin_eof:
        threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
    ctl.start()
    print(f"{READY_LINE} {a.host} dashboard={ctl.ports['dashboard']} rtde={ctl.ports['rtde']} "
          f"script={ctl.ports['script']}", flush=True)
    while not done.wait(0.2) and not ctl.stop_event.is_set():
        pass
    ctl.shutdown()
    if box is not None:
        box.close()
    return 4 if ctl.failed else 0


if __name__ == "__main__":
    sys.exit(main())
