"""Reading an ATI Net F/T box over UDP (RDT, robot.rdt): ``NetFtReader``.

The reader asks the box to stream (real-time mode, endless) and, on every ``poll()``, drains what the socket holds
without blocking (no thread: a read per controller period costs one non-blocking recvfrom per record, and nothing
competes with the control loop for the GIL). Each record is checked before it is kept in a ring buffer:

* sequence: the RDT sequence (uint32, wraps) must advance; a gap counts lost records, an older or repeated one was
  reordered on the way and is dropped; more than ``max_lost_fraction`` of the last ``loss_window`` sequence numbers
  lost is a fault (SENSOR_PACKET_LOSS);
* status: anything but 0 is the box reporting a problem (a broken gauge, saturation, a configuration error): a fault
  (SENSOR_STATUS) with the word in hex;
* saturation: a force axis at or beyond ``range_n`` (or a torque beyond ``range_nm``) means the true force is unknown,
  so the force limit could not be enforced: a fault (SENSOR_SATURATED);
* freshness: no new record for ``stale_s`` on the reader's clock is a fault (SENSOR_LOST) -- the box, its cable or
  the network is gone;
* life: more than ``max_identical`` records in a row with the very same counts on all six axes, or with the same
  F/T sequence (the box's own sample counter), is a fault (SENSOR_FROZEN) -- a live gauge always shows noise
  (thousands of counts for an ATI transducer) and a sampling box counts on, a stuck one repeats itself with a healthy
  status;
* scaling: a reading that is not finite once scaled is a fault (INVALID_READING).

Counts become SI with the box's calibration (counts per N, counts per N m): ``NetFtCalibration``, read from the
box's ``http://BOX/netftapi2.xml`` (``fetch_calibration``) or given. Readings stay in the SENSOR frame here; the
force source (robot.forcesource) zeroes them and turns them into the base frame.
"""
from __future__ import annotations

import math
import re
import socket
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from core.contracts import FaultKind
from robot.rdt import CMD_START_REALTIME, CMD_STOP, RDT_PORT, pack_request, seq_ahead, unpack_records

HTTP_TIMEOUT_S = 2.0
MIN_LOSS_SPAN = 100             # the loss fraction is judged over at least this many sequence numbers


class SensorFault(Exception):
    """The external sensor cannot be trusted now; ``kind`` is a core.contracts.FaultKind."""

    def __init__(self, kind: str, message: str):
        super().__init__(f"{kind}: {message}")
        self.kind, self.message = kind, message


@dataclass(frozen=True)
class NetFtCalibration:
    counts_per_force: float         # counts per N
    counts_per_torque: float        # counts per N m

    def __post_init__(self):
        for name in ("counts_per_force", "counts_per_torque"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} {v!r}: a positive finite number of counts is needed")

    @staticmethod
    def from_xml(text: str) -> "NetFtCalibration":
        """From the box's netftapi2.xml: ``cfgcpf`` / ``cfgcpt`` with their units ``cfgfu`` / ``cfgtu``, which must
        be N and Nm (the box can be configured to others: set it to N and Nm on its configuration page)."""
        def element(tag: str) -> str:
            m = re.search(rf"<{tag}>\s*([^<]*?)\s*</{tag}>", text)
            if m is None:
                raise ValueError(f"netftapi2.xml: no <{tag}> element")
            return m.group(1)
        units = {"cfgfu": ("N", "2"), "cfgtu": ("Nm", "N-m", "3")}     # by name, or the box's unit code
        for tag, allowed in units.items():
            u = element(tag)
            if u not in allowed:
                raise ValueError(f"netftapi2.xml: <{tag}> is {u!r}; set the box's {'force' if tag == 'cfgfu' else 'torque'} "
                                 f"unit to {allowed[0]} on its configuration page")
        try:
            return NetFtCalibration(float(element("cfgcpf")), float(element("cfgcpt")))
        except ValueError as e:
            raise ValueError(f"netftapi2.xml: {e}") from None


