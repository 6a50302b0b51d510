"""The plain data every package shares: the plan file, the probe record, run and fault states, the probe protocol's
constants and the force sensors' datasheet figures. numpy-free and import-free of every other palpate package: fem,
planner, robot and app all import this module, it imports none of them (docs/architecture.md).

Plan file (``plan.json``, version 2)
-----------------------------------
What the planner hands the robot. Plain data, JSON, versioned; no CasADi, no meshes.

* Base frame: the UR base. Poses are ur_rtde's ``[x, y, z, rx, ry, rz]`` (m, rotation vector in rad).
* Tissue frame: origin at the top-left corner of the tissue section (section point x = 0, y = height), x along the
  section's width, z the outward normal of the top surface (the section's +y), y = z cross x (out of the section's
  plane). A section point (x_m, y_m) is the tissue-frame point (x_m, 0, y_m - height_m). A probe's indentation depth is
  measured along -z from the undeformed surface. ``frames.tissue_pose_base`` is the tissue frame's pose in the base
  frame.
* TCP: the probe tip, set with ``setTcp(frames.tcp_offset)``; the tool z axis points along the inward normal (-z of
  the tissue frame) at every probe pose.

Each probe: ``approach_pose`` (tip ``motion.approach_height_m`` above the undeformed surface at x_m), then a slow
straight descent along the tool axis to ``indent_pose`` (tip ``depth_m`` below the undeformed surface), dwell,
retract to ``approach_pose``. ``force_exponent`` (optional, null: unknown): the prior's force ~ depth^p over the
chord from SURFACE_FIT_FROM_FRACTION of ``motion.contact_threshold_n`` (before session 44: from the threshold) to
``depth_m``; the driver counts its depth limit from the surface a line through F^(1/p) gives (robot.tissue_depth).

Timing (planner/timing.py): every move is a moveL; the descent runs at ``motion.probe_speed_m_s`` over approach height
plus depth, the retract at ``RETRACT_SPEED_M_S``; each move takes the larger of its tool-speed and joint-limit times.
``options`` holds the planning options a re-plan must reuse (IK branch, tilt tolerance, force fraction, minimum
depth); ``notes`` only the planner's diagnostics, which nothing reads back: ``solver`` (status, iterations, ``used``:
"nlp" or "seed"), ``timing`` (per-move breakdown), ``times_s``, ``depth_limited_by`` (per probe: "force" or
"depth"), ``target_force_n``. Version 1 files (options inside ``notes``) are read and converted.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

from core.textfile import NESTED_TOO_DEEP, InputFileError, read_user_text

PLAN_VERSION = 2
# a probe's force_exponent (null: unknown): an indentation's force grows at least as fast as its depth (a flat punch:
# p = 1; a sphere 1.5, a cone 2); below 1 the surface's fit found no line and the depth limit went unguarded (0.5 let
# the tip 5.35 mm into tissue 2 mm higher than registered against a 4 mm limit: session 54's safety review)
MIN_FORCE_EXPONENT, MAX_FORCE_EXPONENT = 1.0, 4.0
# the driver's depth limit fits the descent's force curve from where it last rose past this fraction of the contact
# threshold (robot.driver._ForceWatch, robot.tissue_depth); the planner's force_exponent is the prior's over the
# same chord: from this fraction of the threshold to the planned depth
SURFACE_FIT_FROM_FRACTION = 0.3
READABLE_PLAN_VERSIONS = (1, 2)

# Hard caps: no plan may ask for more, whatever its limits say; the planner's options, Plan.check and the driver's
# guard (robot.safety) use these same constants.
HARD_FORCE_LIMIT_N = 10.0          # contact force
MIN_PROBE_SPACING_M = 1e-5         # neighbouring raster points closer than this are one spot for a UR5e (+-0.03 mm)
HARD_DEPTH_LIMIT_M = 0.02          # indentation below the undeformed surface (the tip radius is the other cap)
HARD_TOOL_SPEED_M_S = 0.25         # tool speed in free air
HARD_PROBE_SPEED_M_S = 0.01        # tool speed inside tissue
MIN_PROBE_SPEED_M_S = 1e-4         # slower: a 4 mm descent would take over 40 s (and a run days, in the simulator)
MIN_TOOL_SPEED_M_S = 1e-3          # moves between probes
MIN_ACCEL_M_S2 = 1e-2
HARD_ACCEL_M_S2 = 1.5
MAX_DWELL_S = 10.0                 # hold at depth
MIN_APPROACH_HEIGHT_M = 0.002      # the tip above the registered surface before a descent (robot.safety)
MAX_APPROACH_HEIGHT_M = 0.05
DEFAULT_TIP_RADIUS_M = 0.005       # fem.scene.Indenter's default, for a plan scene without [indenter]


class PlanError(ValueError):
    """A plan that cannot be made or executed: an infeasible planning request or a bad plan file. The message names
    the option or field to change."""


@dataclass
class Limits:
    force_limit_n: float = 2.0           # no probe may be planned or driven above this contact force
    depth_limit_m: float = 0.004         # no probe deeper than this below the undeformed surface (< tip radius)
    workspace_min_m: list[float] = field(default_factory=lambda: [-0.8, -0.8, -0.1])  # base-frame box for the TCP
    workspace_max_m: list[float] = field(default_factory=lambda: [0.8, 0.8, 0.8])
    max_tool_speed_m_s: float = 0.25


TIP_DEPTH_FRACTION = 0.8     # a default depth limit never deeper than this fraction of the tip's radius


def default_depth_limit_m(tip_radius_m: float) -> float:
    """The depth limit a plan or a run takes (and the depth predict presses to) when none is given:
    Limits().depth_limit_m (4 mm), or on a tip of radius below 5 mm TIP_DEPTH_FRACTION of its radius (the built-in
    tips' own ratio, 4 mm on 5 mm). Before session 52 a tip of radius 4 mm or less refused the default and needed
    --depth-limit-m (a review's 2 mm sphere), and one of 4-5 mm was pressed to 4 mm, 0.8-1.0 of its radius (the
    localizer's tissue response reaches 0.96 of it: planner.tissue_response.MAX_FRAC)."""
    return min(Limits().depth_limit_m, round(TIP_DEPTH_FRACTION * tip_radius_m, 7))    # (to 0.1 um: 2.4 mm, not
    #                                                                            0.0024000000000000002 m)


def default_depth_said(tip_radius_m: float) -> str:
    """How a command says it took ``default_depth_limit_m`` on a small tip ("" when it is the 4 mm default)."""
    d = default_depth_limit_m(tip_radius_m)
    if d >= Limits().depth_limit_m:
        return ""
    return (f"{d * 1e3:g} mm (by default {TIP_DEPTH_FRACTION:g} of the tip's radius, {tip_radius_m * 1e3:g} mm, where "
            f"that is below {Limits().depth_limit_m * 1e3:g} mm)")


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
    y_m: float = 0.0                     # tissue frame, along a 3D block's length (0 on a 2D section's plane)
    # the prior's force ~ indentation^p here, p over the chord from the contact threshold to depth_m: the driver's
    # depth limit counts the indentation at which contact was felt from it (robot.tissue_depth); None (a plan
    # without it): the limit counts from the contact felt
    force_exponent: float | None = None


@dataclass
class PlanOptions:
    """The planning choices a re-plan around a candidate stone must keep."""
    branch: list[int] = field(default_factory=lambda: [1, 1, -1])   # IK branch: signs of shoulder, elbow, wrist
    tilt_tol_rad: float = math.radians(0.5)   # tool axis within this of the inward surface normal
    force_fraction: float = 0.5                # depths chosen so the prior force stays under this x force limit
    min_depth_m: float = 0.001                 # shallowest useful indentation


# a probe's fields an older plan may lack: y_m (2D plans before the 3D work: 0, the section's plane; a 3D plan must
# have it) and force_exponent (before session 43: None, the depth limit counts from the contact felt)
OPTIONAL_PROBE_FIELDS = ("y_m", "force_exponent")
PLAN_SCENE_TABLES = ("tissue", "indenter", "analysis")    # a plan's scene holds each (Scene.to_dict writes them)


def _table(cls, d, where: str, optional: tuple = ()):
    """``cls(**d)`` for a plan file's table ``where``, every field present (no default is taken for a limit, a speed
    or a pose the file left out: a hand-edited plan that dropped its force limit ran with 2 N) but ``optional``'s."""
    if d is None:
        raise PlanError(f"plan field '{where}' is missing: re-plan with palpate plan or restore it")
    if not isinstance(d, dict):
        raise PlanError(f"plan field '{where}' must be a table, got {type(d).__name__}")
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(d) - set(names))
    if unknown:
        raise PlanError(f"plan field {where}.{unknown[0]} is unknown: {where} has {', '.join(names)}")
    missing = [n for n in names if n not in d and n not in optional]
    if missing:
        raise PlanError(f"plan field {where}.{missing[0]} is missing: no default is taken for it (a plan palpate "
                        f"writes has {', '.join(n for n in names if n not in optional)}); re-plan with palpate plan "
                        f"or restore the field")
    return cls(**d)


@dataclass
class Plan:
    scene: dict                          # the prior scene (Scene.to_dict() of scene.prior()): no stones
    frames: Frames = field(default_factory=Frames)
    limits: Limits = field(default_factory=Limits)
    motion: Motion = field(default_factory=Motion)
    options: PlanOptions = field(default_factory=PlanOptions)
    probes: list[Probe] = field(default_factory=list)
    total_time_s: float = 0.0
    version: int = PLAN_VERSION
    notes: dict = field(default_factory=dict)  # planner diagnostics (solver status, timings); never read back

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def save(self, path: str | Path) -> None:
        """Write atomically (a temp file renamed over ``path``): a crash never leaves a torn plan."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(self.to_dict(), indent=1, allow_nan=False))
        tmp.replace(path)

    @staticmethod
    def from_dict(d: dict) -> "Plan":
        if not isinstance(d, dict):
            raise PlanError("a plan must be a JSON object")
        if type(d.get("version")) is not int or d["version"] not in READABLE_PLAN_VERSIONS:   # not True, not 2.0
            raise PlanError(f"plan version {d.get('version')!r} is not supported (this palpate reads "
                            f"{', '.join(map(str, READABLE_PLAN_VERSIONS))})")
        if d["version"] == 1 and "options" in d:
            raise PlanError("plan field 'options' is version 2's (version 1 kept its options in 'notes'): set "
                            "\"version\": 2 or move them into 'notes'")
        unknown = sorted(set(d) - {f.name for f in dataclasses.fields(Plan)})
        if unknown:
            raise PlanError(f"plan field(s) {', '.join(map(repr, unknown))} unknown: a plan has "
                            f"{', '.join(f.name for f in dataclasses.fields(Plan))}")
        if not isinstance(d.get("scene"), dict):
            raise PlanError(f"plan field 'scene' must be a table of the prior scene, got {type(d.get('scene')).__name__}")
        for part in PLAN_SCENE_TABLES:      # (fem's scene defaults, a 5 mm cylinder among them, are no plan's)
            if not isinstance(d["scene"].get(part), dict):
                raise PlanError(f"plan field scene.{part} is missing or not a table: no default is taken for it (the "
                                f"tip's radius bounds the depth limit); re-plan with palpate plan or restore it")
        try:
            json.dumps(d.get("notes", {}), allow_nan=False)
        except ValueError:
            raise PlanError("plan field 'notes' holds a number that is not finite (NaN or inf): palpate writes none "
                            "there, and the run's copy of the plan could not be written; restore or remove it") from None
        try:
            notes = d.get("notes", {})
            notes = dict(notes) if isinstance(notes, dict) else {"ignored": notes}
            if d["version"] == 1:       # options lived in notes
                opts = {k: notes[k] for k in ("branch", "tilt_tol_rad", "force_fraction", "min_depth_m") if k in notes}
            else:
                opts = d.get("options")
            parts = {name: _table(cls, d.get(name), name) for name, cls in
                     (("frames", Frames), ("limits", Limits), ("motion", Motion))}
            # (version 1 kept its options in notes, some of them left out: those take PlanOptions' defaults)
            options = PlanOptions(**opts) if d["version"] == 1 else _table(PlanOptions, opts, "options")
            if not isinstance(d.get("probes"), list) or not all(isinstance(p, dict) for p in d["probes"]):
                raise PlanError("plan field 'probes' must be a list of tables")
            three_d = isinstance(d["scene"].get("tissue"), dict) and d["scene"]["tissue"].get("length_m") is not None
            optional = OPTIONAL_PROBE_FIELDS if not three_d else tuple(set(OPTIONAL_PROBE_FIELDS) - {"y_m"})
            plan = Plan(scene=d["scene"], **parts, options=options,
                        probes=[_table(Probe, p, f"probes[{i}]", optional) for i, p in enumerate(d["probes"])],
                        total_time_s=d.get("total_time_s", 0.0), version=PLAN_VERSION, notes=notes)
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, PlanError):
                raise
            raise PlanError(f"malformed plan: {e}") from None
        plan.check()
        return plan

    @staticmethod
    def load(path: str | Path) -> "Plan":
        try:
            d = json.loads(read_user_text(path, "plan"))
        except InputFileError as e:
            raise PlanError(str(e)) from None
        except json.JSONDecodeError as e:
            raise PlanError(f"cannot read plan {path}: not valid JSON ({e})") from None
        except (OSError, UnicodeDecodeError) as e:
            raise PlanError(f"cannot read plan {path}: {e}") from None
        except RecursionError:
            raise PlanError(f"cannot read plan {path}: {NESTED_TOO_DEEP}") from None
        try:
            return Plan.from_dict(d)
        except PlanError as e:          # which file (a run's own saved plans are read too)
            raise PlanError(f"plan {path}: {e}") from None

    def tip_radius_m(self) -> float:
        """The probe tip's radius from the plan's scene (``scene.indenter.radius_m``)."""
        ind = self.scene.get("indenter", {}) if isinstance(self.scene, dict) else {}
        r = ind.get("radius_m", DEFAULT_TIP_RADIUS_M) if isinstance(ind, dict) else None
        if not _is_num(r) or not math.isfinite(r) or r <= 0:
            raise PlanError(f"plan field scene.indenter.radius_m must be a positive finite number, got {r!r}")
        return float(r)

    def check(self) -> None:
        """What every plan must satisfy, when it is made (the planner, before saving) and when it is read
        (``from_dict``): exact types, finite values, positive limits under the hard caps, probes with unique
        non-negative integer indices and depths in (0, min(tip radius, depth limit)]. The driver makes its own safety
        checks (robot.safety) before sending anything."""
        if not isinstance(self.scene, dict):
            raise PlanError(f"plan field 'scene' must be a table of the prior scene, got {type(self.scene).__name__}")

        def finite(where, values, n=None):
            if not isinstance(values, (list, tuple)):
                raise PlanError(f"plan field {where} must be a list of numbers, got {values!r}")
            values = list(values)
            if n is not None and len(values) != n:
                raise PlanError(f"plan field {where} must have {n} entries, got {len(values)}")
            if not all(_is_num(v) and math.isfinite(v) for v in values):
                raise PlanError(f"plan field {where} must be finite numbers, got {values}")

        def number(where, v, lo=0.0, hi=math.inf, lo_open=True, hi_open=False, allowed=None):
            if not _is_num(v):
                raise PlanError(f"plan field {where} must be a number, got {type(v).__name__} {v!r}")
            ok = math.isfinite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)
            if not ok:
                rng = allowed or f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
                raise PlanError(f"plan field {where} = {v!r} must be a finite number in {rng}")

        finite("frames.tissue_pose_base", self.frames.tissue_pose_base, 6)
        finite("frames.tcp_offset", self.frames.tcp_offset, 6)
        finite("limits.workspace_min_m", self.limits.workspace_min_m, 3)
        finite("limits.workspace_max_m", self.limits.workspace_max_m, 3)
        if any(lo >= hi for lo, hi in zip(self.limits.workspace_min_m, self.limits.workspace_max_m)):
            raise PlanError("plan field limits.workspace_min_m must be below limits.workspace_max_m on every axis")
        L, mo = self.limits, self.motion
        tip = self.tip_radius_m()
        tis = self.scene.get("tissue", {})
        width = tis.get("width_m", math.inf) if isinstance(tis, dict) else math.inf
        width = float(width) if _is_num(width) and math.isfinite(width) and width > 0 else math.inf
        length = tis.get("length_m") if isinstance(tis, dict) else None      # a 3D block; None: a 2D section
        length = float(length) if _is_num(length) and math.isfinite(length) and length > 0 else None
        number("limits.force_limit_n", L.force_limit_n, hi=HARD_FORCE_LIMIT_N,
               allowed=f"(0, {HARD_FORCE_LIMIT_N:g}] N (the hard cap)")
        number("limits.depth_limit_m", L.depth_limit_m, hi=min(tip, HARD_DEPTH_LIMIT_M), hi_open=tip <= HARD_DEPTH_LIMIT_M,
               allowed=f"(0, {min(tip, HARD_DEPTH_LIMIT_M):g}) m (below the tip radius {tip:g} m)")
        number("limits.max_tool_speed_m_s", L.max_tool_speed_m_s, lo=MIN_TOOL_SPEED_M_S, lo_open=False,
               hi=HARD_TOOL_SPEED_M_S)
        number("motion.approach_height_m", mo.approach_height_m, hi=1.0)
        number("motion.approach_speed_m_s", mo.approach_speed_m_s, lo=MIN_TOOL_SPEED_M_S, lo_open=False,
               hi=HARD_TOOL_SPEED_M_S)
        number("motion.approach_accel_m_s2", mo.approach_accel_m_s2, lo=MIN_ACCEL_M_S2, lo_open=False,
               hi=HARD_ACCEL_M_S2)
        number("motion.probe_speed_m_s", mo.probe_speed_m_s, lo=MIN_PROBE_SPEED_M_S, lo_open=False,
               hi=HARD_PROBE_SPEED_M_S)
        number("motion.probe_accel_m_s2", mo.probe_accel_m_s2, lo=MIN_ACCEL_M_S2, lo_open=False,
               hi=HARD_ACCEL_M_S2)
        number("motion.contact_threshold_n", mo.contact_threshold_n, hi=L.force_limit_n, hi_open=True,
               allowed=f"(0, limits.force_limit_n = {L.force_limit_n:g}) N")
        number("motion.dwell_s", mo.dwell_s, hi=MAX_DWELL_S)
        op = self.options
        number("options.tilt_tol_rad", op.tilt_tol_rad, hi=math.pi / 2, hi_open=True)
        number("options.force_fraction", op.force_fraction, hi=1.0)
        number("options.min_depth_m", op.min_depth_m, hi=L.depth_limit_m,
               allowed=f"(0, limits.depth_limit_m = {L.depth_limit_m:g}] m")
        if not (isinstance(op.branch, (list, tuple)) and len(op.branch) == 3 and all(b in (-1, 1) and not isinstance(b, bool)
                                                                             for b in op.branch)):
            raise PlanError(f"plan field options.branch must be three signs like [1, 1, -1], got {op.branch!r}")
        if not isinstance(self.probes, list) or not self.probes:
            raise PlanError("plan field probes must be a non-empty list of probes")
        number("total_time_s", self.total_time_s, lo_open=False)
        seen = set()
        for k, p in enumerate(self.probes):
            if not (isinstance(p.index, int) and not isinstance(p.index, bool)) or p.index < 0:
                raise PlanError(f"plan field probes[{k}].index must be a non-negative integer, got {p.index!r}")
            if p.index in seen:
                raise PlanError(f"plan field probes[{k}].index = {p.index} is used twice (indices must be unique)")
            seen.add(p.index)
            w = f"probes[{k}]"
            number(f"{w}.x_m", p.x_m, lo=0.0, lo_open=False, hi=width,
                   allowed=f"[0, {width:g}] m (on the tissue's top surface, scene.tissue.width_m)")
            if length is None:
                number(f"{w}.y_m", p.y_m, lo=0.0, lo_open=False, hi=0.0,
                       allowed="0 (a 2D section's probes lie in its plane; scene.tissue.length_m makes a 3D block)")
            else:
                number(f"{w}.y_m", p.y_m, lo=0.0, lo_open=False, hi=length,
                       allowed=f"[0, {length:g}] m (on the block's top face, scene.tissue.length_m)")
            number(f"{w}.depth_m", p.depth_m, hi=L.depth_limit_m,
                   allowed=f"(0, limits.depth_limit_m = {L.depth_limit_m:g}] m, below the tip radius {tip:g} m")
            if p.depth_m >= tip:
                raise PlanError(f"plan field {w}.depth_m = {p.depth_m!r} must be below the tip radius {tip:g} m")
            number(f"{w}.predicted_force_n", p.predicted_force_n, lo=0.0, lo_open=False)
            if p.force_exponent is not None:
                number(f"{w}.force_exponent", p.force_exponent, lo=MIN_FORCE_EXPONENT, lo_open=False,
                       hi=MAX_FORCE_EXPONENT, allowed=f"[{MIN_FORCE_EXPONENT:g}, {MAX_FORCE_EXPONENT:g}] or null "
                       f"(the prior's force ~ depth^p: 1 a flat punch, 1.5 a Hertz sphere)")
            number(f"{w}.t_start_s", p.t_start_s, lo_open=False)
            number(f"{w}.duration_s", p.duration_s, lo_open=False)
            finite(f"{w}.approach_pose", p.approach_pose, 6)
            finite(f"{w}.indent_pose", p.indent_pose, 6)
            finite(f"{w}.q_approach_rad", p.q_approach_rad, 6)
            finite(f"{w}.q_indent_rad", p.q_indent_rad, 6)


def _is_num(v) -> bool:
    """A real number, not a bool (JSON true is not 1)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


# ---------------------------------------------------------------------------------------------------------------
# The probe protocol: how the driver measures, what the planner and localizer assume of it

RECORD_ABS_MAX = 1e6             # no force (N) or length (m) in a probe record is larger (forces <= 10 N)

PERIOD_S = 0.002                 # controller period (500 Hz on e-Series)
FILTER_WINDOW = 5                # moving average for contact / force-limit decisions (periods)
NOISE_SIGMA_FACTOR = 5.0         # force thresholds must exceed this many filtered-noise sigmas
N_ZERO_AVERAGE = 50              # readings the sensor's zeroing averages (ur_rtde zeroFtSensor)
FREE, DESCENT, DWELL, RETRACT = 0, 1, 2, 3          # raw "phase" codes
BASELINE_CLEARANCE_M = 1e-3      # free-air baseline: descent samples at least this far above the surface
MIN_BASELINE_SAMPLES = 50        # fewer: no baseline (the force is then relative to the sensor's zeroing)
BASELINE_SETTLE_S = 0.05         # ... and not in the descent's first 50 ms (acceleration)
ZERO_SETTLE_S = 0.04             # before each probe the driver waits this long, zeroes the sensor, waits again,
NOISE_SAMPLE_S = 0.1             # and samples the free-air noise this long (the plan's timing counts the three)
RETRACT_SPEED_M_S = 0.02         # the driver retracts from the tissue at this tool speed (at most), probe acceleration


# Plausibility of a probe's force (dwell mean minus its free-air baseline) against the prior's prediction at the
# same indentation: the tissue's modulus is known to a factor of about 4 either way, and a stone under the tip adds
# force but never makes tissue pull; beyond this band, by more than PLAUSIBLE_SIGMAS of the probe's own noise, the
# reading is a sensor or setup problem (a wrong sign, an unseen offset, the wrong sensor), not tissue.
PLAUSIBLE_FORCE_RATIO = (0.25, 10.0)
PLAUSIBLE_SIGMAS = 5.0


class ProbeStatus(StrEnum):
    """How one probe attempt ended (``status`` in probes.jsonl)."""
    OK = "ok"                        # reached its depth, dwelt, retracted
    FORCE_LIMIT = "force_limit"      # stopped at the force limit (e.g. over a stone): a usable, shallower probe
    DEPTH_LIMIT = "depth_limit"      # stopped the depth limit past the contact felt (the surface higher than the
    #                                  plan's): a usable, shallower probe
    REJECTED = "rejected"            # failed the safety checks, never moved
    FAULT = "fault"                  # ended early by a fault; its samples are kept
    INTERRUPTED = "interrupted"      # ended early by Ctrl-C; its samples are kept


MEASURED = (ProbeStatus.OK, ProbeStatus.FORCE_LIMIT, ProbeStatus.DEPTH_LIMIT)   # statuses whose force is measured


class RunStatus(StrEnum):
    """How a driver run ended (``status`` in run.json)."""
    OK = "ok"
    FAULT = "fault"
    INTERRUPTED = "interrupted"
    REJECTED = "rejected"            # the plan failed the safety checks: nothing was sent
    RUNNING = "running"              # written as a round starts: a run.json that still says so was cut off (killed)


class FaultKind(StrEnum):
    """Why a run stopped (``fault.kind`` in run.json)."""
    CONNECTION_LOST = "connection_lost"
    PROTECTIVE_STOP = "protective_stop"
    COMMAND_FAILED = "command_failed"
    MOVE_FAILED = "move_failed"
    INVALID_READING = "invalid_reading"
    TIMEOUT = "timeout"
    SENSOR_NOISE = "sensor_noise"
    FORCE_LIMIT = "force_limit"      # too many consecutive force-limit stops
    COLLISION = "collision"          # force above the limit outside a descent
    SAFETY_VIOLATION = "safety_violation"
    INTERRUPTED = "interrupted"
    CLIENT_CRASHED = "client_crashed"  # the process holding the ur_rtde link died (app.isolate)
    PROGRAM_STOPPED = "program_stopped"  # an operator stopped the control program (pendant, dashboard, local mode)
    SENSOR_LOST = "sensor_lost"          # the external F/T sensor sends nothing (cable, box, network)
    SENSOR_STATUS = "sensor_status"      # the external F/T sensor reports a problem in its status word
    SENSOR_SATURATED = "sensor_saturated"  # a reading at the sensor's rated range: the force is unknown
    SENSOR_PACKET_LOSS = "sensor_packet_loss"  # too many of its records lost on the way
    SENSOR_FROZEN = "sensor_frozen"      # its readings stopped changing (a real sensor always has noise)
    SENSOR_DISAGREES = "sensor_disagrees"  # the wrist sensor reads far more than the external one
    DRIVER_ERROR = "driver_error"        # an unexpected error (a full disk, a bug): the arm stopped, then raised
    FREE_AIR_FORCE = "free_air_force"    # a force at an approach pose before zeroing: the tip touches something
    #                                      there (the surface higher than registered) or the sensor drifts
    SURFACE_HIGH = "surface_high"        # contact within the first mm of a descent: the surface at the approach pose
    CONTACT_UNFELT = "contact_unfelt"    # a probe's predicted force at its depth not above the contact threshold:
    #                                      no contact felt, no depth limit from the true surface (checked before it)
    LATERAL_FORCE = "lateral_force"      # the force across the tissue normal above its limit (the tip caught or
    #                                      pushed from the side)
    RETRACT_FORCE = "retract_force"      # leaving the tissue, the force along its normal rose past the limit or
    #                                      pulled towards the tissue (the tissue holding the tip): stopped, not retracted
    FORCE_DIRECTION = "force_direction"  # the force on the tip far from the normal the tool is held along (an external
    #                                      sensor's orientation stated wrong, a surface far steeper than registered)


@dataclass
class ProbeRecord:
    """One probe attempt: a line of probes.jsonl (written by robot.records, read by planner.localize). SI units in
    every name; None where a quantity was not measured (a rejected probe has only index, x_m, status, reason)."""
    index: int
    x_m: float                                   # planned tissue-frame position along the surface
    status: ProbeStatus
    depth_planned_m: float | None = None         # planned indentation
    depth_target_m: float | None = None          # planned indentation capped at the depth limit
    depth_reached_m: float | None = None         # mean indentation over the dwell (or the last descent samples)
    contact_x_m: float | None = None             # tissue-frame x of the tip over the dwell
    y_m: float = 0.0                             # planned tissue-frame y (3D block; 0 on a 2D section)
    contact_y_m: float | None = None             # tissue-frame y of the tip over the dwell
    contact_depth_m: float | None = None         # indentation at which contact was first felt
    force_mean_n: float | None = None            # mean contact force over the dwell
    force_std_n: float | None = None
    force_peak_n: float | None = None
    force_dwell_start_n: float | None = None     # mean over the first fifth of the dwell (relaxation: vs the last)
    force_dwell_end_n: float | None = None       # mean over the last fifth of the dwell
    force_baseline_n: float | None = None        # free-air mean of the same descent (None: too few samples)
    force_baseline_std_n: float | None = None
    n_samples_baseline: int = 0
    baseline_to_dwell_s: float | None = None     # time from the baseline's middle to the dwell's middle
    force_baseline_at_contact_n: float | None = None  # the free-air readings' straight line (offset and drift) at
    #                                              the first contact: what the sensor read at zero force then
    force_predicted_prior_n: float | None = None  # the planner's prediction for the stone-free prior
    n_samples: int = 0
    n_samples_total: int = 0
    contact_threshold_n: float | None = None
    noise_std_n: float | None = None             # free-air noise measured after zeroing
    t_s: float | None = None                     # controller time at the probe's start
    duration_s: float | None = None
    wall_time_utc: str | None = None
    reason: str | None = None                    # why a probe was rejected or ended early
    implausible: str | None = None               # why its force cannot be tissue (kept out of localization)
    raw_file: str | None = None                  # raw samples, relative to the run directory

    def __post_init__(self):
        self.status = ProbeStatus(self.status)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "ProbeRecord":
        """A record from its probes.jsonl line's dict; ValueError for a number no driver writes (not finite; a force
        or length beyond RECORD_ABS_MAX: 1e308 N overflowed the localizer's residuals; times are a controller's
        clock, days of uptime, and only finite) or of the wrong type."""
        kinds = {f.name: str(f.type) for f in dataclasses.fields(ProbeRecord)}
        for k, v in d.items():
            if k not in kinds:          # (a later version's field: not read)
                continue
            if _is_num(v) and not math.isfinite(v):
                raise ValueError(f"{k} = {v!r} is not a number a probe records (finite)")
            if _is_num(v) and k.endswith(("_n", "_m")) and abs(v) > RECORD_ABS_MAX:
                raise ValueError(f"{k} = {v!r} is not a force or length a probe records (within "
                                 f"+-{RECORD_ABS_MAX:g})")
            t = kinds[k]
            if t.startswith(("float", "int")) and not (_is_num(v) or (v is None and "None" in t)):
                raise ValueError(f"{k} = {v!r} is not a number")
        return ProbeRecord(**{k: v for k, v in d.items() if k in kinds})

    @property
    def measured(self) -> bool:
        """A force measurement the localizer may use: ended ok or at the force limit, and plausible."""
        return self.status in MEASURED and self.implausible is None


# ---------------------------------------------------------------------------------------------------------------
# Force/torque sensors: datasheet figures a user knows before probing

@dataclass(frozen=True)
class SensorSpec:
    name: str
    noise_std_n: float          # white noise per force axis (N)
    noise_std_nm: float         # white noise per torque axis (N m)
    bias_n: float               # std of the random constant force bias per axis (N)
    drift_n_per_s: float        # std of the random linear drift rate per axis (N/s)
    resolution_n: float = 0.0   # quantisation step of the force reading (0: none)
    range_n: float = float("inf")  # readings saturate here


# ``ur5e-builtin``: the UR5e wrist sensor: precision ~3.5 N and accuracy ~5.5 N (docs/reference.md) read as a
# 2-sigma band (noise std 1.75 N per axis), a bias of a few N and a temperature drift of ~0.05 N/s. Far coarser than
# soft-tissue forces (0.1-1 N): with a 2 N force limit the driver refuses to probe with it.
# ``nano17``: a precise external sensor (ATI Nano17 class): resolution ~3 mN, noise std 3 mN, tiny drift.
SENSORS = {
    "ur5e-builtin": SensorSpec("ur5e-builtin", noise_std_n=1.75, noise_std_nm=0.05, bias_n=3.0,
                               drift_n_per_s=0.05, resolution_n=0.0, range_n=50.0),
    "nano17": SensorSpec("nano17", noise_std_n=0.003, noise_std_nm=1.5e-5, bias_n=0.05,
                         drift_n_per_s=1e-4, resolution_n=0.003125, range_n=35.0),
    "ideal": SensorSpec("ideal", noise_std_n=0.0, noise_std_nm=0.0, bias_n=0.0, drift_n_per_s=0.0),
}


def sensor_spec(preset: "str | SensorSpec", **overrides) -> SensorSpec:
    """A sensor by preset name (``SENSORS``), optionally with fields replaced."""
    if isinstance(preset, SensorSpec):
        s = preset
    else:
        try:
            s = SENSORS[preset]
        except (KeyError, TypeError):
            raise ValueError(f"unknown sensor {preset!r}; known: {', '.join(SENSORS)}") from None
    return dataclasses.replace(s, **overrides) if overrides else s
