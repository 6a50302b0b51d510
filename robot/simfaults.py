"""Fault injection for the simulated arms: one syntax for the in-memory arm and the simulated UR controller.

A fault is ``KIND-at-s=T[:X]`` (at simulated time T), ``KIND-at-depth-m=D[:X]`` (the first time the tip is D below
the tissue surface, over the tissue), ``KIND-leaving-depth-m=D[:X]`` (the first time the tip, on its way out of the
tissue after being deeper than D, is back at D: in a retract) or ``KIND-after-probes=N[:X]`` (between probes: AT_REST_S after the arm, having
left the tissue N times, came to rest above the next probe, where the driver zeroes the sensor). The older
``KIND:T[:X]`` means ``KIND-at-s=T[:X]``; ``_`` may replace ``-`` in KIND.

Arm faults (both simulators; robot.sim.ArmModel fires them):
  protective-stop   the safety system halts the arm (cleared only from the pendant or the dashboard)
  disconnect        every socket closed, new connections refused (a controller gone from the network)
  drop              every socket closed, reconnecting allowed (a pulled cable put back; ur_rtde reconnects by itself)
  force-spike       X newtons along the normal for 10 ms
  side-push         X newtons across the normal (along the tissue's x) for SIDE_PUSH_S (0.2 s): the tip caught
  nan               readings NaN for X seconds (default 0.01)
  stall             the current motion freezes until stopped or replaced
Controller faults (the simulated controller only, robot.simcontroller fires them):
  partition         sockets stay open but nothing passes either way for X seconds (0 or none: for good)
  freeze            the controller process stops (SIGSTOP) until it is continued or killed
  program-stop      the program is stopped as from the dashboard or the pendant's stop button
  remote-off        the pendant is switched to local control (programs from the network refused; X = 1: also
                    stop the running program, as an operator taking over would)
External sensor faults (the simulated Net F/T box only, robot.simnetft fires them; ``--ft netft``):
  ft-silent         the box sends nothing for X seconds of simulated time (none: for good)
  ft-status         the box reports status word X (default 1) from then on
  ft-loss           a fraction X (default 0.9) of its records is lost on the way from then on
  ft-spike          X newtons along the tissue normal on its reading for 10 ms (beyond its range: saturated)
  ft-freeze         the box repeats its last reading from then on (sequence advancing, status 0: a stuck box)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

ARM_FAULTS = {"protective-stop": "protective_stop", "disconnect": "disconnect", "drop": "disconnect",
              "force-spike": "force_spike", "side-push": "side_push",
              "nan": "nan", "stall": "stall"}
CONTROLLER_FAULTS = ("partition", "freeze", "program-stop", "remote-off")
FT_FAULTS = ("ft-silent", "ft-status", "ft-loss", "ft-spike", "ft-freeze")
TRIGGERS = {"at-s": "s", "at-depth-m": "depth-m", "leaving-depth-m": "leaving-m", "after-probes": "probes"}
OUT_OF_TISSUE_M = 0.0          # tip above the surface: out of the tissue
IN_TISSUE_M = 5e-4             # tip this far below the surface: in it
FORCE_KINDS = ("force-spike", "side-push", "ft-spike")     # X is a force (N)
MAX_INJECTED_FORCE_N = 1000.0  # |X| of a force fault at most this (beyond what a UR5e or an F/T sensor meets)
SIDE_PUSH_S = 0.2              # a side push lasts this long
LEAVING_HYSTERESIS_M = 5e-5   # leaving-depth-m=D: deeper than D by this first (a dwell's sub-micron jitter is not a
#                               way out)
AT_REST_S = 0.05               # into a rest (the driver zeroes the sensor at rest above a probe for ~0.2 s)


@dataclass(frozen=True)
class FaultSpec:
    kind: str                  # a key of ARM_FAULTS or one of CONTROLLER_FAULTS or FT_FAULTS
    trigger: str               # "s" | "depth-m" | "probes"
    value: float               # the time (s), depth (m) or number of probes
    x: float | None = None     # the kind's parameter (N, s, ...), if given

    @property
    def on_controller(self) -> bool:
        return self.kind in CONTROLLER_FAULTS

    @property
    def on_ft(self) -> bool:
        """A fault of the simulated external F/T box (robot.simnetft)."""
        return self.kind in FT_FAULTS

    @property
    def on_arm(self) -> bool:
        return self.kind in ARM_FAULTS

    def text(self) -> str:
        name = next(k for k, v in TRIGGERS.items() if v == self.trigger)
        val = f"{int(self.value)}" if self.trigger == "probes" else f"{self.value:g}"
        return f"{self.kind}-{name}={val}" + ("" if self.x is None else f":{self.x:g}")


def parse(spec: str) -> FaultSpec:
    """A fault specification; ValueError (naming it and what is allowed) for anything else."""
    given = str(spec).strip()
    s = given
    if not any(f"-{t}=" in s for t in TRIGGERS) and "=" not in s and ":" in s:
        kind, _, rest = s.partition(":")
        s = f"{kind}-at-s={rest}"
    name, _, val = s.partition("=")
    trig = next((t for t in TRIGGERS if name.endswith(f"-{t}")), None)
    kind = name[: -len(trig) - 1].replace("_", "-") if trig else ""
    v, _, x = val.partition(":")
    try:
        value, xv = float(v), (float(x) if x else None)
        ok = (kind in ARM_FAULTS or kind in CONTROLLER_FAULTS or kind in FT_FAULTS) and trig is not None and math.isfinite(value) and \
            (xv is None or math.isfinite(xv))
        if ok and TRIGGERS[trig] == "probes":
            ok = value >= 1 and value == int(value)
        if ok and kind == "side-push":      # (without a force it would push nothing, silently)
            ok = xv is not None and xv > 0
        if ok and kind in FORCE_KINDS and xv is not None:   # (1e300 N wrote records the readers refuse)
            ok = abs(xv) <= MAX_INJECTED_FORCE_N
    except ValueError:
        ok = False
    if not ok:
        raise ValueError(f"bad fault {given!r}: KIND-at-s=T[:X], KIND-at-depth-m=D[:X], KIND-leaving-depth-m=D[:X] or "
                         f"KIND-after-probes=N[:X] "
                         f"(N >= 1; or KIND:T[:X]; side-push needs X > 0, its newtons; a force X at most {MAX_INJECTED_FORCE_N:g} N), KIND one of {', '.join([*ARM_FAULTS, *CONTROLLER_FAULTS, *FT_FAULTS])}; "
                         f"see robot.simfaults")
    return FaultSpec(kind, TRIGGERS[trig], value, xv)


def never_fires(f: FaultSpec, probes: int) -> str | None:
    """Why ``f`` cannot fire in a run that probes ``probes`` times, or None (``disconnect-after-probes=99`` on 5
    probes passed silently, the fault never tried). after-probes=N fires at rest above the probe after the N-th
    (``trigger``): after the last one the driver makes no move, so N must be below the probes."""
    if f.trigger == "probes" and f.value >= probes:
        allowed = f"N at most {probes - 1}" if probes > 1 else "no after-probes fault can fire"
        return f"never fires: this run probes {probes} time{'s' * (probes != 1)} ({allowed})"
    return None


def past_the_limit(f: FaultSpec, depth_limit_m: float) -> str | None:
    """A note when a depth trigger lies deeper than the driver lets the tip go (it fires only if that limit
    fails), else None."""
    if f.trigger in ("depth-m", "leaving-m") and f.value > depth_limit_m:
        return (f"fires only if the tip goes past the plan's depth limit ({depth_limit_m:g} m), which the driver "
                f"does not allow")
    return None


def normalize(spec: str) -> str:
    """The canonical text of a fault specification (ValueError if it is not one)."""
    return parse(spec).text()


def trigger(f: FaultSpec):
    """``when(arm) -> bool`` for a depth or probe-count trigger (stateful: call it once per controller cycle)."""
    if f.trigger == "depth-m":
        def when(arm) -> bool:
            x, depth = arm.tip_in_tissue()
            return depth >= f.value and 0.0 <= x <= arm.width_m
        return when
    if f.trigger == "leaving-m":
        deeper = [False]        # the tip has been deeper than D over the tissue since it last was out of it

        def when(arm) -> bool:
            x, depth = arm.tip_in_tissue()
            over = 0.0 <= x <= arm.width_m
            deeper[0] = (deeper[0] or (over and depth > f.value + LEAVING_HYSTERESIS_M)) and depth >= OUT_OF_TISSUE_M
            return deeper[0] and over and depth <= f.value
        return when
    if f.trigger == "probes":
        # at rest above the next probe: after the N-th exit the arm stops (end of the retract), moves (the approach
        # to the next probe) and stops again; AT_REST_S into that second rest (the driver zeroes the sensor there),
        # whatever the host's timing
        state = {"inside": False, "exits": 0, "rests": 0, "still_since": None}

        def when(arm) -> bool:
            x, depth = arm.tip_in_tissue()
            if 0.0 <= x <= arm.width_m and depth >= IN_TISSUE_M:
                state["inside"] = True
            elif state["inside"] and depth < OUT_OF_TISSUE_M:
                state["inside"], state["rests"] = False, 0
                state["exits"] += 1
            if state["exits"] < f.value:
                return False
            if arm.is_moving:
                state["still_since"] = None
                return False
            if state["still_since"] is None:
                state["still_since"] = arm.t_s
                state["rests"] += 1
            return state["rests"] >= 2 and arm.t_s - state["still_since"] >= AT_REST_S
        return when
    at = f.value
    return lambda arm: arm.t_s >= at


def inject_arm(arm, f: FaultSpec) -> None:
    """Schedule an arm fault on a robot.sim.ArmModel."""
    if f.on_controller:
        raise ValueError(f"fault {f.text()!r} needs the simulated controller (palpate-cell --sim controller)")
    if f.on_ft:
        raise ValueError(f"fault {f.text()!r} is the simulated Net F/T box's (--ft netft; robot.simnetft)")
    kind = ARM_FAULTS[f.kind]
    x = f.x
    kw = {"magnitude_n": float(x or 0.0),
          "duration_s": float(x or 0.01) if kind == "nan" else SIDE_PUSH_S if kind == "side_push" else 0.01,
          "reconnectable": f.kind == "drop"}
    if f.trigger == "s":
        arm.inject(kind, at_s=f.value, **kw)
    else:
        arm.inject(kind, when=trigger(f), **kw)
