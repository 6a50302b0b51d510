"""The probing driver: runs a plan's probes over ur_rtde's control and receive interfaces (or the simulated arm).

``run_plan(plan, rtde_c, rtde_r, out_dir) -> RunReport``. Per probe: moveL above the waypoint (approach pose), check
there that the force against the last free-air zero is within the free-air band (``free_air_band_n``: else the tip
touches something or the sensor drifts, a fault), zero the F/T sensor there, measure the free-air noise, descend
slowly with an *asynchronous* moveL whose target is the planned depth (so even a lost link ends the motion there --
never moveUntilContact, which has no distance limit) while polling the wrench every controller period, note first
contact (filtered force above the contact threshold; in the first millimetre of the descent a fault: the surface is
at the approach pose), stop with stopL if the filtered force exceeds the force limit, dwell and sample, retract to
the approach pose. Only moveL is used (the plan's joint targets q_* are not needed; straight lines keep the path
inside the convex workspace box). Every command passes safety.GuardedControl; every bool is checked; None/NaN/short
receive vectors, a protective stop, a lost connection (RuntimeError, or stale data with isConnected() False: what
ur_rtde shows), stale data and time-outs are faults that end the run in a safe state (stopped; retracted when the
arm still accepts commands) with a report in run.json. A fault during a probe sends one stopL first (the arm may still
be descending), then the interrupted probe's record, its samples and run.json are written, then the rest of the safe
state (the retract). While the link is down no command is sent (ur_rtde 1.6.5 can block for good on one after its
own reconnect failed); reconnect() is tried once after ``DriverConfig.reconnect_after_s``.

The wrench comes from a force source (robot.forcesource): the UR's wrist sensor over the receive interface by
default, or an external ATI Net F/T box over UDP; the UR's own force protection never sees the latter, so then this
driver's force limit is the only guard on the contact force. A sensor fault (robot.netft.SensorFault: silent, bad
status, saturated, too many records lost) is a probe fault like the others.

Contact force convention: getActualTCPForce is the external force on the tool in the base frame; the contact force
is its projection on the tissue's outward normal n (z axis of ``frames.tissue_pose_base``), times
``DriverConfig.force_sign`` (+1): tissue pushing the tip back out gives a positive force. Verify the sign on a new
cell with a gentle push before the first run. Time-outs count controller periods (waitPeriod paces the loop), so
they are wall time on a real arm and simulated time on the simulated one.
"""
from __future__ import annotations

import dataclasses
import gc
import math
import time
from collections import deque
from dataclasses import dataclass, field
from functools import reduce
from operator import add

import numpy as np

from core import ur5e
from core.arrays import first_true
from core.contracts import (
    DESCENT,
    DWELL,
    FILTER_WINDOW,
    FREE,
    MIN_FORCE_EXPONENT,
    NOISE_SAMPLE_S,
    NOISE_SIGMA_FACTOR,
    PERIOD_S,
    RETRACT,
    RETRACT_SPEED_M_S,
    SURFACE_FIT_FROM_FRACTION,
    ZERO_SETTLE_S,
    FaultKind,
    ProbeRecord,
    ProbeStatus,
    RunStatus,
)
from robot.forcesource import ForceSource, RtdeForce
from robot.link import BLOCKING_CALLS, UR_READY_TIMEOUT_S, CallTimeout, CallWorker, deadline_for
from robot.netft import SensorFault
from robot.records import RunLog, done_indices, last_retract_blocked, summarise
from robot.recovery import ProbeFault, Recovery
from robot.safety import (
    GuardedControl,
    SafetyLimits,
    SafetyViolation,
    TissueFrame,
    check_plan,
    preflight,
)
from robot.safety import move_time as _move_time
from robot.signals import SignalGate
from robot.tissue_depth import SurfaceFit

# contact felt within this much of a descent's start (or half the approach height, when smaller) is a fault: the
# surface is at the approach pose (robot.driver._ForceWatch._early)
EARLY_CONTACT_M = 1e-3
# the free-air checks (Driver._check_free_air, _ForceWatch._pulled) allow the contact threshold plus this drift rate
# times the time since the zero: twice the localizer's prior sigma on the drift (planner.localize, 1e-3 N/s, 10x a
# Nano17's), which its fit absorbs. Beyond it a drift is a fault only once it has added up past the threshold too.
DRIFT_ALLOWANCE_N_PER_S = 2e-3
# ... plus the weight of the tool turned between the two zeros: an external sensor's zero is an offset in its own
# frame, so the weight below it comes back as m g (angle) when the tool turns (30 g turned 4 degrees: 20 mN, the
# threshold; the paper plan's approach poses turn 0.6 degrees from one to the next). m: DriverConfig.payload_kg (the
# whole tool's, an upper bound on what hangs below the sensor). The set-up's zero, wherever the arm starts, is thus
# a reference for probe 0 only when the tool points nearly the same way; the descent's checks hold regardless.
GRAVITY_M_S2 = 9.81


@dataclass
class DriverConfig:
    period_s: float = PERIOD_S         # controller period (500 Hz on e-Series)
    filter_window: int = FILTER_WINDOW  # moving average for contact / force-limit decisions
    settle_s: float = ZERO_SETTLE_S    # wait before and after zeroing
    noise_sample_s: float = NOISE_SAMPLE_S  # free-air sampling after zeroing
    noise_sigma_factor: float = NOISE_SIGMA_FACTOR  # thresholds must exceed this many filtered-noise sigmas
    stop_decel_m_s2: float = 10.0
    retract_speed_m_s: float = RETRACT_SPEED_M_S
    timeout_factor: float = 2.0
    timeout_margin_s: float = 2.0
    stale_periods: int = 100           # timestamp not advancing this many periods (0.2 s): a silent link. A real
                                       # controller sends every period; this margin keeps a host or simulator held
                                       # up by a busy machine from being taken for one. The watchdog (<= 0.2 s)
                                       # stops the arm on its own meanwhile.
    reconnect_after_s: float = 5.0     # link lost: wait this long (controller periods) for it to come back on its
                                       # own before calling reconnect() (ur_rtde reconnects in the background)
    payload_kg: float = 0.1
    payload_cog_m: tuple = (0.0, 0.0, 0.05)
    force_sign: float = 1.0
    skip_invalid: bool = False         # True: record unsafe probes as "rejected" and run the others
    max_consecutive_force_stops: int = 3
    watchdog_hz: float = 5.0           # the controller's RTDE watchdog (ur_rtde setWatchdog): if the driver's inputs
                                       # stop for 1/rate (a lost link, a hung host) the controller stops the program
                                       # and the motion. Kicked every period. This is the lowest rate; 0: off.
    max_unsupervised_travel_m: float = 4e-4   # ... and the rate is raised so that a probe moving at its speed
                                       # travels at most this far before that stop (see watchdog_rate_hz)
    fast_forward: bool = True          # on a simulator that can look ahead (robot.sim's look_ahead): step quiet
                                       # periods (nothing for the driver to do but record) many at once -- the
                                       # same records, decisions and commands, tests compare them; False: one by one
    wrist_backstop_margin_n: float = 5.0  # with an external sensor: the wrist sensor (zeroed with it) reading
                                       # more than the force limit + this along the normal (filtered) is a fault --
                                       # the external one, which should have stopped the probe, is stuck, misread
                                       # or wrongly mounted. 5 N is 6.4 sigma of the filtered UR5e wrist noise
                                       # (1.75 N / sqrt(5)). 0: off
    lateral_force_limit_n: float | None = None  # the filtered force across the tissue normal (the wrench's force
                                       # less its part along the normal) above this in a descent or a dwell, or
                                       # above this plus the tool's weight turned since the zero while moving to an
                                       # approach pose: a fault (lateral_force). None: the plan's force limit; inf: off


NEEDS_PROGRAM = frozenset({"moveL", "zeroFtSensor", "setTcp", "setPayload", "setWatchdog"})
# calls made every period that never wait for the controller and need no running program: straight through
_PLAIN_CALLS = frozenset({"getTimestamp", "getActualTCPPose", "getActualTCPForce", "isProtectiveStopped",
                          "isConnected", "initPeriod", "waitPeriod", "getAsyncOperationProgress", "isProgramRunning",
                          "kickWatchdog"})
assert not _PLAIN_CALLS & (BLOCKING_CALLS | NEEDS_PROGRAM)
PROGRAM_STOPPED_BY_OPERATOR = ("the control program was stopped from the pendant or the dashboard (or the pendant "
                               "was switched to local control), not by its watchdog: the driver does not restart "
                               "what an operator stopped")


def watchdog_rate_hz(cfg: DriverConfig, probe_speed_m_s: float) -> float:
    """The watchdog rate for probes at ``probe_speed_m_s``: at least ``cfg.watchdog_hz``, enough that a lost link
    lets a probe travel at most ``cfg.max_unsupervised_travel_m`` unsupervised, at most 100 Hz (kicks go out at
    500 Hz; a faster watchdog would trip on ordinary host jitter). 0 when the watchdog is off."""
    if cfg.watchdog_hz <= 0:
        return 0.0
    return float(min(100.0, max(cfg.watchdog_hz, probe_speed_m_s / cfg.max_unsupervised_travel_m)))


def stop_lead_periods(filter_window: int) -> int:
    """Periods between a force and the arm's stop: the moving average's lag, the reading's latency, the stop."""
    return filter_window // 2 + 2


def unfelt_force_n(p, motion, depth_limit_m: float, threshold_n: float) -> float | None:
    """The prior's force at the depth limit's indentation for probe ``p`` (its predicted force continued as depth^p,
    p its exponent or the flattest a plan may give) when it is not FEEL_MARGIN x ``threshold_n`` and the probe's depth
    plus the approach height passes the limit -- a probe that might feel no contact before the limit
    (``Driver._check_feelable``) -- else None. A plan made in code with no prediction (0) is not judged (as for
    robot.records.implausibility; the planner's plans always predict)."""
    if p.depth_m + motion.approach_height_m <= depth_limit_m or not p.predicted_force_n > 0:
        return None
    f_limit = p.predicted_force_n * (depth_limit_m / p.depth_m) ** (p.force_exponent or MIN_FORCE_EXPONENT)
    return None if f_limit > FEEL_MARGIN * threshold_n else float(f_limit)


def unfelt_probes(plan) -> dict[int, str]:
    """{probe index: why} for the probes the driver would certainly stop with ``contact_unfelt`` before their descent,
    judged on the plan's own contact threshold (a sensor's noise can only raise it): a plan whose threshold no probe
    can pass is refused before anything starts, not at its first probe (session 56's review: exit 1, "the same
    command resumes", which could never succeed)."""
    mo, limit = plan.motion, plan.limits.depth_limit_m
    out = {}
    for p in plan.probes:
        f = unfelt_force_n(p, mo, limit, mo.contact_threshold_n)
        if f is not None:
            out[p.index] = (f"the prior's force at the depth limit ({f:.4f} N) is not {FEEL_MARGIN:g} x "
                            f"motion.contact_threshold_n ({mo.contact_threshold_n:g} N): it might feel no contact "
                            f"before the limit (a surface up to the approach height higher than registered); lower "
                            f"the threshold or plan a smaller approach height")
    return out


