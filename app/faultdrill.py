"""Fault drills: the robot-cell script against the simulated UR controller with a fault injected, through the real
ur_rtde client, as an operator would run it (``palpate-cell --host IP``).

``run_drill(name, workdir)`` starts a controller with the drill's fault (robot.simfaults), runs ``palpate-cell`` on a
three-probe plan over the paper scene (coarse mesh), and returns a ``DrillResult``: the exit code, the wall time of
the whole cell process, the fault report, the records, and how the motion ended as the controller saw it. Used by
tests/test_fault_drills.py (each drill ends within ``DRILL_BOUND_S``) and bench/fault_table.py (docs/robot.md's table).
"""
from __future__ import annotations

import json
import math
import re
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from core import ur5e
from core.contracts import Frames, Limits, Motion, Plan, Probe
from fem import scene as fem_scene
from robot.simlaunch import start_controller

DRILL_BOUND_S = 30.0                      # a drill's cell process ends within this (issue 20)
TCP = [0.0, 0.0, 0.10, 0.0, 0.0, 0.0]
TISSUE = list(Frames().tissue_pose_base)  # the plan default; the controller is told the same
DEPTH_IN_DESCENT_M = 0.0015               # faults "during a descent" fire here (probes go 3 mm deep)
DRILL_PROBE_SPEED_M_S = 0.002             # the driver's RTDE watchdog is then 5 Hz (0.2 s): a drill on a busy
                                          # machine is not cut short by a host held up for 0.1 s


def pose_at(x_m: float, height_m: float) -> list:
    """Base-frame TCP pose with the tip at tissue-frame point (x_m, 0, height_m), tool z along the inward normal."""
    T = ur5e.pose_to_T(TISSUE)
    Tt = np.eye(4)
    Tt[:3, :3] = T[:3, :3] @ ur5e.rotvec_to_matrix([math.pi, 0.0, 0.0])
    Tt[:3, 3] = T[:3, :3] @ [x_m, 0.0, height_m] + T[:3, 3]
    return ur5e.T_to_pose(Tt)


Q0 = ur5e.ik(pose_at(0.035, 0.04), ur5e.IK_SEED, TCP)   # the tip 40 mm above the middle of the tissue


def make_plan(xs=(0.015, 0.035, 0.055), depth_m=0.003, force_limit_n=1.0, probe_speed_m_s=0.005) -> Plan:
    """A plan of probes at ``xs`` (m), ``depth_m`` deep, from Q0, with the plan default frames."""
    mo = Motion(approach_height_m=0.003, approach_speed_m_s=0.1, probe_speed_m_s=probe_speed_m_s, dwell_s=0.3,
                contact_threshold_n=0.01)
    probes, q = [], Q0
    for i, x in enumerate(xs):
        a, d = pose_at(x, mo.approach_height_m), pose_at(x, -depth_m)
        qa = ur5e.ik(a, q, TCP)
        qi = ur5e.ik(d, qa, TCP)
        probes.append(Probe(index=i, x_m=x, depth_m=depth_m, predicted_force_n=0.0, approach_pose=a,
                            indent_pose=d, q_approach_rad=list(qa), q_indent_rad=list(qi)))
        q = qa
    prior = fem_scene.load("paper").prior()
    return Plan(scene=prior.to_dict(), frames=Frames(tissue_pose_base=list(TISSUE), tcp_offset=list(TCP)),
                limits=Limits(force_limit_n=force_limit_n), motion=mo, probes=probes)


def coarse_paper_scene(path: Path) -> Path:
    """The paper scene on a coarse mesh (builds in about a second), written to ``path``."""
    sc = fem_scene.load("paper").with_analysis(mesh_size_m=0.005, surface_refine=2.5)
    path.write_text(fem_scene.dump_toml(sc))
    return path


@dataclass(frozen=True)
class Drill:
    inject: tuple            # robot.simfaults specifications
    interrupted: int         # the probe the fault interrupts
    kinds: frozenset         # fault kinds the run may report
    what: str                # one line for the table


_D = f"at-depth-m={DEPTH_IN_DESCENT_M}"
DRILLS = {
    "partition-descent": Drill((f"partition-{_D}",), 0, frozenset({"connection_lost"}),
                               "network partition (sockets open, no traffic) during a descent"),
    "partition-rest": Drill(("partition-after-probes=1",), 1, frozenset({"connection_lost"}),
                            "network partition at rest between probes"),
    "freeze-descent": Drill((f"freeze-{_D}",), 0, frozenset({"connection_lost"}),
                            "controller frozen (SIGSTOP) during a descent"),
    "drop-reconnect": Drill((f"drop-{_D}",), 0, frozenset({"connection_lost", "client_crashed"}),
                            "link dropped during a descent, reconnecting allowed (ur_rtde reconnects by itself)"),
    "pstop-descent": Drill((f"protective-stop-{_D}",), 0, frozenset({"protective_stop"}),
                           "protective stop during a descent"),
    "pstop-rest": Drill(("protective-stop-after-probes=1",), 1, frozenset({"protective_stop"}),
                        "protective stop at rest between probes"),
    "program-stop-descent": Drill((f"program-stop-{_D}",), 0, frozenset({"program_stopped"}),
                                  "program stopped from the dashboard during a descent"),
    "program-stop-rest": Drill(("program-stop-after-probes=1",), 1, frozenset({"program_stopped"}),
                               "program stopped from the dashboard at rest"),
    "remote-off-rest": Drill(("remote-off-after-probes=1:1",), 1, frozenset({"program_stopped"}),
                             "pendant switched to local control (program stopped) at rest"),
}


