"""The plan file: what the planner hands the robot. Plain data, JSON, versioned; no CasADi, no meshes.

Frames
------
* Base frame: the UR base. Poses are ur_rtde's ``[x, y, z, rx, ry, rz]`` (m, rotation vector in rad).
* Tissue frame: origin at the top-left corner of the tissue section (section point x = 0, y = height), x along the
  section's width, z the outward normal of the top surface (the section's +y), y = z cross x (out of the section's
  plane). A section point (x_m, y_m) is the tissue-frame point (x_m, 0, y_m - height_m). A probe's depth is measured
  along -z from the undeformed surface. ``frames.tissue_pose_base`` is the tissue frame's pose in the base frame.
* TCP: the probe tip, set with ``setTcp(frames.tcp_offset)``; the tool z axis points along the inward normal (-z of
  the tissue frame) at every probe pose.

Each probe: ``approach_pose`` (tip ``motion.approach_height_m`` above the undeformed surface at x_m), then a slow
straight descent along the tool axis to ``indent_pose`` (tip ``depth_m`` below the undeformed surface), dwell,
retract to ``approach_pose``.

Timing (planner/timing.py): every move is a moveL; the descent runs at ``motion.probe_speed_m_s`` over approach height
plus depth, the retract at the approach speed; each move takes the larger of its tool-speed and joint-limit times.
``notes`` carries the planner's diagnostics: ``solver`` (status, iterations, ``used``: "nlp" or "seed"), ``timing``
(per-move breakdown), ``times_s``, ``depth_limited_by`` (per probe: "force" or "depth"), ``target_force_n``,
``branch`` and ``tilt_tol_rad``.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

PLAN_VERSION = 1


class PlanError(ValueError):
    """A plan file that cannot be executed; the message names the field."""


@dataclass
class Limits:
    force_limit_n: float = 2.0           # no probe may be planned or driven above this contact force
    depth_limit_m: float = 0.004         # no probe deeper than this below the undeformed surface (< tip radius)
    workspace_min_m: list[float] = field(default_factory=lambda: [-0.8, -0.8, -0.1])  # base-frame box for the TCP
    workspace_max_m: list[float] = field(default_factory=lambda: [0.8, 0.8, 0.8])
    max_tool_speed_m_s: float = 0.25


@dataclass
class Motion:
    approach_height_m: float = 0.010     # tip above the undeformed surface at the approach pose
    approach_speed_m_s: float = 0.10     # moves between probes
    approach_accel_m_s2: float = 0.5
    probe_speed_m_s: float = 0.002       # slow descent into tissue
    probe_accel_m_s2: float = 0.5
    contact_threshold_n: float = 0.02    # force above which the tip is in contact
    dwell_s: float = 0.5                 # hold at depth while sampling


@dataclass
class Frames:
    tissue_pose_base: list[float] = field(default_factory=lambda: [0.40, -0.035, 0.05, 0.0, 0.0, math.pi / 2])
    tcp_offset: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.10, 0.0, 0.0, 0.0])


@dataclass
class Probe:
    index: int
    x_m: float                           # tissue frame, from the left edge
    depth_m: float                       # planned indentation below the undeformed surface
    predicted_force_n: float             # fem's prediction for the *prior* (stone-free) tissue at this depth
    approach_pose: list[float]           # base frame, ur_rtde pose
    indent_pose: list[float]
    q_approach_rad: list[float]          # UR5e joint targets (6)
    q_indent_rad: list[float]
    t_start_s: float = 0.0               # planned start time from the beginning of the run
    duration_s: float = 0.0              # planned time for this probe (move in, descend, dwell, retract)


@dataclass
class Plan:
    scene: dict                          # the prior scene (Scene.to_dict() of scene.prior()): no stones
    frames: Frames = field(default_factory=Frames)
    limits: Limits = field(default_factory=Limits)
    motion: Motion = field(default_factory=Motion)
    probes: list[Probe] = field(default_factory=list)
    total_time_s: float = 0.0
    version: int = PLAN_VERSION
    notes: dict = field(default_factory=dict)  # free-form planner diagnostics (solver status, timings)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=1))

    @staticmethod
    def from_dict(d: dict) -> "Plan":
        if not isinstance(d, dict):
            raise PlanError("a plan must be a JSON object")
        if d.get("version") != PLAN_VERSION:
            raise PlanError(f"plan version {d.get('version')!r} is not supported (this palpate reads {PLAN_VERSION})")
        try:
            plan = Plan(scene=d["scene"], frames=Frames(**d["frames"]), limits=Limits(**d["limits"]),
                        motion=Motion(**d["motion"]), probes=[Probe(**p) for p in d["probes"]],
                        total_time_s=d.get("total_time_s", 0.0), version=d["version"], notes=d.get("notes", {}))
        except (KeyError, TypeError) as e:
            raise PlanError(f"malformed plan: {e}") from None
        plan.check()
        return plan

    @staticmethod
    def load(path: str | Path) -> "Plan":
        try:
            d = json.loads(Path(path).read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise PlanError(f"cannot read plan {path}: {e}") from None
        return Plan.from_dict(d)

    def check(self) -> None:
        """Structural checks (the driver makes its own safety checks before sending anything)."""
        def finite(where, values, n=None):
            values = list(values)
            if n is not None and len(values) != n:
                raise PlanError(f"{where} must have {n} entries, got {len(values)}")
            if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
                raise PlanError(f"{where} must be finite numbers, got {values}")
        finite("frames.tissue_pose_base", self.frames.tissue_pose_base, 6)
        finite("frames.tcp_offset", self.frames.tcp_offset, 6)
        finite("limits.workspace_min_m", self.limits.workspace_min_m, 3)
        finite("limits.workspace_max_m", self.limits.workspace_max_m, 3)
        if any(lo >= hi for lo, hi in zip(self.limits.workspace_min_m, self.limits.workspace_max_m)):
            raise PlanError("limits.workspace_min_m must be below limits.workspace_max_m on every axis")
        for name in ("force_limit_n", "depth_limit_m", "max_tool_speed_m_s"):
            v = getattr(self.limits, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise PlanError(f"limits.{name} must be positive, got {v!r}")
        for p in self.probes:
            w = f"probes[{p.index}]"
            finite(f"{w}.approach_pose", p.approach_pose, 6)
            finite(f"{w}.indent_pose", p.indent_pose, 6)
            finite(f"{w}.q_approach_rad", p.q_approach_rad, 6)
            finite(f"{w}.q_indent_rad", p.q_indent_rad, 6)
            finite(f"{w}.x_m/depth_m", [p.x_m, p.depth_m, p.predicted_force_n])
