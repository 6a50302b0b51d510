"""After a fault: bring the arm to a safe state (the driver's recovery half; ``Driver`` inherits it).

``safe_state()``: a protective stop needs nothing (the controller halted the arm; it takes no commands until the
stop is cleared on the pendant). Otherwise stop (stopL), then retract along the tissue normal to the approach
height when the arm still takes commands. A lost link: wait for it (only ``isConnected()`` is called meanwhile:
ur_rtde 1.6.5 can block for good on a command or reconnect() that races its own background reconnect), then call
reconnect() once; with no link no command is sent, and the last command was a bounded moveL that ends no deeper than
the planned depth. Uses the driver's primitives (``_stop``, ``_read``, ``_move``, ``_ensure_program``) and state (``c``, ``r``, ``cfg``,
``plan``, ``lim``, ``tf``).
"""
from __future__ import annotations

import math

import numpy as np

from robot.link import SLOW_COMMAND_TIMEOUT_S
from robot.safety import SafetyViolation


class ProbeFault(Exception):
    def __init__(self, kind: str, message: str):
        super().__init__(f"{kind}: {message}")
        self.kind, self.message = kind, message


class Recovery:
    @staticmethod
    def _connected(iface) -> bool:
        try:
            return iface.isConnected() is True
        except RuntimeError:
            return False

    def _await_link(self, out) -> bool:
        """The link is down: wait ``reconnect_after_s`` for it to come back by itself, then call reconnect() once.
        ur_rtde 1.6.5 reconnects in the background; a reconnect() or command racing that, or sent after it failed,
        can block for good, so nothing but isConnected() is called while waiting. The wait counts controller
        periods (initPeriod/waitPeriod are local to the client): wall time on a real arm, simulated on the sim."""
        for _ in range(max(1, int(math.ceil(self.cfg.reconnect_after_s / self.cfg.period_s)))):
            if self._connected(self.c) and self._connected(self.r):
                out["notes"].append("the link came back by itself")
                return True
            t0 = self.c.initPeriod()
            self.c.waitPeriod(t0)
        ok = True
        for iface in (self.c, self.r):
            if not self._connected(iface):
                try:
                    ok = ok and self.worker.call(iface.reconnect, (), SLOW_COMMAND_TIMEOUT_S) is True
                except (RuntimeError, AttributeError, SafetyViolation):     # CallTimeout too
                    ok = False
        out["notes"].append(f"no connection for {self.cfg.reconnect_after_s:g} s; reconnect() "
                            + ("succeeded" if ok else "failed"))
        if ok:
            self.last_ts, self.stale = None, 0
        return ok

    def safe_state(self) -> dict:
        """Stop, then retract along the normal to the approach height if the arm still takes commands."""
        out = {"stopped": False, "retracted": False, "notes": []}
        try:
            pstop = self.r.isProtectiveStopped() is True
        except RuntimeError:
            pstop = False
        if pstop:   # the controller has stopped the arm; it takes no commands until the stop is cleared
            out["stopped"] = True
            out["notes"].append("protective stop: the arm halted where it was; clear the stop on the pendant, "
                                "then resume (the driver first retracts along the tissue normal)")
            return out
        bounded = ("the last command was a bounded moveL (target no deeper than the planned depth); the arm stops "
                   "there at the latest")
        silent = self.link_dead or (self.stale >= self.cfg.stale_periods and self._connected(self.c)
                                    and self._connected(self.r))
        if silent:
            out["silent_link"] = True       # the session's end sends nothing either (no disconnect)
            # A silent link (controller data stale although ur_rtde reports a connection): a command now would wait
            # up to ur_rtde's execution time-out (300 s) for an answer that never comes. Send nothing; the driver
            # no longer kicks the RTDE watchdog, so the controller stops the program and the motion within 1/rate.
            rate = getattr(self, "watchdog_hz", 0.0) if getattr(self, "watchdog_on", False) else 0.0
            if self.link_dead:
                out["notes"].append(f"a command got no answer: {self.link_dead}")
            if rate > 0:
                self._idle(2.0 / rate)
                out["notes"].append(f"silent link: no command sent (it could block for ur_rtde's 300 s time-out); "
                                    f"the controller's RTDE watchdog stops the program and the motion within "
                                    f"{1.0 / rate:.2f} s of the last kick")
            else:
                out["notes"].append(f"silent link: no command sent; watchdog off: {bounded}")
            return out
        if not self._connected(self.c) and not self._await_link(out):
            out["notes"].append(f"no connection: no command sent; {bounded}")
            return out
        # (a link ur_rtde reconnected by itself: its control interface is back with a new program -- no watchdog,
        # the flange as TCP -- while its receive interface may still be reconnecting: stop, wait, reconfigure,
        # retract)
        for attempt in range(2):
            try:
                running = self._call(self.c.isProgramRunning) is True
                self._stop()              # ur_rtde's stopL returns nothing; a lost link raises
                out["stopped"] = True
                out["stopped_by"] = "stopL" if running else "the controller (its program had already ended)"
                break
            except ProbeFault as f:
                out["notes"].append(f"stopL failed: {f.message}")
                if attempt == 1:
                    out["notes"].append(f"stopL failed again after reconnecting: {bounded}")
                    return out
                if not self._await_link(out):
                    out["notes"].append(f"reconnect failed: {bounded}")
                    return out
        if not self._connected(self.r) and not self._await_link(out):
            out["notes"].append("retract skipped: the receive interface did not come back")
            return out
        # The program may be a new one (ur_rtde's own reconnect, an upload after the watchdog's stop) with the
        # flange as TCP: the pose means the tip only once the TCP is set again, so configure first, then read.
        try:
            self._ensure_program()
        except Exception as e:     # noqa: BLE001 -- ProbeFault, SafetyViolation, or an error no one foresaw
            out["notes"].append(f"retract skipped: the control program could not be configured ({e}); the reported "
                                f"pose is not the tip's: check on the pendant whether the tip is still in the tissue "
                                f"before moving the arm")
            return out
        if self.retract_blocked:
            out["notes"].append(f"not retracted: {self.retract_blocked}; the arm holds where it stopped (free the "
                                f"tip with freedrive on the pendant, out of the tissue, then resume: a resume does not "
                                f"pull it out through that force)")
            return out
        try:
            s = self._read(strict=False)
            if not self._needs_retract(s["depth"], s["x"]):
                out["notes"].append("the tip is already clear of the tissue: no retract needed")
            out["retracted"] = self._retract_from(s["pose"], s["depth"], s["x"])
        except Exception as e:     # noqa: BLE001 -- the arm is stopped; the operator is told what failed
            out["notes"].append(f"retract failed: {type(e).__name__}: {e}")
        return out

    def _idle(self, seconds: float) -> None:
        """Let ``seconds`` of controller periods pass without sending anything (initPeriod/waitPeriod are local to
        the client: wall time on a real arm, simulated time on the simulator)."""
        for _ in range(max(1, int(math.ceil(seconds / self.cfg.period_s)))):
            self.c.waitPeriod(self.c.initPeriod())

    def _needs_retract(self, depth, x) -> bool:
        """The tip is below the approach height (within 1 mm), over the tissue or beside it: a straight move from
        there to a probe could cut through the tissue (before session 38 only a tip over the tissue was retracted,
        and a start beside it, below its surface, moved sideways into it). Straight up along the normal is free air
        in both cases (``x``: kept for the callers' reports)."""
        return depth > -self.plan.motion.approach_height_m + 1e-3

    def _retract_from(self, pose, depth, x) -> bool:
        h = self.plan.motion.approach_height_m
        if not self._needs_retract(depth, x):
            return True
        target = list(np.asarray(pose[:3]) + self.tf.normal * (depth + h)) + list(pose[3:])
        self._move(target, min(self.cfg.retract_speed_m_s, self.lim.tool_speed_m_s), min(0.5, self.lim.accel_m_s2),
                   self._retract_watch(), strict=False, what="retract")
        return True

