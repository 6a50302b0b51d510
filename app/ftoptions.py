"""The force-source options shared by ``palpate run``, ``palpate-cell`` and ``palpate ft`` (issue 18), and the force
source they build (robot.forcesource).

``--ft rtde`` (default): the UR's wrist sensor over ur_rtde. ``--ft netft:HOST``: an ATI Net F/T box at HOST (a
real arm, ``--host``); ``--ft netft``: the simulated box on loopback (with ``--sim``: in memory, stepped with the
arm, or served by the simulated controller). A real box needs its mounting (``--ft-sensor-pose``) and rated range
(``--ft-range-n``, ``--ft-range-nm``): there is no safe default for either; its calibration is read from the box's
netftapi2.xml unless ``--ft-counts-per-force`` and ``--ft-counts-per-torque`` are given.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass

from app.errors import UsageError
from app.options import int_range, positive_float
from core.contracts import SENSORS
from robot.forcesource import Mount, NetFtForce, RtdeForce
from robot.netft import NetFtCalibration, NetFtConfig, fetch_calibration
from robot.rdt import RDT_PORT
from robot.simnetft import SIM_CALIBRATION, SIM_SENSOR_POSE_FLANGE, attach_box

# the simulated controller's box lives in a process a busy machine can hold up (its records then stop, unlike a real
# box's, which the host's kernel keeps): the margin the driver gives its RTDE data for the same reason
# (DriverConfig.stale_periods, 0.2 s) instead of a real box's 50 ms
SIM_CONTROLLER_STALE_S = 0.2
SIM_RANGE_NM = 0.25             # the simulated box's torque range (an ATI Nano17 SI-25-0.25's); its force range is
                                # the --sensor preset's range_n


@dataclass(frozen=True)
class FtChoice:
    kind: str                   # "rtde" or "netft"
    host: str | None = None     # a real Net F/T box's address; None: the simulated one

    @property
    def text(self) -> str:
        return self.kind + (f":{self.host}" if self.host else "")


def ft_choice(s: str) -> FtChoice:
    """argparse type of --ft: rtde | netft | netft:HOST."""
    kind, sep, host = str(s).partition(":")
    if kind == "rtde" and not sep:
        return FtChoice("rtde")
    if kind == "netft" and (not sep or host.strip()):
        return FtChoice("netft", host.strip() or None)
    raise argparse.ArgumentTypeError(f"must be rtde (the UR's wrist sensor), netft:HOST (an ATI Net F/T box at HOST) "
                                     f"or netft (a simulated box), got {s!r}")


def pose6(s: str) -> tuple:
    """argparse type of a pose: x,y,z,rx,ry,rz (m, rad), six finite numbers."""
    try:
        v = tuple(float(a) for a in str(s).split(","))
    except ValueError:
        v = ()
    if len(v) != 6 or not all(math.isfinite(a) for a in v) or math.dist(v[:3], (0, 0, 0)) > 0.3:
        raise argparse.ArgumentTypeError(f"must be x,y,z,rx,ry,rz: six finite numbers (m, rad), within 0.3 m of the "
                                         f"flange, got {s!r}")
    turn = math.dist(v[3:], (0, 0, 0))
    if turn > math.pi + 1e-9:       # (a rotation vector's length is its angle: every rotation has one of at most pi;
        #                             degrees typed -- 90, 180 -- misread the force: 180 read 0.6 N per newton)
        raise argparse.ArgumentTypeError(f"rx,ry,rz is a rotation vector in radians, at most pi ({math.pi:.4f}) long; "
                                         f"got {turn:g} ({s!r}): degrees? ({turn:g} degrees is "
                                         f"{math.radians(turn):.4f} rad)")
    return v


def add_ft_options(p, *, sim_help: str = "with --sim") -> None:
    g = p.add_argument_group("force sensor (--ft)")
    g.add_argument("--ft", type=ft_choice, default=FtChoice("rtde"), metavar="rtde|netft[:HOST]",
                   help="where the force comes from: rtde (the UR's wrist sensor, default), netft:HOST (an ATI Net "
                        f"F/T box at HOST, UDP port {RDT_PORT}) or netft (the simulated box, {sim_help})")
    g.add_argument("--ft-sensor-pose", type=pose6, metavar="X,Y,Z,RX,RY,RZ",
                   help="the Net F/T sensor's frame on the flange (m, rad; from the mounting drawing); needed for a "
                        "real box; default for the simulated one " + ",".join(f"{v:g}" for v in SIM_SENSOR_POSE_FLANGE))
    g.add_argument("--ft-range-n", type=positive_float, metavar="N",
                   help="the sensor's rated force range per axis (N; a reading there is saturated); needed for a real "
                        "box; the simulated one's is the --sensor preset's")
    g.add_argument("--ft-range-nm", type=positive_float, metavar="NM",
                   help=f"its rated torque range per axis (N m); needed for a real box (simulated: {SIM_RANGE_NM:g})")
    g.add_argument("--ft-port", type=int_range(1, 65535), metavar="PORT",
                   help=f"a real box's RDT port (default {RDT_PORT}, ATI's)")
    g.add_argument("--ft-counts-per-force", type=positive_float, metavar="COUNTS",
                   help="the box's counts per N (default: read from http://HOST/netftapi2.xml)")
    g.add_argument("--ft-counts-per-torque", type=positive_float, metavar="COUNTS",
                   help="the box's counts per N m (default: read from the box with the counts per N)")


FT_DETAIL = ("ft_sensor_pose", "ft_range_n", "ft_range_nm", "ft_port", "ft_counts_per_force", "ft_counts_per_torque")


def _opt(name: str) -> str:
    return "--" + name.replace("_", "-")


def check_ft(args, *, sim: bool, real_host: bool) -> None:
    """Cross-option rules, before anything is touched or moves (UsageError naming the option); a real box's
    calibration is read here (``args.ft_config``)."""
    args.ft_config = None
    ft: FtChoice = args.ft
    given = [n for n in FT_DETAIL if getattr(args, n, None) is not None]
    if ft.kind == "rtde":
        if given:
            raise UsageError(f"{_opt(given[0])}: an option of the Net F/T sensor; give --ft netft:HOST (or --ft netft "
                             f"with --sim) too")
        return
    if sim and ft.host:
        raise UsageError(f"--ft {ft.text}: with a simulated arm the Net F/T box is simulated too: give --ft netft")
    if not sim and not ft.host:
        raise UsageError("--ft netft: the simulated Net F/T box needs --sim; for a real box give --ft netft:HOST")
    if ft.host:
        if not real_host:
            raise UsageError(f"--ft {ft.text}: a real Net F/T box needs a real arm (--host IP)")
        for name in ("ft_sensor_pose", "ft_range_n", "ft_range_nm"):
            if getattr(args, name) is None:
                raise UsageError(f"--ft {ft.text} needs {_opt(name)} (no safe default: "
                                 + ("the sensor's frame on the flange, m and rad, from the mounting drawing)"
                                    if name == "ft_sensor_pose" else "the rated range of its calibration sheet)"))
    else:
        extra = [n for n in given if n != "ft_sensor_pose"]
        if extra:
            raise UsageError(f"{_opt(extra[0])}: the simulated box's range, port and calibration are its own "
                             f"(--sensor preset); only --ft-sensor-pose applies to it")
    cpf, cpt = getattr(args, "ft_counts_per_force", None), getattr(args, "ft_counts_per_torque", None)
    if (cpf is None) != (cpt is None):
        raise UsageError(f"{'--ft-counts-per-force' if cpf is not None else '--ft-counts-per-torque'}: give both "
                         f"--ft-counts-per-force and --ft-counts-per-torque, or neither (read from the box)")
    if ft.host:
        args.ft_config = real_config(args)


def sensor_pose(args) -> tuple:
    return tuple(args.ft_sensor_pose) if args.ft_sensor_pose is not None else SIM_SENSOR_POSE_FLANGE


def real_config(args) -> NetFtConfig:
    """A real box's configuration; its calibration read from the box unless given (UsageError if it cannot be)."""
    host = args.ft.host
    if args.ft_counts_per_force is not None:
        cal = NetFtCalibration(args.ft_counts_per_force, args.ft_counts_per_torque)
    else:
        try:
            cal = fetch_calibration(host)
        except (OSError, ValueError) as e:
            raise UsageError(f"--ft {args.ft.text}: cannot read the calibration from http://{host}/netftapi2.xml "
                             f"({e}); give --ft-counts-per-force and --ft-counts-per-torque from its calibration "
                             f"sheet") from None
    return NetFtConfig(host=host, port=args.ft_port or RDT_PORT, calibration=cal, range_n=args.ft_range_n,
                       range_nm=args.ft_range_nm)


