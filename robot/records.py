"""What a run leaves on disk, and how a run resumes from it.

``<out>/probes.jsonl``  one JSON object per probe attempt, appended, flushed and fsync'ed before the next probe.
                        Keys carry units (see ``driver.summarise``); ``status`` is "ok", "force_limit" (stopped at
                        the force limit, e.g. over a stone), "depth_limit" (stopped the depth limit below the surface
                        fitted to the force felt, or past the contact felt: the surface higher than planned), "rejected" (failed the safety checks, never moved),
                        "fault" or "interrupted" (the attempt ended early; its samples are still kept).
``<out>/raw/probe_NNN[_aK].npz``  the raw samples of that attempt: ``time_s`` (N), ``tcp_pose`` (N x 6, base
                        frame), ``wrench`` (N x 6, as read), ``force_n`` (N, contact force along the tissue normal),
                        ``depth_m`` (N), ``phase`` (N: 0 free air, 1 descent, 2 dwell, 3 retract).
``<out>/run.json``      the run's summary: status ("running" while a round runs), fault report, counts (written atomically).

Resume: the last record of each index wins; indices whose last status is "ok" are not probed again ("force_limit"
and "depth_limit" ones are: the stop may have been a sensor spike, the surface may have been registered again). A torn last line (a crash mid-write) is ignored, and the next record starts on a
line of its own.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import time
import zipfile
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from core.contracts import (
    BASELINE_CLEARANCE_M,
    BASELINE_SETTLE_S,
    DESCENT,
    DWELL,
    MEASURED,
    MIN_BASELINE_SAMPLES,
    PLAUSIBLE_FORCE_RATIO,
    PLAUSIBLE_SIGMAS,
    ProbeRecord,
    ProbeStatus,
)

# what a resumed run does not press again: an ok probe, and a depth_limit one (a measurement a repeat would only
# repeat; session 59's review found a resume pressing them again); a force_limit stop may be a sensor's spike:
# a resumed run probes it again
DONE = (ProbeStatus.OK, ProbeStatus.DEPTH_LIMIT)


HISTORY = "run_history.jsonl"     # every run.json a later report replaced, one per line


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class RunLog:
    def __init__(self, out_dir: str | Path):
        self.out = Path(out_dir)
        (self.out / "raw").mkdir(parents=True, exist_ok=True)
        self.jsonl = self.out / "probes.jsonl"
        if self.jsonl.exists() and self.jsonl.stat().st_size:
            self._set_torn_line_aside()
        self._f = open(self.jsonl, "a", encoding="utf-8")
        self._own_running = False      # run.json holds this log's own "running" marker (write_run)

    def _set_torn_line_aside(self) -> None:
        """A process killed mid-line left a torn last line (no newline after it): appended to probes.jsonl.torn
        (fsync'ed; kept, never read as a record) and cut from probes.jsonl, so the next record is a line of its own
        and the file holds records only (read_records lists any other line as damaged). Before session 48 the torn
        line was ended with a newline and stayed, and a resumed run then called it damaged."""
        data = self.jsonl.read_bytes()
        if data.endswith(b"\n"):
            return
        keep = data.rfind(b"\n") + 1
        with open(self.out / "probes.jsonl.torn", "ab") as f:
            f.write(data[keep:] + b"\n")
            f.flush()
            os.fsync(f.fileno())
        with open(self.jsonl, "r+b") as f:
            f.truncate(keep)
            f.flush()
            os.fsync(f.fileno())

    def _raw_path(self, index: int) -> Path:
        p = self.out / "raw" / f"probe_{index:03d}.npz"
        k = 2
        while p.exists():
            p = self.out / "raw" / f"probe_{index:03d}_a{k}.npz"
            k += 1
        return p

    def write_probe(self, record: ProbeRecord, raw: dict | None = None) -> ProbeRecord:
        """Raw samples first (so a record never points at a missing file), then the summary line; both on disk
        (flush + fsync) when this returns."""
        record = dataclasses.replace(record)
        if raw is not None:
            path = self._raw_path(int(record.index))
            with open(path, "wb") as f:
                np.savez(f, **{k: np.asarray(v) for k, v in raw.items()})
                f.flush()
                os.fsync(f.fileno())
            record.raw_file = str(path.relative_to(self.out))
        self._f.write(json.dumps(record.to_dict(), allow_nan=False, default=_jsonable) + "\n")
        self._f.flush()
        os.fsync(self._f.fileno())
        return record

    def write_run(self, summary: dict) -> None:
        """run.json: this run's report (atomically); the report it replaces is appended to run_history.jsonl first,
        so a resumed run keeps every earlier fault's report (a session-54 safety review: after four interrupts and a
        resume, run.json said "ok" and the stops' reports were gone)."""
        old = self.out / "run.json"
        if not self._own_running:               # (this round's own "running" marker is not history; a
            with contextlib.suppress(OSError):  # killed process's is: it says the process was cut off)
                self._keep(old)
        self._own_running = summary.get("status") == "running"
        tmp = self.out / "run.json.tmp"
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(summary, f, indent=1, default=_jsonable)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.out / "run.json")
        _fsync_dir(self.out)

    def _keep(self, old: Path) -> None:
        """The report in ``old`` (if any) appended to run_history.jsonl, as JSON (a damaged one as its text)."""
        if not old.exists():
            return
        text = old.read_text(encoding="utf-8", errors="replace")
        try:
            line = json.dumps(json.loads(text), allow_nan=False)
        except ValueError:              # (damaged or edited: kept as it is, as a string)
            line = json.dumps({"unparsed_run_json": text})
        with open(self.out / HISTORY, "a", encoding="utf-8") as f:
            f.write(line + "\n")
            f.flush()
            os.fsync(f.fileno())

    def close(self) -> None:
        self._f.close()