def force_when_stopped(hist, lead: int) -> float:
    """Where the filtered force will be when the arm has stopped: the newest of ``hist`` (filtered forces, one per
    period) plus its rising slope over ``lead`` periods. The force monitor stops when this exceeds the limit."""
    slope = (hist[-1] - hist[0]) / (len(hist) - 1) if len(hist) > 1 else 0.0
    return hist[-1] + max(slope, 0.0) * lead


@dataclass
class RunReport:
    status: RunStatus
    out_dir: str
    n_planned: int = 0
    n_ok: int = 0
    n_force_limit: int = 0
    n_depth_limit: int = 0             # stopped at the depth limit (the surface higher than planned: robot.tissue_depth)
    n_rejected: int = 0
    n_skipped: int = 0                 # already ok in the log (resume)
    fault: dict | None = None
    problems: list = field(default_factory=list)
    records: list = field(default_factory=list)
    controller_time_s: float = 0.0
    wall_s: float = 0.0
    program_restarts: int = 0          # control programs uploaded again at rest (the watchdog ended one)
    early_contacts_dismissed: int = 0  # readings past the contact threshold near a descent's start, back to free air
    #                                    within a filter window: noise taken for contact (robot.driver._ForceWatch)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d.pop("records")
        return d


def _vec6(v) -> bool:
    """Six finite numbers (their sum is finite exactly when each is, short of an overflow past 1e308: no reading)."""
    try:
        return v is not None and len(v) == 6 and math.isfinite(sum(map(float, v)))
    except (TypeError, ValueError):
        return False


# periods looked ahead at once (1 s): a fault, a stop or a move's end cuts it short. Always the full length: a look's
# cost is mostly fixed (57 us for 4 periods, 131 us for 500 on this machine), so looking short after a period that
# was not quiet and doubling from there (until session 31) cost more looks than it saved (the arm's phase of a
# cached paper run 1.0-1.1 s against 0.8-0.9 s, block3d's 1.9-2.0 against 1.5-1.8; the records the same)
FF_PERIODS = 500
# after a descent stopped at the depth limit the probe dwells where the arm came to rest (its force is measured as
# a planned dwell's is); deeper than that by more than this while it holds, the dwell ends (the arm must not creep)
HOLD_SLACK_M = 1e-4
# the depth limit counts from the surface fitted to a descent's force curve (robot.tissue_depth) where that stands
# more than this above the registered surface: within it, the plan's depth (at most the limit below the registered
# surface) governs, so a small error of the fit (a tissue relaxing by 25 % over 2 s read its lag about 0.1 mm long)
# cannot stop a probe at its planned depth; the tip goes at most this much past the limit unless the fit errs more
SURFACE_TOL_M = 2.5e-4
# a pending early contact (robot.driver._ForceWatch) is noise once the filtered force falls below this fraction of
# the contact threshold (the threshold is >= 5 filtered sigmas of the free-air noise: half of it is >= 2.5 sigmas)
EARLY_DISMISS_FRACTION = 0.5
# the surface's fit (robot.tissue_depth) takes a descent's readings from where the filtered force last rose past
# this fraction of the contact threshold, not only those from the contact on: in soft tissue the contact is felt 2-3
# mm in and the limit leaves 1-1.5 mm of travel after it, so a line through those alone extrapolates far to its zero
# (1000 Pa, the surface 2 mm high: the tip went up to 0.8 mm past a 4 mm limit with a Nano17's noise, session 44's
# review: 4.52-4.75 mm over 3 seeds, now 4.16-4.35); from FIT_FROM_FRACTION of the threshold, or FIT_FROM_SIGMAS
# of the filtered free-air noise measured at the zeroing if that is more (a reading there is that clear of free air)
FIT_FROM_FRACTION = SURFACE_FIT_FROM_FRACTION
FIT_FROM_SIGMAS = 3.0
# readings kept before the contact (the last ones: 2 s of a descent; the rise from 30 % of the threshold to it takes
# about 0.5 s at 2 mm/s in 1000 Pa tissue); they go into the fit at the contact's period at once (1 ms for 1000)
FIT_FROM_MAX = 1024
# a probe whose plan gives no force_exponent (a version-1 plan, or the planner found none): the depth limit still
# counts from the surface fitted to the force curve, with this exponent -- a sphere's; the fit tries exponents down to
# 0.6 of it (robot.tissue_depth), so a flatter truth (a cylinder's 1.1-1.2) puts the fitted surface high and stops the
# probe early, the safe side, and a steeper one goes up to 0.35 mm past the limit, as with a plan's own exponent.
# Before session 54 the limit then counted from the contact felt, and a surface 2 mm high let the tip 5.35 mm into
# the tissue against a 4 mm limit (a safety review)
UNKNOWN_FORCE_EXPONENT = 1.5
# a probe must be predicted to press this many contact thresholds at the depth limit's indentation (Driver.
# _check_feelable): the planner's margin for a suggested depth limit (planner.refine.CONTACT_MARGIN), so tissue a
# third softer than the prior still passes the threshold before the limit
FEEL_MARGIN = 1.5
# the lateral watch (DriverConfig.lateral_force_limit_n) needs its limit this many sigmas of the filtered free-air
# noise across the normal (per axis) clear: the filtered lateral force's length is then past it on noise alone with
# a probability exp(-8^2 / 2) = 1e-14 a period (a 2D Gaussian's length); with the force limit as its limit, a
# sensor that passes the noise check along the normal (5 sigmas within half the limit) passes this one when its
# noise is about the same on every axis
LATERAL_NOISE_SIGMAS = 8.0
# once the filtered force's length passes FORCE_ANGLE_FROM contact thresholds in a descent or dwell (and
# ASKEW_NOISE_SIGMAS of the filtered free-air noise across the normal), the force on the tip may point at most
# FORCE_ANGLE_MAX_RAD from the normal the tool is held along (its force across the normal, less the drift allowed
# since the zero, at most tan of that times its force along it), else the fault force_direction: an external sensor
# whose stated orientation is turned by e from its mounting reads the force along the normal cos(e) short, and the
# force limit with it (a review of session 55: turned 60 degrees, 0.13 N read for 0.29 N, every probe ok); read short
# by at most 18 %, it lets at most 1 / cos(35) = 1.22 times the limit pass. Judged on the force's length, not its part
# along the normal, so that a sensor turned 90 degrees (axes swapped: nothing along) is judged too (the review of the
# check). A surface tilted theta from the registered one leans a frictionless contact's force by theta; friction mu
# moves that by up to atan(mu) either way. From 2 thresholds (at least 10 sigmas of the filtered noise along the
# normal, and 10 across): the noise across it then needs 7 sigmas to trip it, exp(-24.5) = 2e-11 a period
FORCE_ANGLE_MAX_RAD = math.radians(35.0)
FORCE_ANGLE_FROM = 2.0
ASKEW_NOISE_SIGMAS = 10.0
# the free-air check before a zero allows the filtered force across the normal this many of its noise sigmas (per
# axis, measured at the last zero) beyond the free-air band: the length of a 2D noise averaged over the settle's
# second half is about 1.25 sigmas, its spread about 0.5 (a sensor noisier across than along: the review of the check)
FREE_AIR_LATERAL_SIGMAS = 4.0


def window_means(prev, f: np.ndarray, window: int) -> np.ndarray:
    """The moving average the driver's filter gives after each value of ``f`` (``prev``: the values in the filter
    before), each window summed in order as ``_read`` sums it (the same float operations: the same values). ``f``
    may hold rows (vectors, each component filtered alike; ``prev`` then holds such rows)."""
    seq = np.concatenate([np.asarray(list(prev), dtype=float).reshape(-1, *f.shape[1:]), f])
    first = len(seq) - len(f) - window + 1          # the first window's start, when every window is full
    if first >= 0:                  # (the filter full before: the usual case) sliced, not indexed
        acc = seq[first:first + len(f)].copy()
        for o in range(1, window):
            acc += seq[first + o:first + o + len(f)]
        return acc / window
    end = np.arange(len(seq) - len(f), len(seq))
    start = np.maximum(0, end - window + 1)
    acc = seq[start].copy()
    for o in range(1, window):
        idx = start + o
        ok = idx <= end
        acc[ok] += seq[idx[ok]]
    return acc / (end - start + 1).reshape(-1, *([1] * (f.ndim - 1)))


def across_normal(w: np.ndarray, normal) -> np.ndarray:
    """The force of each wrench (rows) across the unit ``normal``: the force less its part along it (as
    ``Driver._across_normal`` computes one: the same float operations)."""
    n0, n1, n2 = normal
    d = w[:, 0] * n0 + w[:, 1] * n1 + w[:, 2] * n2
    return np.column_stack([w[:, 0] - d * n0, w[:, 1] - d * n1, w[:, 2] - d * n2])


def lateral_magnitudes(means: np.ndarray) -> np.ndarray:
    """The length of each filtered lateral force (rows: its three components), as ``_read`` computes it."""
    return np.sqrt(means[:, 0] * means[:, 0] + means[:, 1] * means[:, 1] + means[:, 2] * means[:, 2])


@dataclass
class _Block:
    """Periods read at once (robot.sim's look-ahead): what ``_read`` gives one period at a time, as arrays, and
    the asynchronous progress (getAsyncOperationProgress) of each."""
    ts: np.ndarray
    pose: np.ndarray
    wrench: np.ndarray
    f: np.ndarray
    filt: np.ndarray
    lat: np.ndarray              # the filtered lateral force's magnitude (Driver._read's "lat")
    depth: np.ndarray
    x: np.ndarray
    y: np.ndarray
    prog: list

    @property
    def n(self) -> int:
        return len(self.ts)


SAMPLE_COLUMNS = ("time_s", "tcp_pose", "wrench", "force_n", "depth_m", "x_m", "phase", "y_m")


class _Samples:
    def __init__(self):
        self.rows, self.parts = [], []

    def add(self, *row):
        self.rows.append(row)

    def _flush(self):
        if self.rows:
            self.parts.append({c: np.array([r[i] for r in self.rows], dtype=float)
                               for i, c in enumerate(SAMPLE_COLUMNS)})
            self.rows = []

    def add_block(self, b: _Block, k: int, phase: int) -> None:
        """The first ``k`` periods of ``b``."""
        self._flush()
        self.parts.append({"time_s": b.ts[:k], "tcp_pose": b.pose[:k], "wrench": b.wrench[:k], "force_n": b.f[:k],
                           "depth_m": b.depth[:k], "x_m": b.x[:k], "phase": np.full(k, float(phase)),
                           "y_m": b.y[:k]})

    def arrays(self) -> dict:
        self._flush()
        if not self.parts:
            return {c: np.zeros((0, 6) if c in ("tcp_pose", "wrench") else 0) for c in SAMPLE_COLUMNS}
        if len(self.parts) > 1:
            self.parts = [{c: np.concatenate([p[c] for p in self.parts]) for c in SAMPLE_COLUMNS}]
        return dict(self.parts[0])


