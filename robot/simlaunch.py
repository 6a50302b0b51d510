"""Start the simulated UR controller (robot/simcontroller.py) in a child process: ``start_controller``.

The controller must run in its own process: the ur_rtde binding holds the GIL while it connects, so a controller in
the client's process would deadlock. ``start_controller(..., host="auto")`` gives each controller a loopback address
of its own (127.a.b.1, see ``rtde_wire.loopback_candidates``), since ur_rtde's ports are fixed; it raises
``PortsUnavailable`` only when the ports are taken on every address tried.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from robot.rtde_wire import loopback_candidates
from robot.simcontroller import READY_LINE, PortsUnavailable

__all__ = ["ControllerProcess", "PortsUnavailable", "start_controller"]


class ControllerProcess:
    """A controller in a child process; ``stop()`` (or leaving the ``with`` block) ends it, always."""

    def __init__(self, args, ready_timeout_s=60.0, log_path=None, host="127.0.0.1"):
        self.host = host
        root = Path(__file__).resolve().parent.parent
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]))
        self.log_path = Path(log_path) if log_path else None
        # appended: a resumed run's controller must not erase how the last one's motion ended (nothing measured is
        # overwritten; the safety review of session 38)
        err = open(self.log_path, "a") if self.log_path else subprocess.DEVNULL
        self.proc = subprocess.Popen([sys.executable, "-m", "robot.simcontroller", "--exit-on-stdin-eof", *args],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err, text=True, env=env,
                                     # (a session of its own: a terminal's Ctrl-C to the run does not end the
                                     # simulated controller under the driver's stop, as it would not a real one;
                                     # it ends at stop(), or when this process's end closes its stdin)
                                     start_new_session=True)
        if err is not subprocess.DEVNULL:
            err.close()
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(iter(self.proc.stdout.readline, "")), daemon=True)
        reader.start()
        t_end = time.monotonic() + ready_timeout_s
        while time.monotonic() < t_end:
            if any(READY_LINE in ln for ln in lines):
                return
            if any("PORTS UNAVAILABLE" in ln for ln in lines):
                self.stop()
                raise PortsUnavailable(next(ln for ln in lines if "PORTS" in ln).strip())
            if self.proc.poll() is not None:
                break
            time.sleep(0.02)
        self.stop()
        raise RuntimeError(f"simulated controller did not start (exit {self.proc.returncode}); "
                           f"output: {''.join(lines)[-2000:]!r}; log: {self.log_path}")

    def stop(self, timeout_s=5.0) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)      # a frozen controller (fault injection) takes SIGTERM then
            try:
                self.proc.stdin.close()
            except OSError:
                pass
            self.proc.terminate()
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout_s)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def start_controller(scene=None, sensor="nano17", seed=0, inject=(), force="fem", tissue_pose=None, q0=None,
                     mesh_m=None, host="127.0.0.1", log_path=None, ready_timeout_s=60.0,
                     tool=None, netft_sensor_pose=None) -> ControllerProcess:
    """Start a simulated controller on ``host`` (loopback) in a child process; return when its ports accept.
    ``host="auto"``: the first loopback address whose ports are free (see ``loopback_candidates``); connect the
    clients to ``.host`` of the result. Raises PortsUnavailable if the ports are taken (on every candidate).
    ``netft_sensor_pose``: also serve a simulated Net F/T box there (UDP port robot.rdt.RDT_PORT), its sensor mounted
    at that pose on the flange."""
    args = (["--scene", str(scene)] if scene is not None else []) + ["--sensor", sensor, "--seed", str(seed),
                                                                      "--force", force]
    for spec in inject:
        args += ["--inject", spec]
    if mesh_m:
        args += ["--mesh-m", repr(float(mesh_m))]
    if netft_sensor_pose is not None:
        args.append("--netft")
    for flag, vec in (("--tissue-pose", tissue_pose), ("--q0", q0), ("--tool", tool),
                      ("--netft-sensor-pose", netft_sensor_pose)):
        if vec is not None:
            args.append(f"{flag}=" + ",".join(repr(float(v)) for v in vec))   # '=': values may start with '-'
    err = None
    for h in (loopback_candidates() if host == "auto" else [host]):
        try:
            return ControllerProcess(args + ["--host", h], ready_timeout_s, log_path, host=h)
        except PortsUnavailable as e:
            err = e
    raise err