def fetch_calibration(host: str, timeout_s: float = HTTP_TIMEOUT_S, port: int = 80) -> NetFtCalibration:
    """The box's calibration from ``http://HOST/netftapi2.xml``. OSError (unreachable) or ValueError (not a Net
    F/T configuration page, other units)."""
    from urllib.request import urlopen  # http, ssl and email: only next to a real box (15 ms of a simulated run)
    with urlopen(f"http://{host}:{port}/netftapi2.xml", timeout=timeout_s) as resp:
        return NetFtCalibration.from_xml(resp.read().decode("utf-8", "replace"))


@dataclass(frozen=True)
class NetFtConfig:
    host: str
    calibration: NetFtCalibration
    port: int = RDT_PORT
    range_n: float = math.inf       # rated force range per axis: a reading there is saturated
    range_nm: float = math.inf      # rated torque range per axis
    resync_after_s: float = 0.1     # no poll for this long: the host was away, what the socket holds is old
    stale_s: float = 0.05           # no new record for this long (reader's clock): the sensor is lost. A real box
                                    # sends >= 1 kHz and the kernel keeps what a held-up host has not read, so only
                                    # a silent box trips it; the margin is for a simulated box in a busy process.
                                    # Blind travel at 2 mm/s: 0.1 mm (bench/ft_reaction.py has the overshoot)
    start_timeout_s: float = 1.0    # the first record must come within this (wall time)
    max_lost_fraction: float = 0.5  # of the last loss_window sequence numbers
    loss_window: int = 200          # sequence numbers (0.2 s at 1 kHz)
    buffer_len: int = 4096          # records kept (a few seconds at 1 kHz)
    max_identical: int = 50         # records in a row with identical counts (0: not checked, a noiseless sensor):
                                    # 50 ms at 1 kHz, the same blind time as stale_s