def forces_when_stopped(hist, filt: np.ndarray, lead: int) -> np.ndarray:
    """``force_when_stopped`` after each of ``filt`` appended to ``hist`` (a deque with its maxlen) in turn: the
    same float operations, so the same values."""
    seq = np.concatenate([np.asarray(list(hist), dtype=float), filt])
    end = np.arange(len(hist), len(seq))
    start = np.maximum(0, end - hist.maxlen + 1)
    first, last, n = seq[start], seq[end], end - start + 1
    slope = np.where(n > 1, (last - first) / np.maximum(n - 1, 1), 0.0)
    return last + np.maximum(slope, 0.0) * lead


class _Collision:
    """Moving to a probe's approach pose: a force above the limit there, along the normal, or across it above the
    lateral limit plus the tool's weight turned by up to ``turn_rad`` since the zero, is a collision (a fault)."""

    def __init__(self, driver: "Driver", turn_rad: float = 0.0):
        self.d = driver
        self.lat_limit_n = driver.lat_limit_n + driver.cfg.payload_kg * GRAVITY_M_S2 * turn_rad

    def __call__(self, s):
        if s["lat"] > self.lat_limit_n:
            self.d._lateral(s["lat"], self.lat_limit_n, s["filt"], "move to an approach pose")
        return self.d._halt(FaultKind.COLLISION) if s["filt"] > self.d.lim.force_limit_n else None

    def quiet(self, b: _Block, limit: int) -> int:
        return first_true((b.filt[:limit] > self.d.lim.force_limit_n) | (b.lat[:limit] > self.lat_limit_n), limit)


class _RetractWatch:
    """Leaving the tissue along its normal: moving away only lowers the force the tissue pushes back with. The arm
    stops where it is (a fault, ``retract_force`` or ``lateral_force``) if the filtered force along the normal
    rises above the force limit (or above where the retract began, if higher) by a contact threshold -- the tissue
    rising with the tip, a force the sensor should not see -- or pulls towards the tissue more than the force limit
    (or more than where it began) -- the tissue holding the tip, something above pressing on the tool -- or the
    force across the normal rises above its limit (or above where it began) by a contact threshold. The safe state
    after such a fault does not retract again: the retract is what met the force (``Driver.retract_blocked``).

    Where the retract began: the extremes of its first filter window (``filter_window`` periods: 10 ms, under
    0.03 mm from rest at the retract's acceleration), nothing stopped meanwhile but, in a probe's own retract, what
    its descent and dwell would have stopped (``watched``). A retract may begin with forces still entering the filter: a
    probe stopped at the force limit retracts at once, and the safe state's retract follows a fault (a push across
    the normal that ended a descent is still acting).

    ``zeroed``: the sensor was zeroed in free air in this run (the forces are the tissue's). Else (a resumed run's
    first move, the tip perhaps in tissue, the sensor not yet zeroed) only changes from where the retract began
    count: up by more than the force limit, down by more than twice it (the probe's push released, then the limit
    pulling), across by more than the lateral limit."""

    def __init__(self, driver: "Driver", zeroed: bool, watched: bool = False):
        self.d = driver
        self.zeroed = zeroed
        # ``watched``: a probe's retract, its descent and dwell watched to their last period (the force across the
        # normal within its limit, no pull): its first filter window is judged against those limits too, or a push
        # arriving with the retract's first readings would set where it began (session 56's review: 40 N across,
        # the run ok)
        self.watched = watched and zeroed
        self.left = driver.cfg.filter_window        # readings that set where the retract began
        self.f_max, self.f_min, self.lat_max = -math.inf, math.inf, 0.0
        self.hi = self.lo = self.lat_hi = None      # set once they are in

    def _begin(self, s) -> bool:
        """One of the readings where the retract began; True once the bounds are set."""
        if math.isfinite(s["filt"]):
            self.f_max, self.f_min = max(self.f_max, s["filt"]), min(self.f_min, s["filt"])
        if math.isfinite(s["lat"]):
            self.lat_max = max(self.lat_max, s["lat"])
        self.left -= 1
        if self.left > 0:
            return False
        d = self.d
        lim, lat_lim, thr = d.lim.force_limit_n, d.lat_limit_n, d.contact_thr
        f_max = self.f_max if math.isfinite(self.f_max) else 0.0
        f_min = self.f_min if math.isfinite(self.f_min) else 0.0
        if self.zeroed:
            self.hi, self.lo = max(lim, f_max) + thr, min(-lim, f_min - thr)
            self.lat_hi = max(lat_lim, self.lat_max) + thr
        else:
            self.hi, self.lo, self.lat_hi = f_max + lim, f_min - 2.0 * lim, self.lat_max + lat_lim
        return True

    def __call__(self, s):
        if self.hi is None:
            if self.watched:
                self._judge(s, math.inf, -self.d.lim.force_limit_n - self.d.contact_thr,
                            self.d.lat_limit_n + self.d.contact_thr)
            if not self._begin(s):
                return None
        self._judge(s, self.hi, self.lo, self.lat_hi)
        return None

    def _judge(self, s, hi: float, lo: float, lat_hi: float) -> None:
        f, lat = s["filt"], s["lat"]
        if lat > lat_hi:
            self.d.retract_blocked = "the retract met a force across the tissue normal"
            self.d._lateral(lat, lat_hi, f, "retract", self._lateral_bound(lat_hi), held=True)
        if f > hi or f < lo:
            self._fault(f, lat, hi, lo)

    def _lateral_bound(self, lat_hi: float) -> str:
        lim = self.d.lat_limit_n
        if not self.zeroed:
            return f"{lat_hi:.3f} N (where the retract began plus the lateral limit {lim:g} N; the sensor not zeroed yet)"
        return f"{lat_hi:.3f} N (the lateral limit {lim:g} N, or the force across where the retract began, plus a " \
               f"contact threshold)"

    def _fault(self, f: float, lat: float, hi: float, lo: float) -> None:
        d = self.d
        d.retract_blocked = "the retract met a force along the tissue normal"
        d._stop()
        if not self.zeroed:         # (a resumed run's first move: the sensor not zeroed, its offset unknown)
            up = f > hi
            why = (f"changed from {self.f_max if up else self.f_min:+.3f} N to {f:+.3f} N, "
                   f"{'above' if up else 'below'} {hi if up else lo:+.3f} N (the sensor not zeroed yet: only a change "
                   f"of more than the force limit up, or twice it down, counts): the tissue holds the tip, or lets "
                   f"it go after holding it, or something presses on the tool")
        elif f > hi:
            why = (f"rose to {f:+.3f} N, above {hi:.3f} N: the tissue rises with the tip (or the registered "
                   f"normal is wrong)")
        else:
            why = (f"pulls towards the tissue with {-f:.3f} N, beyond {-lo:.3f} N: the tissue holds the tip, or "
                   f"something above presses on the tool")
        raise ProbeFault(FaultKind.RETRACT_FORCE,
                         f"leaving the tissue, the force along its normal (filtered; {lat:.3f} N across it) {why}; "
                         f"the arm stopped where it was and is not moved again: free the tip (freedrive on the "
                         f"pendant, out of the tissue), then resume")

    def quiet(self, b: _Block, limit: int) -> int:
        if self.hi is None:
            return 0                # (where the retract began sets the bounds: read one period at a time)
        f = b.filt[:limit]
        return first_true((f > self.hi) | (f < self.lo) | (b.lat[:limit] > self.lat_hi), limit)