@dataclass
class DrillResult:
    name: str
    returncode: int
    wall_s: float                      # the whole cell process, connect to exit
    fault: dict
    statuses: dict                     # probe index -> statuses in probes.jsonl order
    raw_samples: int                   # samples kept for the interrupted probe
    fault_at_s: float | None           # controller time the fault was injected
    detected_at_s: float | None        # controller time of the driver's last reading (fault.controller_time_s)
    reaction_s: float | None           # wall time from the injection (controller log) to the driver's fault
    watchdog_at_s: float | None        # controller time the RTDE watchdog stopped the program, if it did
    final_state: dict | None           # the controller's state after the cell ended (None: could not be asked)
    stdout: str = ""
    stderr: str = ""
    notes: list = field(default_factory=list)

    @property
    def detection_s(self) -> float | None:
        if self.fault_at_s is None or self.detected_at_s is None:
            return None
        return self.detected_at_s - self.fault_at_s


def ask_dashboard(host: str, command: str, timeout_s: float = 2.0) -> str:
    with socket.create_connection((host, 29999), timeout=timeout_s) as db:
        db.recv(200)
        db.sendall(command.encode() + b"\n")
        return db.recv(4096).decode().strip()


def controller_state(host: str, timeout_s: float = 3.0) -> dict | None:
    """The simulated controller's state (the ``simcontroller state`` dashboard hook) once the arm is at rest, or the
    last state seen after ``timeout_s``; None if the dashboard does not answer."""
    t_end, state = time.monotonic() + timeout_s, None
    while time.monotonic() < t_end:
        try:
            state = json.loads(ask_dashboard(host, "simcontroller state").split(": ", 1)[1])
        except (OSError, IndexError, ValueError):
            return state
        if not state["moving"] and (not state["program_running"] or state["protective_stopped"]):
            return state
        time.sleep(0.05)
    return state


def _log_time(log: str, pattern: str) -> float | None:
    """The controller time (``at t=... s``) of the first log line matching ``pattern``."""
    m = re.search(pattern + r".*? at t=([0-9.]+) s", log)
    return float(m.group(1)) if m else None


def _log_unix_time(log: str, pattern: str) -> float | None:
    """The wall time (Unix s) the controller logged the first line matching ``pattern`` (same machine clock)."""
    m = re.search(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d),(\d{3}) .*" + pattern, log, re.M)
    if not m:
        return None
    return datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S").timestamp() + int(m.group(2)) / 1e3


def run_cell(host: str, plan: Plan, out: Path, extra=(), timeout_s: float = 120.0) -> subprocess.CompletedProcess:
    """``palpate-cell --host HOST --plan ... --out OUT --yes`` as a subprocess (python -m app.cell)."""
    plan_path = out.parent / f"{out.name}_plan.json"
    plan.save(plan_path)
    cmd = [sys.executable, "-m", "app.cell", "--host", host, "--plan", str(plan_path), "--out", str(out), "--yes",
           *extra]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s,
                          cwd=Path(__file__).resolve().parent.parent)


def run_drill(name: str, workdir: Path, scene_path: Path | None = None) -> DrillResult:
    """Run drill ``name`` (a key of DRILLS) in ``workdir`` (created; the run goes to workdir/run)."""
    drill = DRILLS[name]
    workdir.mkdir(parents=True, exist_ok=True)
    scene_path = scene_path or coarse_paper_scene(workdir / "paper_coarse.toml")
    log_path = workdir / "controller.log"
    out = workdir / "run"
    ctl = start_controller(scene=str(scene_path), q0=Q0, tissue_pose=TISSUE, tool=TCP, host="auto", log_path=log_path,
                           inject=list(drill.inject))
    try:
        w0 = time.monotonic()
        p = run_cell(ctl.host, make_plan(probe_speed_m_s=DRILL_PROBE_SPEED_M_S), out, extra=("--fresh",),
                     timeout_s=DRILL_BOUND_S + 60.0)
        wall = time.monotonic() - w0
        if "freeze" in name:
            ctl.proc.send_signal(signal.SIGCONT)        # thaw it to ask how the motion ended
        healed = "partition" not in name
        state = controller_state(ctl.host) if healed else None
    finally:
        ctl.stop()
    log = log_path.read_text(encoding="utf-8", errors="replace")
    run = json.loads((out / "run.json").read_text()) if (out / "run.json").exists() else {}
    statuses: dict = {}
    lines = (out / "probes.jsonl").read_text().splitlines() if (out / "probes.jsonl").exists() else []
    for ln in lines:
        d = json.loads(ln)
        statuses.setdefault(d["index"], []).append(d["status"])
    raw = sorted((out / "raw").glob(f"probe_{drill.interrupted:03d}*.npz")) if (out / "raw").exists() else []
    n_raw = len(np.load(raw[-1])["time_s"]) if raw else 0
    fault = run.get("fault") or {}
    t_inj = _log_unix_time(log, "injected fault")
    return DrillResult(name, p.returncode, wall, fault, statuses, n_raw,
                       fault_at_s=_log_time(log, "injected fault"), detected_at_s=fault.get("controller_time_s"),
                       reaction_s=(fault["detected_unix_s"] - t_inj if fault.get("detected_unix_s") and
                                   t_inj is not None else None),
                       watchdog_at_s=_log_time(log, "RTDE watchdog: no update"), final_state=state,
                       stdout=p.stdout, stderr=p.stderr)