def sim_config(host: str, port: int, sensor: str, **kw) -> NetFtConfig:
    """The simulated box's configuration (a noiseless preset repeats itself: not a stuck box there)."""
    if SENSORS[sensor].noise_std_n == 0:
        kw.setdefault("max_identical", 0)
    return NetFtConfig(host=host, port=port, calibration=SIM_CALIBRATION, range_n=SENSORS[sensor].range_n,
                       range_nm=SIM_RANGE_NM, **kw)


def inmemory_source(args, arm, c, tcp_offset, faults=(), **cfg_kw) -> tuple[NetFtForce, object]:
    """A simulated box stepped with the in-memory ``arm`` and the force source reading it: staleness on the clock the
    driver paces with (``c.initPeriod()``: simulated time), the first record awaited by letting controller periods
    pass. ``args``: ``sensor``, ``seed``, ``ft_sensor_pose``; ``cfg_kw``: NetFtConfig fields. (source, box)."""
    box = attach_box(arm, faults=faults, host="127.0.0.1", port=0, sensor=args.sensor, seed=args.seed,
                     sensor_pose_flange=sensor_pose(args))
    fs = NetFtForce(sim_config("127.0.0.1", box.address[1], args.sensor, **cfg_kw),
                    Mount(sensor_pose(args), tuple(tcp_offset)),
                    clock=lambda: c.initPeriod().total_seconds(), wait=lambda: c.waitPeriod(c.initPeriod()))
    return fs, box


def linked_source(args, c, r, tcp_offset, host: str | None = None):
    """The force source for a ur_rtde link: the wrist sensor, a real box (``args.ft.host``) or the simulated
    controller's box at ``host`` (its loopback address). ``args`` None: the wrist sensor."""
    if args is None or args.ft.kind == "rtde":
        return RtdeForce(c, r)
    cfg = args.ft_config if args.ft.host else sim_config(host, RDT_PORT, args.sensor,
                                                         stale_s=SIM_CONTROLLER_STALE_S)
    return NetFtForce(cfg, Mount(sensor_pose(args), tuple(tcp_offset)))


def controller_pose(args):
    """The simulated controller's Net F/T mounting (None: no box)."""
    return list(sensor_pose(args)) if args is not None and args.ft.kind == "netft" else None