class _ForceWatch:
    """The descent's and the dwell's force monitor: notes the first contact (the filtered force above the contact
    threshold) and stops the arm when the force where it will have stopped (``force_when_stopped``) exceeds the
    limit."""

    def __init__(self, driver: "Driver", force_exponent: float | None = None):
        self.d = driver
        self.exponent = force_exponent  # the prior's force ~ depth^p (the plan's): the depth limit's lag
        self.fit: SurfaceFit | None = None      # the surface from the force since contact (robot.tissue_depth)
        self.lag_m: float | None = None         # its lag when the descent ended (held through the dwell)
        self.contact: dict = {}
        self.hist = deque(maxlen=driver.cfg.filter_window + 1)
        self.lead = stop_lead_periods(driver.cfg.filter_window)
        self.holding = False            # dwelling after a depth-limit stop: the depth held is the limit
        self.start_depth_m: float | None = None    # where the descent began (the approach pose)
        self.rest_depth: float | None = None    # (where the arm came to rest: its first dwell period)
        self.early: dict | None = None  # a reading past the threshold near the descent's start, being confirmed
        self.early_dismissed = 0        # such readings whose force fell back to free air within a window
        # the readings (depth, filtered force) before the contact since the force last rose past FIT_FROM_FRACTION of
        # the threshold: the surface's fit starts from them
        self.pre_depth: deque = deque(maxlen=FIT_FROM_MAX)
        self.pre_filt: deque = deque(maxlen=FIT_FROM_MAX)

    def _before_contact(self, depth, filt) -> None:
        """Readings before the contact (floats, or arrays in order): kept for the surface's fit from the last one at
        or below FIT_FROM_FRACTION of the threshold (or FIT_FROM_SIGMAS of the filtered noise, if more) on."""
        if self.exponent is None:
            return
        noise = self.d.noise_filt_n if math.isfinite(self.d.noise_filt_n) else 0.0
        low = max(FIT_FROM_FRACTION * self.d.contact_thr, FIT_FROM_SIGMAS * noise)
        if isinstance(depth, float):
            if filt <= low:
                self.pre_depth.clear()
                self.pre_filt.clear()
            else:
                self.pre_depth.append(depth)
                self.pre_filt.append(filt)
            return
        below = np.flatnonzero(filt <= low)
        if below.size:
            self.pre_depth.clear()
            self.pre_filt.clear()
            depth, filt = depth[below[-1] + 1:], filt[below[-1] + 1:]
        self.pre_depth.extend(depth.tolist())
        self.pre_filt.extend(filt.tolist())

    def _early(self, depth: float) -> None:
        """Contact felt within ``early_contact_m`` of the descent's start: the tissue's surface is at the approach
        pose (higher than registered by about the approach height), where the moves between probes pass and the
        sensor was zeroed -- possibly in the tissue, against a force no later reading sees. A fault."""
        d = self.d
        if depth - self.start_depth_m < d.early_contact_m:
            d._stop()
            h = d.plan.motion.approach_height_m
            raise ProbeFault(FaultKind.SURFACE_HIGH, f"contact felt {(depth - self.start_depth_m) * 1e3:.2f} mm into "
                             f"the descent from the approach pose, {h * 1e3:g} mm above the planned surface: the "
                             f"tissue's surface is about that much higher than registered, where the moves between "
                             f"probes pass (and the sensor may have been zeroed in the tissue); re-register the "
                             f"surface, or plan a larger approach height: palpate plan --approach-height-m")

    def _too_deep(self, depth, filt):
        """The depth limit (floats or arrays of periods: the depth below the nominal surface, the filtered force):
        while descending, the depth below the tissue's surface (robot.tissue_depth: the travel since contact was
        felt plus the lag the force curve gives) past the limit; while holding after a stop there, deeper than
        where the arm came to rest by HOLD_SLACK_M."""
        one = isinstance(depth, float)  # one period (a float, the loop's): SurfaceFit's path of floats
        if self.holding:
            return depth > self.rest_depth + HOLD_SLACK_M
        past = depth - self.contact["depth"]
        if self.lag_m is not None:      # dwelling: the descent's lag (a dwell's readings are not its curve)
            lag = self.lag_m
        else:
            if self.fit is None:
                self.fit = SurfaceFit(self.exponent, self.contact["depth"] - self.start_depth_m,
                                      self.d.cfg.filter_window)
                if self.pre_depth:      # the readings on the way up to the threshold first
                    self.fit.commit(np.array(self.pre_depth) - self.contact["depth"], np.array(self.pre_filt))
            lag = (self.fit.depth_one(past, filt) if one else self.fit.depth_m(past, filt)) - past
        limit = self.d.lim.depth_limit_m
        # counted from the fitted surface where it stands SURFACE_TOL_M above the registered one (else the plan's
        # depth, at most the limit, governs), and never more than the limit past the contact felt
        return (past > limit) | ((past + lag > limit) & (lag - self.contact["depth"] > SURFACE_TOL_M))

    def end_descent(self) -> None:
        """The descent is over: the lag its readings gave holds through the dwell (a relaxing tissue's force
        falls at constant depth: fitted as the curve, it would lengthen the lag and stop a probe already there)."""
        self.lag_m = self.fit.lag_m() if self.fit is not None else 0.0

    def _commit(self, depth, filt) -> None:
        """Readings past the contact that did not stop the arm: into the surface's fit (the descent's only)."""
        if self.fit is not None and not self.holding and self.lag_m is None:
            if isinstance(depth, float):
                self.fit.commit_one(depth - self.contact["depth"], filt)
            else:
                self.fit.commit(depth - self.contact["depth"], filt)

    def _pulled(self, f: float) -> None:
        """A filtered force below minus the free-air band (the contact threshold and the drift allowed since the zero)
        in a descent or dwell: tissue pushes back, it does not pull; the sensor drifts (a drift that would also hide
        the contact, and the depth limit counted from it), or its sign or zero is wrong. A fault."""
        d = self.d
        d._stop()
        raise ProbeFault(FaultKind.FREE_AIR_FORCE, f"the force reads {f:+.3f} N in a descent or dwell, below minus "
                         f"the contact threshold ({d.contact_thr:.3f} N) and {DRIFT_ALLOWANCE_N_PER_S:g} N/s of drift, "
                         f"{d.ts - d.zeroed_ts:.1f} s after the sensor was zeroed in free air: tissue pushes back, it "
                         f"does not pull; the sensor drifts (let it warm up, check its cable and mounting) or its "
                         f"force sign is wrong")

    def __call__(self, s):
        if self.start_depth_m is None:
            self.start_depth_m = s["depth"]
        if s["lat"] > self.d.lat_limit_n:
            self.d._lateral(s["lat"], self.d.lat_limit_n, s["filt"], "dwell" if self.lag_m is not None else "descent")
        f, lat = s["filt"], s["lat"]
        if f * f + lat * lat > self.d.askew_from2 and \
                lat - DRIFT_ALLOWANCE_N_PER_S * (s["t"] - self.d.zeroed_ts) > self.d.askew_tan * f:
            self.d._askew(lat, f)
        if s["filt"] < -self.d.free_air_band_n(s["t"] - self.d.zeroed_ts):
            self._pulled(s["filt"])
        if "depth" not in self.contact and s["filt"] > self.d.contact_thr:
            if not self.holding and (self.early is not None
                                     or s["depth"] - self.start_depth_m < self.d.early_contact_m):
                # contact this early is a fault once a filter window's readings have been past the threshold
                # before the force fell back to free air (below EARLY_DISMISS_FRACTION of the threshold): one
                # reading past it in free air is noise (a quick mismatch study's trial met 8.1 mN against 8 mN,
                # 8.5 mm above the surface, and ended with this fault); a real surface's force, hovering about the
                # threshold as it rises, does not fall that far back and is still the fault
                e = self.early = self.early or {"depth": s["depth"], "n": 0}
                e["n"] += 1
                if e["n"] >= self.d.cfg.filter_window:
                    self._early(e["depth"])
            else:
                self.contact.update(depth=s["depth"], x=s["x"], t=s["t"])
        elif ("depth" not in self.contact and self.early is not None
              and s["filt"] < EARLY_DISMISS_FRACTION * self.d.contact_thr):
            self.early = None           # back down to free air before a window's readings: noise, not the surface
            self.early_dismissed += 1
        if "depth" not in self.contact:
            self._before_contact(s["depth"], s["filt"])
        self.hist.append(s["filt"])
        if force_when_stopped(self.hist, self.lead) > self.d.lim.force_limit_n:
            if self.early is not None:  # the limit while an early contact is confirmed: that contact was real
                self._early(self.early["depth"])
            self.d._stop()
            return ProbeStatus.FORCE_LIMIT
        if self.holding and self.rest_depth is None:
            self.rest_depth = s["depth"]
        if "depth" in self.contact:
            if self._too_deep(s["depth"], s["filt"]):
                self.d._stop()          # the depth limit counts from the surface felt, not only the plan's
                return ProbeStatus.DEPTH_LIMIT
            self._commit(s["depth"], s["filt"])
        return None

    def quiet(self, b: _Block, limit: int) -> int:
        """The first ``limit`` periods of ``b`` up to the first that stops the arm, with their effects."""
        filt = b.filt[:limit]
        k = first_true(forces_when_stopped(self.hist, filt, self.lead) > self.d.lim.force_limit_n, limit)
        k = first_true(filt[:k] < -self.d.free_air_band_n(b.ts[:k] - self.d.zeroed_ts), k)   # (one at a time:
        k = first_true(b.lat[:k] > self.d.lat_limit_n, k)                                    # __call__ raises)
        lat, f = b.lat[:k], filt[:k]
        k = first_true((f * f + lat * lat > self.d.askew_from2)
                       & (lat - DRIFT_ALLOWANCE_N_PER_S * (b.ts[:k] - self.d.zeroed_ts) > self.d.askew_tan * f), k)
        if self.start_depth_m is None and b.n:
            self.start_depth_m = float(b.depth[0])
        if self.early is not None:      # an early contact being confirmed: one period at a time
            return 0
        j = 0
        if "depth" not in self.contact:
            j = first_true(filt[:k] > self.d.contact_thr, -1)
            before = j if j >= 0 else k           # the periods before any contact's
            self._before_contact(b.depth[:before], filt[:before])
            if j >= 0 and not self.holding and b.depth[j] - self.start_depth_m < self.d.early_contact_m:
                k = j                   # that period one at a time: __call__ raises the fault
                j = 0
            elif j >= 0:
                self.contact.update(depth=float(b.depth[j]), x=float(b.x[j]), t=float(b.ts[j]))
        if self.holding and self.rest_depth is None and b.n:
            self.rest_depth = float(b.depth[0])
        if "depth" in self.contact:     # and up to the first past the depth limit (below the fitted surface)
            k = j + first_true(self._too_deep(b.depth[j:k], filt[j:k]), k - j)
            self._commit(b.depth[j:k], filt[j:k])
        self.hist.extend(filt[:k].tolist())
        return k