def _jsonable(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(f"not JSON serialisable: {type(v).__name__}")


def _non_finite(constant: str):
    raise ValueError(f"{constant} (the driver writes finite numbers only)")


def read_records(out_dir: str | Path, damaged: list | None = None) -> list[ProbeRecord]:
    """Every readable line of probes.jsonl, in order. A torn final line (a crash mid-write: no newline after it) is
    skipped; any other line that is not a record (edited or damaged: not JSON, a non-finite or absurd number, a
    field of the wrong type) is skipped too and, with ``damaged``, listed there as (line number, why)."""
    path = Path(out_dir) / "probes.jsonl"
    if not path.exists():
        return []
    text = path.read_text(encoding="utf-8", errors="replace")
    lines = text.splitlines()
    out = []
    for k, line in enumerate(lines, 1):
        try:
            out.append(ProbeRecord.from_dict(json.loads(line, parse_constant=_non_finite)))
        except (json.JSONDecodeError, TypeError, ValueError, AttributeError) as e:
            torn = k == len(lines) and not text.endswith("\n")
            if damaged is not None and not torn:
                damaged.append((k, str(e).splitlines()[0][:120] if str(e) else type(e).__name__))
    return out


def last_retract_blocked(out_dir: str | Path) -> bool:
    """Did the last run in ``out_dir`` (its run.json) end held in a retract that met a force (``retract_blocked``)?
    A run.json that cannot be read says no (its report is kept in run_history.jsonl as it is)."""
    try:
        rep = json.loads((Path(out_dir) / "run.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    fault = rep.get("fault") if isinstance(rep, dict) else None
    return isinstance(fault, dict) and fault.get("retract_blocked") is True


def damaged_note(out_dir: str | Path) -> str | None:
    """A warning line when probes.jsonl in ``out_dir`` holds lines that are not probe records (edited or damaged),
    which a resumed run leaves as they are, does not use, and whose probes it presses again; else None."""
    damaged: list = []
    read_records(out_dir, damaged)
    if not damaged:
        return None
    where = "; ".join(f"line {k}: {why}" for k, why in damaged[:3]) + ("; ..." if len(damaged) > 3 else "")
    return (f"warning: {len(damaged)} line(s) of {Path(out_dir) / 'probes.jsonl'} are not probe records (edited or "
            f"damaged; {where}): they are left as they are and not used, and their probes are pressed again")


def raw_damaged_note(out_dir: str | Path) -> str | None:
    """A warning line when a kept probe's raw samples (its record's ``raw_file``) are missing or cannot be read
    whole (truncated, garbled: the zip's checksums); else None. The record holds what the fit uses, so the probe is
    not pressed again, but its samples are gone: said, never silent (a resume read only the records until session
    60)."""
    bad = []
    for i, r in sorted(latest_by_index(out_dir).items()):
        if not r.raw_file:
            continue
        try:
            with np.load(Path(out_dir) / r.raw_file) as z:
                for k in z.files:
                    z[k]
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
            bad.append(f"probe {i}: {r.raw_file} ({type(e).__name__})")
    if not bad:
        return None
    return (f"warning: the raw samples of {len(bad)} probe(s) measured before are missing or damaged "
            f"({'; '.join(bad[:3])}{'; ...' if len(bad) > 3 else ''}): their records are kept and used (the fit needs "
            f"no more), but those samples cannot be read again")


def latest_by_index(out_dir: str | Path) -> dict[int, ProbeRecord]:
    return {int(r.index): r for r in read_records(out_dir)}


def done_indices(out_dir: str | Path) -> set[int]:
    return {i for i, r in latest_by_index(out_dir).items() if r.status in DONE}


def foreign_record(out_dir: str | Path, plan) -> str | None:
    """The first record in ``out_dir`` that ``plan`` did not make (its index not among the plan's probes, or the
    probe at that index elsewhere), said in words; None when every record fits the plan. A run of one plan resumes by
    index, so another plan's records would count as its own."""
    probes = {p.index: p for p in plan.probes}
    for i, r in sorted(latest_by_index(out_dir).items()):
        p = probes.get(i)
        if p is None:
            return f"probe {i}, which the plan does not have"
        ry, py = r.y_m or 0.0, p.y_m or 0.0
        if abs(r.x_m - p.x_m) > 1e-9 or abs(ry - py) > 1e-9:
            return f"probe {i} at x {r.x_m:.4f} m, y {ry:.4f} m where the plan has x {p.x_m:.4f} m, y {py:.4f} m"
        if r.depth_planned_m is not None and abs(r.depth_planned_m - p.depth_m) > 1e-9:
            return f"probe {i} planned {r.depth_planned_m:.4f} m deep where the plan has {p.depth_m:.4f} m"
    return None


def read_measurements(out_dir: str | Path, statuses=MEASURED) -> list[ProbeRecord]:
    """For the localizer: the latest record per probe index with a usable, plausible measurement, sorted by (x_m, y_m)."""
    recs = [r for r in latest_by_index(out_dir).values() if r.status in statuses and r.implausible is None]
    return sorted(recs, key=lambda r: (r.x_m, r.y_m))


def load_raw(out_dir: str | Path, record: ProbeRecord) -> dict:
    with np.load(Path(out_dir) / record.raw_file) as z:
        return {k: z[k] for k in z.files}


def summarise(p, raw: dict, status: ProbeStatus, contact: dict, t0: float, t1: float, contact_thr: float,
              noise_std: float, depth_limit_m: float) -> ProbeRecord:
    """The summary line of one probe (SI units in the key names) from its raw arrays."""
    ph, f = raw["phase"], raw["force_n"]
    sel = ph == DWELL
    if not sel.any():  # stopped at the force limit (or cut short): the last filter window of the descent
        idx = np.flatnonzero(ph == DESCENT)[-5:]
        sel = np.zeros(len(ph), bool)
        sel[idx] = True
    fin = sel & np.isfinite(f)
    active = ((ph == DESCENT) | (ph == DWELL)) & np.isfinite(f)
    # free-air baseline: the descent's readings while the tip is still >= BASELINE_CLEARANCE_M above the surface
    # (above the nominal surface and above where contact was first felt). It measures what the sensor reads at
    # zero force right now -- the zeroing's own noise error and the drift since -- from thousands of samples.
    # The first BASELINE_SETTLE_S of the descent are left out: the tool accelerating is an inertial force too.
    # Contact is noticed only once the force passes the threshold (about 1 mm into tissue): stay 2 mm behind that.
    top = min(-BASELINE_CLEARANCE_M, (contact.get("depth") if contact.get("depth") is not None else 0.0)
              - 2 * BASELINE_CLEARANCE_M)
    desc = ph == DESCENT
    t_start = raw["time_s"][desc][0] if desc.any() else 0.0
    base = desc & np.isfinite(f) & (raw["depth_m"] <= top) & (raw["time_s"] >= t_start + BASELINE_SETTLE_S)
    n_base = int(base.sum())

    def num(v):
        return None if v is None or not math.isfinite(v) else float(v)
    has_base = n_base >= MIN_BASELINE_SAMPLES
    # the zero-force reading at the first contact: the baseline's straight line in time taken to the contact (the
    # drift since the zeroing is in the reading the contact threshold was compared with: 2.4 mN at 0.4 mN/s)
    at_contact = None
    if has_base and contact.get("t") is not None:
        tb = raw["time_s"][base]
        slope, icpt = np.polyfit(tb - tb.mean(), f[base], 1)
        at_contact = float(icpt + slope * (contact["t"] - tb.mean()))
    dwell = np.flatnonzero((ph == DWELL) & np.isfinite(f))
    fifth = len(dwell) // 5
    rec = ProbeRecord(
        index=p.index, x_m=p.x_m, y_m=p.y_m, status=status, depth_planned_m=p.depth_m,
        depth_target_m=min(p.depth_m, depth_limit_m),
        depth_reached_m=num(float(np.mean(raw["depth_m"][sel]))) if sel.any() else None,
        contact_x_m=num(float(np.mean(raw["x_m"][sel]))) if sel.any() else None,
        contact_y_m=num(float(np.mean(raw["y_m"][sel]))) if sel.any() and "y_m" in raw else None,
        contact_depth_m=num(contact.get("depth")),
        force_mean_n=num(float(np.mean(f[fin]))) if fin.any() else None,
        force_std_n=num(float(np.std(f[fin]))) if fin.any() else None,
        force_peak_n=num(float(np.max(f[active]))) if active.any() else None,
        force_dwell_start_n=num(float(np.mean(f[dwell[:fifth]]))) if fifth >= 10 else None,
        force_dwell_end_n=num(float(np.mean(f[dwell[-fifth:]]))) if fifth >= 10 else None,
        force_baseline_n=num(float(np.mean(f[base]))) if has_base else None,
        force_baseline_std_n=num(float(np.std(f[base]))) if has_base else None,
        n_samples_baseline=n_base,
        force_baseline_at_contact_n=num(at_contact),
        baseline_to_dwell_s=(num(float(np.mean(raw["time_s"][fin]) - np.mean(raw["time_s"][base])))
                             if has_base and fin.any() else None),
        force_predicted_prior_n=p.predicted_force_n, n_samples=int(fin.sum()), n_samples_total=int(len(ph)),
        contact_threshold_n=num(contact_thr), noise_std_n=num(noise_std), t_s=num(t0), duration_s=num(t1 - t0),
        wall_time_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    rec.implausible = implausibility(rec)
    return rec


def implausibility(rec: ProbeRecord) -> str | None:
    """Why a probe's force cannot be tissue pushing back (None: plausible). The force relative to the free-air
    baseline (else to the zeroing) against the prior's prediction scaled to the indentation reached (Hertz-like,
    d^1.5), outside PLAUSIBLE_FORCE_RATIO by more than PLAUSIBLE_SIGMAS of the probe's own noise."""
    if rec.status not in MEASURED or rec.force_mean_n is None:
        return None
    pred, d, d_plan = rec.force_predicted_prior_n, rec.depth_reached_m, rec.depth_planned_m
    if not pred or pred <= 0 or not d or d <= 0 or not d_plan or d_plan <= 0:
        return None
    f = rec.force_mean_n - (rec.force_baseline_n or 0.0)
    std = rec.force_std_n or rec.noise_std_n or 0.0
    var = std ** 2 / max(rec.n_samples, 1)
    if rec.force_baseline_n is not None:
        var += (rec.force_baseline_std_n or std) ** 2 / max(rec.n_samples_baseline, 1)
    sigma = math.sqrt(var)
    # Where contact was felt bounds the true indentation (the registered surface may be off by millimetres,
    # issue 14): felt below the nominal surface, the tissue was indented at least d - contact_depth_m; felt above it,
    # up to d - contact_depth_m. The low check takes the smallest indentation, the high check the largest.
    c = rec.contact_depth_m
    d_low = d - c if c is not None and 0 < c < d else d
    d_high = d - c if c is not None and c < 0 else d
    expect = pred * (d_low / d_plan) ** 1.5
    lo, hi = PLAUSIBLE_FORCE_RATIO
    if f < lo * expect - PLAUSIBLE_SIGMAS * sigma:
        # no contact felt and no force either way: the tissue is not where the prior says (a force well below zero
        # is no tissue's)
        air = c is None and f > -PLAUSIBLE_SIGMAS * sigma
        why = ("no contact was felt: no tissue here, or lower or far softer than the prior says (or a sensor "
               "offset, sign or the wrong sensor?)" if air else "not tissue (sensor offset, sign or the wrong "
               "sensor?)")
        return (f"force {f:.4g} N at {d_low * 1e3:.2f} mm of indentation is below {lo:g} x the prior's "
                f"{expect:.4g} N by more than {PLAUSIBLE_SIGMAS:g} sigma ({sigma:.2g} N): {why}")
    expect = pred * (d_high / d_plan) ** 1.5
    if f > hi * expect + PLAUSIBLE_SIGMAS * sigma:
        return (f"force {f:.4g} N at {d * 1e3:.2f} mm is above {hi:g} x the prior's {expect:.4g} N by more than "
                f"{PLAUSIBLE_SIGMAS:g} sigma ({sigma:.2g} N): not tissue (collision, sensor spike?)")
    return None


def move_aside(out_dir: str | Path, keep=()) -> Path | None:
    """Move everything in ``out_dir`` (except earlier previous-* folders and the files ``keep`` names: the command's
    own inputs, a scene or plan file kept there) into ``out_dir/previous-<UTC time>/`` and return that folder; None
    when there is nothing to move. Measured data are never deleted."""
    out = Path(out_dir)
    kept = {Path(k).resolve() for k in keep if k is not None and Path(k).exists()}

    def moves(p: Path) -> bool:
        return not p.name.startswith("previous-") and p.resolve() not in kept
    if not out.is_dir() or not any(moves(p) for p in out.iterdir()):
        return None
    dest = out / f"previous-{datetime.now(timezone.utc).strftime('%Y%m%dT%H%M%S.%fZ')}"
    dest.mkdir()
    for p in sorted(out.iterdir()):
        if p != dest and moves(p):
            p.rename(dest / p.name)
    _fsync_dir(out)
    return dest