class NetFtReader:
    """A Net F/T box's stream: ``start()``, then ``poll()`` and ``latest()`` / ``mean(n)`` each control period,
    ``stop()``. ``clock``: what ``stale_s`` is measured on (wall time for a real box; the simulated controller's time
    for a box stepped with the in-memory arm, whose ``wait`` then lets a controller period pass)."""

    def __init__(self, cfg: NetFtConfig, clock=time.monotonic, wait=None):
        self.cfg, self.clock = cfg, clock
        self.wait = wait or (lambda: time.sleep(0.001))   # between polls while waiting for the first record
        self.sock: socket.socket | None = None
        n = cfg.buffer_len
        self.ft = np.zeros((n, 6))          # SI, sensor frame
        self.seq = np.zeros(n, dtype=np.int64)
        self.t = np.zeros(n)                # reader's clock at the poll that received it
        self.count = 0                      # records kept since start (index of the next slot = count % n)
        self.last_seq: int | None = None
        self.last_rx: float | None = None
        self.gaps: deque = deque()          # per kept record of the loss window: sequence numbers it advanced by
        self.span = 0                       # their sum
        self.n_lost = self.n_reordered = self.n_datagrams_bad = self.resyncs = 0
        self.last_poll: float | None = None
        self.prev_counts, self.prev_ft_seq, self.identical = None, None, 0
        self.max_abs_n = 0.0
        self._scale = np.array([1.0 / cfg.calibration.counts_per_force] * 3 +
                               [1.0 / cfg.calibration.counts_per_torque] * 3)

    # ---- session ---------------------------------------------------------------------------------------------
    def start(self) -> None:
        """Open the socket, ask for endless real-time streaming, wait for the first record."""
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)   # a host held up 1 s at 7 kHz loses nothing
        try:
            s.connect((self.cfg.host, self.cfg.port))   # only the box's datagrams are received
        except OSError as e:
            s.close()
            raise SensorFault(FaultKind.SENSOR_LOST, f"Net F/T at {self.cfg.host}:{self.cfg.port}: {e.strerror or e}")
        s.setblocking(False)
        self.sock = s
        self._send(CMD_START_REALTIME)
        t_end = time.monotonic() + self.cfg.start_timeout_s
        while self.poll() == 0:
            if time.monotonic() > t_end:
                self.stop()
                raise SensorFault(FaultKind.SENSOR_LOST, f"no record from the Net F/T at {self.cfg.host}:"
                                                         f"{self.cfg.port} within {self.cfg.start_timeout_s:g} s "
                                                         f"of asking it to stream (address, cable, power?)")
            self.wait()

    def _send(self, command: int) -> None:
        try:
            self.sock.send(pack_request(command))
        except OSError as e:       # e.g. ECONNREFUSED from an earlier datagram: nothing listens there
            raise SensorFault(FaultKind.SENSOR_LOST, f"Net F/T at {self.cfg.host}:{self.cfg.port}: "
                                                     f"{e.strerror or e}") from None

    def stop(self) -> None:
        """Ask the box to stop streaming and close the socket (never raises)."""
        if self.sock is not None:
            try:
                self.sock.send(pack_request(CMD_STOP))
            except OSError:
                pass
            self.sock.close()
            self.sock = None

    # ---- data ------------------------------------------------------------------------------------------------
    def poll(self) -> int:
        """Drain the socket; check and keep every record. Returns how many were kept; raises SensorFault. After
        more than ``resync_after_s`` without a poll (the host was busy elsewhere: between runs, planning) the reader
        resynchronises first."""
        if self.sock is None:
            raise SensorFault(FaultKind.SENSOR_LOST, f"the Net F/T at {self.cfg.host} is not streaming (stopped)")
        now = self.clock()
        away = self.last_poll is not None and now - self.last_poll > self.cfg.resync_after_s
        self.last_poll = now
        if away:
            self.resync()
            now = self.last_poll = self.clock()
        kept = self._drain(now)
        if kept:
            self.last_rx = now
        return kept

    def _drain(self, now: float, keep: bool = True) -> int:
        kept = 0
        while True:
            try:
                data = self.sock.recv(4096)
            except (BlockingIOError, InterruptedError):
                return kept
            except OSError as e:
                raise SensorFault(FaultKind.SENSOR_LOST, f"Net F/T at {self.cfg.host}: {e.strerror or e}") from None
            try:
                records = unpack_records(data)
            except ValueError:
                self.n_datagrams_bad += 1
                continue
            for rec in records:
                kept += self._keep(rec, now) if keep else 0

    def resync(self) -> None:
        """What the socket holds is old: the host did not read it for a while, and once the kernel's buffer was full
        the newer records were dropped (the host's doing, not the network's). Discard it, forget the sequence and
        the loss window, and wait (``wait``, at most ``start_timeout_s``) for a fresh record."""
        self._drain(0.0, keep=False)
        self.last_seq, self.span, self.last_rx = None, 0, None
        self.gaps.clear()
        self.resyncs += 1
        t_end = time.monotonic() + self.cfg.start_timeout_s
        while self._drain(self.clock()) == 0:
            if time.monotonic() > t_end:
                raise SensorFault(FaultKind.SENSOR_LOST, f"no fresh record from the Net F/T at {self.cfg.host} within "
                                                         f"{self.cfg.start_timeout_s:g} s")
            self.wait()
        self.last_rx = self.clock()

    def _keep(self, rec, now: float) -> int:
        if self.last_seq is not None:
            ahead = seq_ahead(rec.rdt_sequence, self.last_seq)
            if ahead <= 0:
                self.n_reordered += 1
                return 0
            self.n_lost += ahead - 1
            self.gaps.append(ahead)
            self.span += ahead
            while len(self.gaps) > 1 and self.span - self.gaps[0] >= self.cfg.loss_window:
                self.span -= self.gaps.popleft()
            total, lost = self.span, self.span - len(self.gaps)
            if total >= min(MIN_LOSS_SPAN, self.cfg.loss_window) and lost > self.cfg.max_lost_fraction * total:
                raise SensorFault(FaultKind.SENSOR_PACKET_LOSS,
                                  f"{lost} of the last {total} Net F/T records lost on the way (more than "
                                  f"{self.cfg.max_lost_fraction:.0%}): check the network between host and box")
        self.last_seq = rec.rdt_sequence
        if rec.status != 0:
            raise SensorFault(FaultKind.SENSOR_STATUS, f"the Net F/T box reports status 0x{rec.status:08x} (record "
                                                       f"{rec.rdt_sequence}): see its manual and web page")
        if rec.counts == self.prev_counts or rec.ft_sequence == self.prev_ft_seq:
            self.identical += 1
            if self.cfg.max_identical and self.identical >= self.cfg.max_identical:
                raise SensorFault(FaultKind.SENSOR_FROZEN, f"{self.identical + 1} Net F/T records in a row with the "
                                                           f"same counts or F/T sequence (counts {list(rec.counts)}, "
                                                           f"F/T sequence {rec.ft_sequence}): the box or its gauges "
                                                           f"are stuck (a live sensor shows noise and counts on)")
        else:
            self.identical = 0
        self.prev_counts, self.prev_ft_seq = rec.counts, rec.ft_sequence
        ft = np.asarray(rec.counts, dtype=float) * self._scale
        if not np.all(np.isfinite(ft)):
            raise SensorFault(FaultKind.INVALID_READING, f"Net F/T record {rec.rdt_sequence} scales to {ft.tolist()}")
        fmax, tmax = float(np.max(np.abs(ft[:3]))), float(np.max(np.abs(ft[3:])))
        self.max_abs_n = max(self.max_abs_n, fmax)
        if fmax >= self.cfg.range_n or tmax >= self.cfg.range_nm:
            raise SensorFault(FaultKind.SENSOR_SATURATED,
                              f"Net F/T reading {np.round(ft, 4).tolist()} at its rated range ({self.cfg.range_n:g} N, "
                              f"{self.cfg.range_nm:g} N m): the true force is unknown")
        i = self.count % self.cfg.buffer_len
        self.ft[i], self.seq[i], self.t[i] = ft, rec.rdt_sequence, now
        self.count += 1
        return 1

    def check_fresh(self) -> None:
        if self.last_rx is None or self.clock() - self.last_rx > self.cfg.stale_s:
            age = "never" if self.last_rx is None else f"{self.clock() - self.last_rx:.3f} s ago"
            raise SensorFault(FaultKind.SENSOR_LOST, f"no new Net F/T record for more than {self.cfg.stale_s:g} s "
                                                     f"(last {age}): the box, its cable or the network is gone")

    def latest(self) -> np.ndarray:
        """The newest record (N, N m; sensor frame) after ``poll()``; SensorFault if it is stale."""
        self.poll()
        self.check_fresh()
        return self.ft[(self.count - 1) % self.cfg.buffer_len].copy()

    def mean(self, window_s: float) -> tuple[np.ndarray, int]:
        """The mean of the records received in the last ``window_s`` (at least the newest one; at most the buffer)
        and how many they were."""
        k = min(self.count, self.cfg.buffer_len)
        if k == 0:
            raise SensorFault(FaultKind.SENSOR_LOST, "no Net F/T record to average")
        idx = (self.count - 1 - np.arange(k)) % self.cfg.buffer_len
        recent = idx[self.t[idx] >= self.t[idx[0]] - window_s]
        return self.ft[recent].mean(axis=0), len(recent)

    def report(self) -> dict:
        return {"records": int(self.count), "lost": int(self.n_lost), "reordered": int(self.n_reordered),
                "bad_datagrams": int(self.n_datagrams_bad),
                "resyncs": int(self.resyncs), "max_abs_force_n": self.max_abs_n}