class Driver(Recovery):
    def __init__(self, plan, rtde_c, rtde_r, config: DriverConfig | None = None, diagnose=None,
                 force_source: ForceSource | None = None):
        self.plan, self.cfg = plan, config or DriverConfig()
        self.diagnose = diagnose        # () -> an operator hint or None, asked after a fault (bounded in time)
        self.lim = SafetyLimits.from_plan(plan)
        self.tf = TissueFrame(plan.frames.tissue_pose_base)
        self.c, self.r = GuardedControl(rtde_c, self.lim), rtde_r
        # the wrench: the UR's wrist sensor (default) or an external one (robot.forcesource); the caller owns it
        self.fs = force_source if force_source is not None else RtdeForce(self.c, rtde_r)
        if isinstance(self.fs, RtdeForce) and self.fs.c is rtde_c:     # the caller's wrist sensor on this link: its
            self.fs = RtdeForce(self.c, self.fs.r)                      # zeroFtSensor through the guard too
        self.backstop = self.fs.name != "rtde" and self.cfg.wrist_backstop_margin_n > 0
        self.wrist_filt = deque(maxlen=self.cfg.filter_window)
        self.filt = deque(maxlen=self.cfg.filter_window)
        self.lat = deque(maxlen=self.cfg.filter_window)     # the force across the normal: (x, y, z) per period
        lat = self.cfg.lateral_force_limit_n
        if lat is not None and not (isinstance(lat, (int, float)) and float(lat) > 0):     # (NaN fails too)
            raise ValueError(f"DriverConfig.lateral_force_limit_n = {lat!r}: a positive number of newtons, inf (the "
                             f"watch off) or None (the plan's force limit)")
        self.lat_limit_n = self.lim.force_limit_n if lat is None else float(lat)
        self.noise_lat_n = float("nan")     # the filtered lateral force's free-air noise at the last zeroing (N, 1
        #                                     sigma per axis across the normal)
        self.last_ts, self.stale, self.ts = None, 0, 0.0
        self.samples = _Samples()
        self.phase = FREE
        self.contact_thr = plan.motion.contact_threshold_n
        self.early_contact_m = min(EARLY_CONTACT_M, 0.5 * plan.motion.approach_height_m)
        self.zeroed_ts: float | None = None      # when the sensor was last zeroed in this run (controller time)
        self.zeroed_rotvec: list | None = None   # and the tool's orientation then (a rotation vector, rad)
        self.noise_std = float("nan")
        self.noise_filt_n = float("nan")    # the filtered force's free-air noise at the last zeroing (N, 1 sigma)
        self.watchdog_on = False
        self.watchdog_hz = watchdog_rate_hz(self.cfg, self.lim.probe_speed_m_s)
        self.program_restarts = 0
        self.early_dismissed = 0        # early contacts dismissed as noise (RunReport.early_contacts_dismissed)
        self.link_dead: str = ""        # why the link is taken for silent (a command got no answer)
        self.worker = CallWorker()      # every waiting ur_rtde call, one at a time, each with a deadline
        self.last_kick_ts = None        # controller time of the last accepted watchdog kick
        self.program_ended_ts = None    # controller time by which the driver found its control program ended (None:
                                        # running as far as it knows); whose stop it was is judged at this time
        self.normal = tuple(float(v) for v in self.tf.normal)
        # a simulator's look-ahead (robot.sim): quiet periods many at once; with the wrist sensor only (an external
        # sensor's readings come from elsewhere)
        look = getattr(rtde_r, "look_ahead", None)
        own = look is not None and getattr(look, "__self__", None) is rtde_r     # its own, not one it forwards
        self.look = (lambda n, kicks: look(n, kicks, rtde_c)) \
            if own and self.cfg.fast_forward and self.fs.name == "rtde" and not self.backstop else None
        self.n_fast = 0                 # periods stepped through the look-ahead
        self.retract_blocked: str = ""  # why the safe state must not retract (a retract met a force: _RetractWatch)
        self.last_blocked = False       # the last run in the output directory ended so (run.json): run() reads it

    # ---- primitives --------------------------------------------------------------------------------------
    def _call(self, fn, *args):
        """One ur_rtde call. Those that wait for the controller are bounded in time (robot.link.call_within): one
        unanswered means a silent link, and nothing more is sent on it (a second would queue behind the first)."""
        name = getattr(fn, "__name__", None) or str(fn)
        if name in _PLAIN_CALLS:        # a getter, initPeriod/waitPeriod, kickWatchdog: local or never waiting
            try:
                return fn(*args)
            except RuntimeError as e:
                raise ProbeFault(FaultKind.CONNECTION_LOST, f"{name}: {e}") from None
        deadline = deadline_for(name)
        if deadline is not None and self.link_dead:
            raise ProbeFault(FaultKind.CONNECTION_LOST, f"{name} not sent: {self.link_dead}")
        if name in NEEDS_PROGRAM and self.c.isProgramRunning() is False:
            # ur_rtde would wait its ready time-out (seconds) and return False: say why now instead
            self._require(False, f"{name} (not sent: the control program is not running)", program=True)
        try:
            return fn(*args) if deadline is None else self.worker.call(fn, args, deadline)
        except CallTimeout as e:
            self.link_dead = f"{e} (a silent link: a network partition or a frozen controller)"
            raise ProbeFault(FaultKind.CONNECTION_LOST, self.link_dead) from None
        except RuntimeError as e:
            raise ProbeFault(FaultKind.CONNECTION_LOST, f"{name}: {e}") from None

    def _require(self, ok, what: str, program: bool = False, sent_ts: float | None = None) -> None:
        """A command's bool must be True. If not, say why: a protective stop (the receive data may lag the control
        interface's by a period or two, so it is watched for a few periods), a link down or silent (ur_rtde's
        control interface may notice a silent link first, and refuse), for a command that needs the control program
        (``program``) an operator's stop of it (not its watchdog's), or else the command failed. ``sent_ts``: the
        controller time of the last reading before the refused call, if it was made directly (a kick)."""
        if ok is True:
            return
        ts0 = self._call(self.r.getTimestamp)
        if program and self._call(self.c.isProgramRunning) is False:
            # ended by the refusal: whose stop it was is judged at that time, not after the wait below. A call
            # refused only after ur_rtde's ready time-out (UR_READY_TIMEOUT_S) waited for a script that never got
            # ready again: the program ended within a cycle of the call (at ``sent_ts``), not seconds later
            spun = isinstance(sent_ts, (int, float)) and isinstance(ts0, (int, float)) and \
                ts0 - sent_ts >= UR_READY_TIMEOUT_S
            self._note_program_ended(sent_ts if spun else ts0)
        for k in range(self.cfg.stale_periods):
            if self._call(self.r.isProtectiveStopped) is True:
                raise ProbeFault(FaultKind.PROTECTIVE_STOP, f"{what} refused: the controller is protective-stopped")
            if not (self._connected(self.c) and self._connected(self.r)):
                raise ProbeFault(FaultKind.CONNECTION_LOST, f"{what} returned {ok!r}: ur_rtde reports no connection")
            if k >= 10 and self._call(self.r.getTimestamp) != ts0:
                if program and self._call(self.c.isProgramRunning) is False:
                    self._note_program_ended(self._call(self.r.getTimestamp))    # (if it ended while waiting here)
                    if not self._watchdog_may_have_fired():
                        raise ProbeFault(FaultKind.PROGRAM_STOPPED, PROGRAM_STOPPED_BY_OPERATOR)
                raise ProbeFault(FaultKind.COMMAND_FAILED, f"{what} returned {ok!r}")
            self._call(self.c.waitPeriod, self._call(self.c.initPeriod))
        self.stale = self.cfg.stale_periods          # safe_state: a silent link, send nothing
        raise ProbeFault(FaultKind.CONNECTION_LOST, f"{what} returned {ok!r}, and controller data stopped updating "
                                                    f"(a silent link: a network partition or a frozen controller)")

    def _read(self, strict=True):
        r = self.r
        if self._call(r.isConnected) is not True:    # ur_rtde reconnecting by itself: its getters are not safe now
            raise ProbeFault(FaultKind.CONNECTION_LOST, "the receive interface reports no connection (the link "
                                                        "dropped; ur_rtde may be reconnecting by itself)")
        ts, pose, ps = self._call(r.getTimestamp), self._call(r.getActualTCPPose), self._call(r.isProtectiveStopped)
        if ps is True:
            raise ProbeFault(FaultKind.PROTECTIVE_STOP, "the controller reports a protective stop")
        if not _vec6(pose):
            raise ProbeFault(FaultKind.INVALID_READING, f"getActualTCPPose returned {pose!r}")
        if not isinstance(ts, (int, float)) or not math.isfinite(ts):
            raise ProbeFault(FaultKind.INVALID_READING, f"getTimestamp returned {ts!r}")
        try:
            w = self.fs.wrench(self._call, pose)
        except SensorFault as e:          # strict: a fault; else (stopping, retracting out of tissue) no force
            if strict:
                raise ProbeFault(e.kind, e.message) from None
            w = None
        if strict and self.backstop:
            self._check_wrist(w)
        ok_w = _vec6(w)
        if strict and not ok_w:
            what = "getActualTCPForce" if self.fs.name == "rtde" else f"the {self.fs.name} force source"
            raise ProbeFault(FaultKind.INVALID_READING, f"{what} returned {w!r}")
        self.stale = self.stale + 1 if (self.last_ts is not None and ts <= self.last_ts) else 0
        if self.stale >= self.cfg.stale_periods:   # ur_rtde keeps returning the last values when the link drops
            lost = self._call(self.r.isConnected) is False
            raise ProbeFault(FaultKind.CONNECTION_LOST,
                             f"controller data stopped updating at t={ts:.3f} s"
                             + (" (the receive interface reports no connection)" if lost else
                                " while the receive interface still reports a connection (a silent link: a network "
                                "partition or a frozen controller)"))
        self.last_ts = self.ts = float(ts)
        x, y, depth = self.tf.xy_depth(pose)
        f = self._along_normal(w) if ok_w else float("nan")
        if ok_w:
            self.filt.append(f)
            self.lat.append(self._across_normal(w))
        filt = reduce(add, self.filt) / len(self.filt) if self.filt else float("nan")
        lat = float("nan")
        if self.lat:
            lx, ly, lz = self.lat[0]
            for a, b, c in list(self.lat)[1:]:
                lx, ly, lz = lx + a, ly + b, lz + c
            n = len(self.lat)
            lx, ly, lz = lx / n, ly / n, lz / n
            lat = math.sqrt(lx * lx + ly * ly + lz * lz)
        self.samples.add(ts, list(pose), list(w) if ok_w else [math.nan] * 6, f, depth, x, self.phase, y)
        return {"t": ts, "pose": pose, "f": f, "filt": filt, "lat": lat, "depth": depth, "x": x}

    def _along_normal(self, w) -> float:
        """The contact force: the wrench's force along the tissue normal (written out as ``_fast_forward`` does it
        on many periods at once: the same values)."""
        n0, n1, n2 = self.normal
        return self.cfg.force_sign * (float(w[0]) * n0 + float(w[1]) * n1 + float(w[2]) * n2)

    def _across_normal(self, w) -> tuple:
        """The wrench's force across the tissue normal (the force less its part along it; ``across_normal`` on
        many periods at once: the same values)."""
        n0, n1, n2 = self.normal
        w0, w1, w2 = float(w[0]), float(w[1]), float(w[2])
        d = w0 * n0 + w1 * n1 + w2 * n2
        return w0 - d * n0, w1 - d * n1, w2 - d * n2

    @property
    def askew_from2(self) -> float:
        """The squared length of the filtered force from which its direction is judged: FORCE_ANGLE_FROM contact
        thresholds, or ASKEW_NOISE_SIGMAS of the noise across the normal at the last zero if more."""
        noise = self.noise_lat_n if math.isfinite(self.noise_lat_n) else 0.0
        v = max(FORCE_ANGLE_FROM * self.contact_thr, ASKEW_NOISE_SIGMAS * noise)
        return v * v

    askew_tan = math.tan(FORCE_ANGLE_MAX_RAD)

    def _askew(self, lat: float, filt: float) -> None:
        """The force on the tip points more than FORCE_ANGLE_MAX_RAD from the tissue normal: a fault (stopped first)."""
        self._stop()
        turned = "" if self.fs.name == "rtde" else (
            f"the {self.fs.name} sensor's stated orientation (--ft-sensor-pose) is turned from its mounting (the "
            f"force along the normal then reads short, and the force limit with it), ")
        raise ProbeFault(FaultKind.FORCE_DIRECTION,
                         f"the force on the tip points {math.degrees(math.atan2(lat, filt)):.0f} degrees from the "
                         f"tissue normal the tool is held along ({lat:.3f} N across it, {filt:+.3f} N along it, "
                         f"filtered), more than {math.degrees(FORCE_ANGLE_MAX_RAD):g}: {turned}the tissue's surface "
                         f"is far steeper than registered (plan.frames.tissue_pose_base), something pushes the tip "
                         f"sideways, or the sensor drifts across the normal (more than {DRIFT_ALLOWANCE_N_PER_S:g} N/s "
                         f"since its zero)")

    def _lateral(self, lat: float, limit: float, filt: float, where: str, bound: str | None = None,
                 held: bool = False) -> None:
        """The filtered force across the tissue normal above its limit (``bound``: what the limit is, said): a fault
        (the arm stopped first; ``held``: and not retracted)."""
        self._stop()
        raise ProbeFault(FaultKind.LATERAL_FORCE,
                         f"{lat:.3f} N across the tissue normal in the {where} (filtered; {filt:+.3f} N along it), "
                         f"above {bound or f'the lateral limit {limit:.3f} N'}: the tip is caught or pushed from the "
                         f"side" + ("; the arm stopped where it was and is not moved again: free the tip (freedrive "
                                    "on the pendant), then resume" if held else ""))

    def _check_wrist(self, w) -> None:
        """The backstop behind an external sensor: the wrist sensor's filtered force along the normal."""
        wr = self._call(self.r.getActualTCPForce)
        if not _vec6(wr):
            return                  # the wrist's reading is not the one the probe relies on
        self.wrist_filt.append(self._along_normal(wr))
        fw = reduce(add, self.wrist_filt) / len(self.wrist_filt)
        backstop = self.lim.force_limit_n + self.cfg.wrist_backstop_margin_n
        if fw > backstop:
            fe = self._along_normal(w) if _vec6(w) else float("nan")
            raise ProbeFault(FaultKind.SENSOR_DISAGREES,
                             f"the wrist sensor reads {fw:.2f} N along the normal, above the backstop {backstop:g} N "
                             f"(the force limit + {self.cfg.wrist_backstop_margin_n:g} N), while the {self.fs.name} "
                             f"sensor reads {fe:.3f} N: the "
                             f"external sensor is stuck, misread or wrongly mounted")

    def _loop(self, max_s: float, body, strict=True, what="wait", quiet=None):
        """Call ``body(sample)`` once per controller period until it returns a value; time out after max_s.
        ``quiet(block)``: how many leading periods of a block of periods read at once ``body`` would have returned
        None for (and their effects applied: see ``_fast_forward``); None: one period at a time only."""
        n_max = max(1, int(math.ceil(max_s / self.cfg.period_s)))
        i = 0
        while i < n_max:
            if quiet is not None and self.look is not None:
                k, more = self._fast_forward(quiet, n_max - i)
                i += k
                if more:                # the look-ahead ran out before a period that is not quiet: look again
                    continue
                if i >= n_max:
                    break
            t0 = self._call(self.c.initPeriod)
            self._kick()
            res = body(self._read(strict))
            self._call(self.c.waitPeriod, t0)
            i += 1
            if res is not None:
                return res
        raise ProbeFault(FaultKind.TIMEOUT, f"{what} did not finish within {max_s:.1f} s")

    def _fast_forward(self, quiet, limit: int) -> tuple[int, bool]:
        """Step the periods in which nothing happens but recording, many at once, on a simulator that computes them
        ahead (robot.sim.ArmModel.look_ahead): the readings of up to FF_PERIODS periods are read as ``_read`` would
        read them one by one; ``quiet`` counts the leading periods whose ``body`` would return None (it looks at
        no period after one that would not); those are taken -- the simulator advances by them, the driver
        records them and updates its filter, timestamps and watchdog kicks exactly as period by period -- and
        the first period that is not quiet runs in ``_loop`` one at a time. Returns how many were taken (0: the
        simulator cannot look ahead now, a reading would be a fault, or the first period is not quiet) and whether
        all the periods looked at were quiet (look again). Only readings the driver would have had by then decide
        anything; the rest of the look-ahead is dropped."""
        if self.stale or self.link_dead or limit < 1:
            return 0, False
        # the periods' watchdog kicks: as _kick sends them (the link is up on a simulator that looks ahead)
        kicks = self.watchdog_on and self.stale < self.cfg.stale_periods // 4
        la = self.look(min(limit, FF_PERIODS), kicks)
        if la is None:
            return 0, False
        ts, pose, w = la.seen
        if ((self.last_ts is not None and not ts[0] > self.last_ts) or not np.all(np.diff(ts) > 0)
                or not (np.isfinite(pose).all() and np.isfinite(w).all() and np.isfinite(ts).all())):
            return 0, False             # a stale or invalid reading: one period at a time says what it is
        n0, n1, n2 = self.normal
        f = self.cfg.force_sign * (w[:, 0] * n0 + w[:, 1] * n1 + w[:, 2] * n2)
        lat = across_normal(w, self.normal)
        x, y, depth = self.tf.xy_depth_many(pose)
        b = _Block(ts, pose, w, f, window_means(self.filt, f, self.cfg.filter_window),
                   lateral_magnitudes(window_means(self.lat, lat, self.cfg.filter_window)), depth, x, y, la.prog)
        k = quiet(b)
        if k < 1:
            return 0, False
        la.commit(k)
        if kicks:                       # each period's kick went out before its read: the last one after ts[k - 2]
            self.last_kick_ts = self.ts if k == 1 else float(ts[k - 2])
        self.filt.extend(f[:k].tolist())
        self.lat.extend(map(tuple, lat[max(0, k - self.cfg.filter_window):k].tolist()))
        self.last_ts = self.ts = float(ts[k - 1])
        self.stale = 0
        self.samples.add_block(b, k, self.phase)
        self.n_fast += k
        return k, k == la.n

    def _wait(self, seconds: float, collect=None):
        n = [0]

        def body(s):
            if collect is not None:
                collect.append((s["f"], s["filt"], s["lat"]))
            n[0] += 1
            return True if n[0] * self.cfg.period_s >= seconds else None

        def quiet(b: _Block) -> int:
            k = first_true(((n[0] + np.arange(1, b.n + 1)) * self.cfg.period_s) >= seconds, b.n)
            if collect is not None:
                collect.extend(zip(b.f[:k].tolist(), b.filt[:k].tolist(), b.lat[:k].tolist()))
            n[0] += k
            return k
        self._loop(seconds + 1.0, body, quiet=quiet)

    def _link_up(self, what: str) -> None:
        """No command while ur_rtde reports the link down (one sent then can block for good)."""
        if not self._connected(self.c):
            raise ProbeFault(FaultKind.CONNECTION_LOST, f"{what}: the control interface reports no connection")

    def _ensure_program(self) -> None:
        """At rest, before any motion of set-up, a probe or a retract: the control program runs, with the plan's TCP,
        payload and watchdog -- set every time, because a program ur_rtde restarted on its own (its background
        reconnect) or our own re-upload starts with the installation's TCP and no watchdog. The watchdog may have
        ended the program while the arm stood still (the host busy writing a record, planning the next round):
        then it is uploaded again (reuploadScript, counted in run.json). A stop during a motion is a fault instead
        (a kick fails)."""
        c, cfg = self.c, self.cfg
        self._link_up("before configuring the control program")
        if self._call(self.r.isProtectiveStopped) is True:
            raise ProbeFault(FaultKind.PROTECTIVE_STOP, "the arm is protective-stopped: clear it on the pendant first")
        self.watchdog_on = False
        if self._call(c.isProgramRunning) is not True:
            # found ended now, unless a refused call found it before (safe_state after such a fault)
            self._note_program_ended(self._call(self.r.getTimestamp))
            if not self._watchdog_may_have_fired():
                raise ProbeFault(FaultKind.PROGRAM_STOPPED, PROGRAM_STOPPED_BY_OPERATOR)
            self._require(self._call(c.reuploadScript), "reuploadScript")
            self._loop(5.0, lambda s: True if self._call(c.isProgramRunning) is True else None, strict=False,
                       what="restart of the control script")
            self.program_restarts += 1
        self.program_ended_ts = None
        self._require(self._call(c.setTcp, list(self.plan.frames.tcp_offset)), "setTcp", program=True)
        self._require(self._call(c.setPayload, cfg.payload_kg, list(cfg.payload_cog_m)), "setPayload", program=True)
        if self.watchdog_hz > 0:
            self._require(self._call(c.setWatchdog, self.watchdog_hz), "setWatchdog", program=True)
            self.watchdog_on = True

    def _kick(self) -> None:
        """Feed the watchdog. Not while the link is down -- that is the point: the controller then stops the
        motion within 1/watchdog_hz, whatever the driver can or cannot send."""
        # only while the data are fresh (a kick on a dead link waits for ur_rtde's ready time-out, seconds); the
        # margin of 25 periods keeps a host or simulator held up for a moment from skipping kicks
        if self.watchdog_on and self._connected(self.c) and self.stale < self.cfg.stale_periods // 4:
            ok = self._call(self.c.kickWatchdog)
            if ok is True:
                self.last_kick_ts = self.ts
                return
            self._require(ok, "kickWatchdog (the control program has stopped)", program=True, sent_ts=self.ts)

    def _note_program_ended(self, seen_ts) -> None:
        """The control program was found ended by controller time ``seen_ts`` (the first finding counts)."""
        if self.program_ended_ts is None:
            self.program_ended_ts = seen_ts

    def _watchdog_may_have_fired(self) -> bool:
        """Could the program have been ended by its RTDE watchdog (no accepted kick for 1/rate of controller
        time), rather than by an operator (the pendant's or the dashboard's stop, local control)? Only then may the
        driver upload it again. Judged at the time the driver found it ended (``_note_program_ended``), not now:
        a fault's report, a refused kick's wait in ur_rtde or the safe state come later, and by then any stop
        would look like the watchdog's."""
        if self.last_kick_ts is None or self.watchdog_hz <= 0:
            return True
        seen = self.program_ended_ts
        return not isinstance(seen, (int, float)) or seen - self.last_kick_ts >= 1.0 / self.watchdog_hz - 0.01

    def _stop(self) -> None:
        self._call(self.c.stopL, self.cfg.stop_decel_m_s2)

    def _halt_first(self) -> list[str]:
        """One stopL at a fault raised during a probe, before its record, samples and run.json are written (with
        fsync: 15-17 ms in memory, 68 ms through the real client, in which a descending tip went 0.03-0.14 mm on
        with no force read; a session-59 review) and before the rest of the safe state (safe_state stops again, then
        retracts). Nothing is sent over a silent or dead link, nor in a protective stop (the controller holds the arm
        and refuses commands): safe_state says so. Returns notes (a failed stop: the safe state tries again)."""
        if self.link_dead or self.stale >= self.cfg.stale_periods or not self._connected(self.c):
            return []
        try:
            if self._call(self.r.isProtectiveStopped) is True:
                return []
            self._stop()
        except Exception as w:              # noqa: BLE001 -- noted; safe_state() stops (or says why not)
            return [f"the first stopL at the fault failed ({type(w).__name__}: {w}); the safe state stopped again"]
        return []

    def _move(self, pose, speed, accel, watch=None, strict=True, what="move"):
        """Asynchronous moveL to ``pose``, polled each period; ``watch(sample)`` may stop it early (its result)."""
        start = self._read(strict)["pose"]
        dist = math.dist(start[:3], pose[:3])
        self._link_up(f"moveL ({what})")
        before = self._call(self.c.getAsyncOperationProgress)
        self._require(self._call(self.c.moveL, list(pose), speed, accel, True), f"moveL ({what})", program=True)
        timeout = self.cfg.timeout_factor * _move_time(dist, speed, accel) + self.cfg.timeout_margin_s
        state = {"started": False, "idle": 0}

        def body(s):
            if watch is not None:
                res = watch(s)
                if res is not None:
                    return res
            prog = self._call(self.c.getAsyncOperationProgress)
            if prog is None:
                raise ProbeFault(FaultKind.INVALID_READING, "getAsyncOperationProgress returned None")
            # < 0: no operation running; a negative value other than the one before the command marks the end
            # of this one (ur_rtde toggles -1/-2), so even a move too short to be seen running is detected
            state["started"] |= prog >= 0 or prog != before
            if prog < 0:
                if math.dist(s["pose"][:3], pose[:3]) < 2e-4:
                    return "reached"
                state["idle"] += 1
                if state["idle"] > 25 and (state["started"] or state["idle"] > 100):
                    short_mm = math.dist(s['pose'][:3], pose[:3]) * 1e3
                    raise ProbeFault(FaultKind.MOVE_FAILED, f"{what} ended {short_mm:.2f} mm short of its target")
            return None

        def quiet(b: _Block) -> int:
            """The periods while the move runs (progress >= 0) and ``watch`` has nothing to say."""
            k = first_true(np.asarray(b.prog) < 0, b.n)
            if watch is not None and k:
                k = watch.quiet(b, k)
            state["started"] |= k > 0
            return k
        quiet_ok = watch is None or hasattr(watch, "quiet")
        # a fault is recorded first, then safe_state() stops
        return self._loop(timeout, body, strict, what, quiet if quiet_ok else None)

    # ---- one probe ---------------------------------------------------------------------------------------
    def _zero(self, probe=None, rotvec=None) -> None:
        """Zero the sensor at rest in free air (at ``probe``'s approach pose, first checked against the last zero;
        or where the set-up left the tool, turned as ``rotvec``) and measure the free-air noise."""
        self.phase = FREE
        before: list = []
        self._wait(self.cfg.settle_s, before)
        if probe is not None:
            self._check_free_air(before, probe)
            rotvec = probe.approach_pose[3:]
        self._link_up("zeroFtSensor")
        rtde = self.fs.name == "rtde"           # zeroFtSensor: a command of the control program
        self._require(self._sensor(self.fs.zero, self._call),
                      "zeroFtSensor" if rtde else f"zeroing the {self.fs.name} sensor", program=rtde)
        if self.backstop:           # the wrist sensor too: it is the backstop
            self._require(self._call(self.c.zeroFtSensor), "zeroFtSensor (the wrist sensor: the backstop)",
                          program=True)
            self.wrist_filt.clear()
        self.filt.clear()
        self.lat.clear()
        self._wait(self.cfg.settle_s)
        self.filt.clear()
        self.lat.clear()
        vals: list = []
        self._wait(self.cfg.noise_sample_s, vals)
        vals = np.array(vals[self.cfg.filter_window:]).reshape(-1, 3)
        self.noise_std = float(np.std(vals[:, 0])) if len(vals) > 1 else 0.0
        noise_f = self.noise_filt_n = float(np.std(vals[:, 1])) if len(vals) > 1 else 0.0
        # per axis across the normal: a 2D Gaussian's mean squared length is 2 sigma^2
        noise_lat = self.noise_lat_n = float(np.sqrt(np.mean(vals[:, 2] ** 2) / 2)) if len(vals) > 1 else 0.0
        noise_thr = self.cfg.noise_sigma_factor * noise_f
        if noise_thr >= 0.5 * self.lim.force_limit_n:
            raise ProbeFault(FaultKind.SENSOR_NOISE, f"free-air force noise {noise_f:.3f} N (filtered) is too large "
                                             f"for the force limit {self.lim.force_limit_n} N: the limit cannot be "
                                             f"enforced with this sensor")
        if LATERAL_NOISE_SIGMAS * noise_lat >= self.lat_limit_n:
            raise ProbeFault(FaultKind.SENSOR_NOISE, f"the force across the normal after zeroing in free air, "
                                             f"{noise_lat:.4g} N RMS per axis (filtered: noise, or a steady load), "
                                             f"is too large for the lateral limit {self.lat_limit_n:g} N: "
                                             f"{LATERAL_NOISE_SIGMAS:g} times it, {LATERAL_NOISE_SIGMAS * noise_lat:.4g}"
                                             f" N, must fit below the limit, or the lateral watch would stop the arm "
                                             f"on noise")
        self.contact_thr = max(self.plan.motion.contact_threshold_n, noise_thr)
        self.zeroed_ts = self.ts
        self.zeroed_rotvec = None if rotvec is None else list(rotvec)

    def _check_feelable(self, p) -> None:
        """Before a descent: the depth limit counts from the surface the force curve gives once contact is felt, so
        a probe must feel contact before the limit even where the surface is higher than registered. Nothing checked
        before the descent rules out a surface up to the approach height above the registered one; with it that high
        the tip would reach the limit's indentation, where the prior predicts the probe's predicted force continued
        as depth^p (p its plan's exponent, or 1, the flattest a plan may give: the least force). Where that is not
        FEEL_MARGIN x the contact threshold (the plan's, or 5 sigmas of this sensor's filtered noise at the zeroing
        if more) and the probe's depth plus the approach height passes the limit, a fault before the tip enters the
        tissue (a safety review: 6 mm into tissue 2 mm high against a 4 mm limit, a plan's threshold raised to
        0.2 N, or the UR wrist sensor's noise raising it to 4.2 N)."""
        thr, plan_thr, mo = self.contact_thr, self.plan.motion.contact_threshold_n, self.plan.motion
        f_limit = unfelt_force_n(p, mo, self.lim.depth_limit_m, thr)
        if f_limit is None:
            return
        why = (f"5 sigmas of the {self.fs.name} sensor's filtered free-air noise ({self.noise_filt_n:.4f} N), above "
               f"the plan's {plan_thr:g} N: use a less noisy sensor, e.g. an external F/T sensor (--ft)"
               if thr > plan_thr else "motion.contact_threshold_n: lower it to what the sensor's noise allows")
        raise ProbeFault(FaultKind.CONTACT_UNFELT,
                         f"probe {p.index} might feel no contact before the depth limit: the prior's force there "
                         f"({f_limit:.4f} N, from its predicted {p.predicted_force_n:.4f} N at {p.depth_m * 1e3:.2f} "
                         f"mm) is not {FEEL_MARGIN:g} x the contact threshold ({thr:.4f} N, {why}), and the limit "
                         f"counts from the surface felt, so a surface up to the approach height "
                         f"({mo.approach_height_m * 1e3:g} mm) higher than registered could take the tip past it; or "
                         f"plan a smaller approach height (palpate plan --approach-height-m)")

    def _check_free_air(self, vals: list, probe) -> None:
        """At a probe's approach pose, before zeroing there: the force against the previous zero (the set-up's or
        the last probe's, in this run) must be below the contact threshold -- else the tip touches something (the
        tissue's surface higher than registered, the probe about to be zeroed in it: its descent would then count
        its depth limit from a force no reading sees) or the sensor drifts; either way no probe can be trusted. The
        force across the normal too (session 55's review: a sideways load there, zeroed, is hidden from the lateral
        watch)."""
        if self.zeroed_ts is None or not vals or self.zeroed_rotvec is None:
            return
        turn = self._turn_since_zero(probe.approach_pose)
        f = float(np.mean([v[0] for v in vals[len(vals) // 2:]]))
        lat = float(np.mean([v[2] for v in vals[len(vals) // 2:]]))   # (the filtered lateral force's length)
        dt = self.ts - self.zeroed_ts
        if abs(f) > self.free_air_band_n(dt, turn):
            h = self.plan.motion.approach_height_m
            raise ProbeFault(FaultKind.FREE_AIR_FORCE, f"{f:+.3f} N at probe {probe.index}'s approach pose, {dt:.1f} s "
                             f"after the sensor was zeroed in free air (more than the contact threshold "
                             f"{self.contact_thr:.3f} N, {DRIFT_ALLOWANCE_N_PER_S:g} N/s of drift and the tool's weight "
                             f"turned {math.degrees(turn):.2f} degrees since): the tip touches "
                             f"something there (the tissue's surface higher than registered by about the approach "
                             f"height, {h * 1e3:g} mm: re-register it, or plan a larger approach height: palpate plan "
                             f"--approach-height-m) or the sensor drifts ({f / max(dt, 1e-9):+.4f} N/s: let it warm "
                             f"up, check its cable and mounting)")
        noise_lat = self.noise_lat_n if math.isfinite(self.noise_lat_n) else 0.0
        if lat > self.free_air_band_n(dt, turn) + FREE_AIR_LATERAL_SIGMAS * noise_lat:
            raise ProbeFault(FaultKind.FREE_AIR_FORCE, f"{lat:.3f} N across the tissue normal at probe {probe.index}'s "
                             f"approach pose, {dt:.1f} s after the sensor was zeroed in free air (more than the "
                             f"contact threshold {self.contact_thr:.3f} N, {DRIFT_ALLOWANCE_N_PER_S:g} N/s of drift, "
                             f"the tool's weight turned {math.degrees(turn):.2f} degrees since and "
                             f"{FREE_AIR_LATERAL_SIGMAS:g} sigmas of the noise across the normal): something "
                             f"pushes the tip from the side there (zeroed, that load would be hidden from the lateral "
                             f"watch), or the sensor drifts; check the tool and the cell")

    def _turn_since_zero(self, pose) -> float:
        """The angle (rad) between the tool's orientation at the last zero and ``pose``'s."""
        return ur5e.rotation_angle(ur5e.rotvec_to_matrix(self.zeroed_rotvec), ur5e.rotvec_to_matrix(pose[3:]))

    def free_air_band_n(self, dt_s, turn_rad: float = 0.0):
        """The largest force magnitude a reading ``dt_s`` after a free-air zero may show with nothing touching: the
        contact threshold, plus DRIFT_ALLOWANCE_N_PER_S of drift since (a float, or an array of times), plus the
        tool's weight times the angle ``turn_rad`` it turned since (GRAVITY_M_S2)."""
        return self.contact_thr + DRIFT_ALLOWANCE_N_PER_S * dt_s + self.cfg.payload_kg * GRAVITY_M_S2 * turn_rad

    @staticmethod
    def _sensor(fn, *args):
        """A force-source call whose SensorFault is a probe fault."""
        try:
            return fn(*args)
        except SensorFault as e:
            raise ProbeFault(e.kind, e.message) from None

    def _probe(self, p):
        mo, lim = self.plan.motion, self.lim
        self.samples, self.phase = _Samples(), FREE
        t0 = self.ts
        turn = 0.0 if self.zeroed_rotvec is None else self._turn_since_zero(p.approach_pose)
        self._move(p.approach_pose, mo.approach_speed_m_s, min(mo.approach_accel_m_s2, lim.accel_m_s2),
                   _Collision(self, turn), what=f"approach to probe {p.index}")
        self._zero(p)
        self._check_feelable(p)
        watch = _ForceWatch(self, UNKNOWN_FORCE_EXPONENT if p.force_exponent is None else p.force_exponent)
        self.phase = DESCENT
        try:
            outcome = self._move(p.indent_pose, min(mo.probe_speed_m_s, lim.probe_speed_m_s),
                                 min(mo.probe_accel_m_s2, lim.accel_m_s2), watch, what=f"descent of probe {p.index}")
        finally:
            self.early_dismissed += watch.early_dismissed
        limited = outcome == ProbeStatus.DEPTH_LIMIT
        if (outcome == "reached" or limited) and mo.dwell_s > 0:
            # stopped at the depth limit (the surface higher than registered): the arm holds there for the dwell
            watch.holding = limited
            watch.end_descent()
            self.phase = DWELL
            n = [0]

            def dwell(s):
                n[0] += 1
                r = watch(s)
                return r if r is not None else ("reached" if n[0] * self.cfg.period_s >= mo.dwell_s else None)

            def quiet(b: _Block) -> int:
                k = watch.quiet(b, first_true(((n[0] + np.arange(1, b.n + 1)) * self.cfg.period_s) >= mo.dwell_s, b.n))
                n[0] += k
                return k
            outcome = self._loop(mo.dwell_s + 1.0, dwell, what="dwell", quiet=quiet)
        self.phase = RETRACT
        self._move(p.approach_pose, min(self.cfg.retract_speed_m_s, lim.tool_speed_m_s),
                   min(mo.probe_accel_m_s2, lim.accel_m_s2), self._retract_watch(watched=True),
                   what=f"retract of probe {p.index}")
        if limited and outcome == "reached":
            outcome = ProbeStatus.DEPTH_LIMIT       # (its dwell done at the limit, not at the planned depth)
        status = ProbeStatus.OK if outcome == "reached" else ProbeStatus(outcome)
        raw = self.samples.arrays()
        return summarise(p, raw, status, watch.contact, t0, self.ts, self.contact_thr, self.noise_std,
                         lim.depth_limit_m), raw

    def _retract_watch(self, watched: bool = False) -> _RetractWatch:
        """The watch on a move out of the tissue: a probe's retract (``watched``: after its watched descent and
        dwell), the safe state's, a resumed run's first."""
        return _RetractWatch(self, zeroed=self.zeroed_ts is not None, watched=watched)

    def _halt(self, kind):
        self._stop()
        raise ProbeFault(kind, f"force above the limit {self.lim.force_limit_n} N outside the descent")

    # ---- the run -----------------------------------------------------------------------------------------
    def run(self, out_dir, resume=True, progress=None) -> RunReport:
        wall0 = time.monotonic()
        plan, cfg = self.plan, self.cfg
        done = done_indices(out_dir) if resume else set()
        self.last_blocked = resume and last_retract_blocked(out_dir)
        pre = preflight(plan, done)
        problems, bad = check_plan(plan)
        rep = RunReport(RunStatus.OK, str(out_dir), n_planned=len(plan.probes), problems=problems,
                        n_skipped=sum(1 for p in plan.probes if p.index in done))
        log = RunLog(out_dir)
        # No garbage-collector pauses in the control loop (a full collection of a big heap can take longer than
        # the watchdog allows); reference counting frees what a run makes.
        gc_was_enabled = gc.isenabled()
        gc.disable()

        def write_run():
            rep.controller_time_s, rep.wall_s = self.ts, round(time.monotonic() - wall0, 3)
            rep.program_restarts = self.program_restarts
            rep.early_contacts_dismissed = self.early_dismissed
            log.write_run({**rep.to_dict(), "preflight": pre, "force_stop_threshold_n": self.lim.force_limit_n,
                           "lateral_force_limit_n": self.lat_limit_n if math.isfinite(self.lat_limit_n) else None,
                           "commands_sent": len(self.c.sent), "force_source": self.fs.report(),
                           "periods_fast_forwarded": self.n_fast})
        gate = SignalGate()     # Ctrl-C and SIGTERM raise until the first does or a fault begins; then only noted
        try:
            if problems or (bad and not cfg.skip_invalid):
                rep.status = RunStatus.REJECTED
                rep.problems = problems + [f"probe {k}: {v}" for k, v in bad.items()]
                return rep
            current = None
            rep.status = RunStatus.RUNNING      # on disk while the round runs: a process killed meanwhile (SIGKILL,
            write_run()                         # a power cut) leaves "running", not the last round's "ok"
            rep.status = RunStatus.OK
            gate.__enter__()
            try:
                self._setup()
                consecutive = 0
                for p in plan.probes:
                    if p.index in done:
                        continue
                    current = p
                    self.samples = _Samples()       # a fault before the probe starts keeps none of the last one's
                    if p.index in bad:
                        rep.records.append(log.write_probe(ProbeRecord(index=p.index, x_m=p.x_m, y_m=p.y_m,
                                                                       status=ProbeStatus.REJECTED,
                                                                       reason=bad[p.index])))
                        rep.n_rejected += 1
                        continue
                    self._ensure_program()
                    rec, raw = self._probe(p)
                    rec = log.write_probe(rec, raw)
                    current = None          # on disk: a fault raised from here on must not write it again
                    rep.records.append(rec)
                    rep.n_ok += rec.status == ProbeStatus.OK
                    rep.n_force_limit += rec.status == ProbeStatus.FORCE_LIMIT
                    rep.n_depth_limit += rec.status == ProbeStatus.DEPTH_LIMIT
                    consecutive = consecutive + 1 if rec.status == ProbeStatus.FORCE_LIMIT else 0
                    if progress:
                        progress(rec, len(rep.records), pre["n_to_run"])
                    if consecutive >= cfg.max_consecutive_force_stops:
                        raise ProbeFault(FaultKind.FORCE_LIMIT, f"{consecutive} consecutive probes stopped at the "
                                                                f"force limit: check the plan and the tissue")
            except BaseException as e:      # any fault ends with the arm stopped and the data kept
                gate.hold()                 # first: from here to the stop's end no signal cuts it short
                if isinstance(e, GeneratorExit):
                    raise
                self._fault_stop(e, rep, current, log, write_run)
                rep.fault["notes"] += [f"{n} during the safe stop: held until the arm was stopped" for n in gate.held]
                try:
                    hint = self.diagnose() if self.diagnose is not None else None
                except Exception as w:      # noqa: BLE001 -- a hint, not a reason to lose the report
                    hint = f"the operator hint could not be made ({type(w).__name__}: {w})"
                if hint:                    # what the operator must do (e.g. the pendant left in local control)
                    rep.fault["notes"].append(hint)
                if not isinstance(e, (ProbeFault, SafetyViolation, KeyboardInterrupt)):
                    raise                   # stopped, and on disk as far as the disk allows: now raise it
                # a signal the safe stop held back is in the notes: the run has ended with a fault or an interrupt
                # already, which its callers end on (app.runexec raises RunAborted; the cell reports and exits)
            return rep
        finally:
            try:
                try:
                    write_run()
                    log.close()
                except Exception as w:      # noqa: BLE001 -- a full disk: the report (returned) says so
                    if rep.fault is not None:
                        rep.fault.setdefault("notes", []).append(f"run.json could not be written at the end ({w})")
                    else:
                        raise
            finally:
                try:
                    log.close()             # idempotent; here when the write before it failed
                finally:
                    gate.__exit__(None, None, None)
                    if gc_was_enabled:
                        gc.enable()

    def _fault_stop(self, e: BaseException, rep: RunReport, current, log: RunLog, write_run) -> None:
        """After ``e``: the fault into ``rep``, the interrupted probe's record and run.json on disk (a failed write
        is a note: it must not keep the arm from stopping), then the safe state (whatever it raises is a note)."""
        interrupted = isinstance(e, (KeyboardInterrupt, SystemExit))
        kind = e.kind if isinstance(e, ProbeFault) else (
            FaultKind.INTERRUPTED if interrupted else FaultKind.SAFETY_VIOLATION
            if isinstance(e, SafetyViolation) else FaultKind.DRIVER_ERROR)
        rep.status = RunStatus.INTERRUPTED if kind == FaultKind.INTERRUPTED else RunStatus.FAULT
        expected = interrupted or isinstance(e, (ProbeFault, SafetyViolation))
        try:
            message = (str(e) or "Ctrl-C") if expected and not isinstance(e, SystemExit) else f"{type(e).__name__}: {e}"
        except Exception:                   # noqa: BLE001 -- an exception whose text fails: its type will do
            message = type(e).__name__
        rep.fault = {"kind": kind, "message": message, "probe_index": getattr(current, "index", None),
                     "controller_time_s": self.ts, "detected_unix_s": time.time(), "notes": []}
        if self.retract_blocked:            # a resume must not pull the tip out through that force (_setup)
            rep.fault["retract_blocked"] = True
        lost = []
        if current is not None:
            lost += self._halt_first()      # mid-probe the arm may still be descending: one stopL before any write
        if current is not None:             # on disk before the retract: a hang in safe_state() must not lose them
            try:
                raw = self.samples.arrays()
                st = ProbeStatus.INTERRUPTED if kind == FaultKind.INTERRUPTED else ProbeStatus.FAULT
                rec = summarise(current, raw, st, {}, self.ts, self.ts, self.contact_thr, self.noise_std,
                                self.lim.depth_limit_m)
                rec.reason = rep.fault["message"]
                rep.records.append(log.write_probe(rec, raw))
            except Exception as w:          # noqa: BLE001 -- reported with the fault, after the stop
                lost.append(f"the interrupted probe's record could not be written ({w})")
        try:
            write_run()                     # the fault, before any command is sent
        except Exception as w:              # noqa: BLE001
            lost.append(f"run.json could not be written before stopping ({w})")
        try:
            state = self.safe_state()
        except Exception as w:              # noqa: BLE001 -- what failed is told; a stop is tried once more
            state = {"stopped": False, "retracted": False, "notes": [f"the safe stop failed: {type(w).__name__}: {w}"]}
            if not (self.link_dead or self.stale):
                try:
                    self._stop()
                    state["stopped"] = True
                except Exception as w2:     # noqa: BLE001
                    state["notes"].append(f"stopL failed too: {type(w2).__name__}: {w2}")
        notes = state.pop("notes", [])
        rep.fault.update(state)
        rep.fault["notes"] = notes + lost

    def _setup(self) -> None:
        self._sensor(self.fs.start)                  # an external sensor streams before anything moves
        self._ensure_program()
        s = self._read(strict=False)
        p = s["pose"]
        if not all(self.lim.box_min[k] <= p[k] <= self.lim.box_max[k] for k in range(3)):
            raise SafetyViolation(f"the arm starts at {[round(v, 3) for v in p[:3]]}, outside the workspace box")
        if self.last_blocked and self._needs_retract(s["depth"], s["x"]):
            self.retract_blocked = "the last run stopped in a retract that met a force"
            raise ProbeFault(FaultKind.RETRACT_FORCE,
                             f"the last run in this directory stopped in a retract that met a force (run.json), and "
                             f"the tip is still {(s['depth'] + self.plan.motion.approach_height_m) * 1e3:.1f} mm below "
                             f"its approach height: the driver does not pull it out through that force; free the tip "
                             f"(freedrive on the pendant, out of the tissue), then resume")
        self._retract_from(p, s["depth"], s["x"])   # a resumed run may start with the tip in tissue
        self._zero(rotvec=p[3:])                     # free air: zero and check the sensor before moving on


def run_plan(plan, rtde_c, rtde_r, out_dir, *, config: DriverConfig | None = None, resume=True,
             progress=None, diagnose=None, force_source: ForceSource | None = None) -> RunReport:
    """Execute ``plan`` on the arm behind ``rtde_c``/``rtde_r``; records go to ``out_dir`` (see records.py).
    ``diagnose()``: after a fault, an operator hint to add to the report (or None). ``force_source``: where the
    wrench comes from (robot.forcesource; default the UR's wrist sensor over ur_rtde)."""
    return Driver(plan, rtde_c, rtde_r, config, diagnose, force_source).run(out_dir, resume=resume,
                                                                            progress=progress)
