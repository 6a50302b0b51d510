"""`palpate ft --ft netft:HOST [--duration-s S]`: read an ATI Net F/T box for a while and report what it sends.

The check of a cell's external sensor before the first run: records received and their rate, records lost or
reordered on the way, and the mean and spread of each axis in the SENSOR frame (unzeroed: what the box sends;
push the tip gently along the tool axis to see the sign and the axis). ``--ft netft`` reads a simulated box on
loopback instead (its sensor at rest, in free air: the numbers are its noise and bias). Nothing moves.
Exit 0 when the stream was healthy, 1 on a sensor fault (the line says which), 2 on bad input.
"""
from __future__ import annotations

import argparse
import sys
import threading
import time

import numpy as np

from app.commands.output import write_json
from app.errors import UsageError
from app.ftoptions import FtChoice, add_ft_options, real_config, sim_config
from app.options import check_output_file, float_range, int_range
from core.contracts import SENSORS
from robot.netft import NetFtReader, SensorFault
from robot.sim import ArmModel
from robot.simnetft import SIM_SENSOR_POSE_FLANGE, attach_box


def add_parser(sub) -> None:
    p = sub.add_parser("ft", help="read an ATI Net F/T box for a while: rate, lost records, mean and noise per axis",
                       description=__doc__.split("\n\n")[0],
                       epilog="examples:\n  palpate ft --ft netft:192.168.1.1 --ft-range-n 25 --ft-range-nm 0.25\n"
                              "  palpate ft --ft netft:192.168.1.1 --duration-s 5 --json ft.json\n"
                              "  palpate ft --ft netft            (a simulated box on loopback)",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    add_ft_options(p, sim_help="on loopback")
    p.add_argument("--netft", metavar="HOST", help="the box at HOST: the same as --ft netft:HOST")
    p.add_argument("--port", dest="ft_port", type=int_range(1, 65535), metavar="PORT",
                   help="the same as --ft-port (default 49152)")
    p.add_argument("--duration-s", "--seconds", type=float_range(0.1, 600.0, lo_open=False, unit="s"),
                   default=2.0, help="how long to read, 0.1-600 s (default 2 s; long enough to count the rate)")
    p.add_argument("--sensor", choices=list(SENSORS), help="the simulated box's sensor preset (default nano17)")
    p.add_argument("--seed", type=int_range(0, 2 ** 32 - 1), help="the simulated box's noise seed (default 0)")
    p.add_argument("--json", metavar="PATH", help="also write the report here ('-': standard output)")
    p.set_defaults(func=run)


def _check(args) -> None:
    if args.netft is not None:
        host = args.netft.strip()
        if not host:
            raise UsageError("--netft: give the box's host name or address, e.g. --netft 192.168.1.1")
        if args.ft.kind != "rtde" and args.ft.host != host:
            raise UsageError(f"--netft {host} and --ft {args.ft.text}: give one of them")
        args.ft = FtChoice("netft", host)
    ft: FtChoice = args.ft
    if ft.kind != "netft":
        raise UsageError(f"--ft {ft.text}: palpate ft reads a Net F/T box: give --ft netft:HOST (or --ft netft for "
                         f"the simulated one)")
    if not ft.host:
        for name in ("ft_sensor_pose", "ft_range_n", "ft_range_nm", "ft_port", "ft_counts_per_force",
                     "ft_counts_per_torque"):
            if getattr(args, name) is not None:
                raise UsageError(f"--{name.replace('_', '-')}: the simulated box's settings are its own")
        args.sensor = args.sensor or "nano17"
        args.seed = 0 if args.seed is None else args.seed
    elif args.sensor is not None or args.seed is not None:      # a real box's noise is its own
        flag = f"--sensor {args.sensor}" if args.sensor is not None else f"--seed {args.seed}"
        raise UsageError(f"{flag}: only for the simulated box (--ft netft); a real box at {ft.host} is read as it is")
    elif args.ft_sensor_pose is not None:
        raise UsageError("--ft-sensor-pose: palpate ft reports the sensor frame; the mounting is not used here")
    if (args.ft_counts_per_force is None) != (args.ft_counts_per_torque is None):
        raise UsageError("--ft-counts-per-force / --ft-counts-per-torque: give both or neither (read from the box)")


# The simulated box here is a thread of this process stepped on the wall clock: on a loaded machine it may not run
# for tens of ms (3 runs in 30 read "no new record for more than 0.05 s" under a load of 3 on two cores), which a
# real box's 0.05 s would call a lost sensor. Its reader waits this long instead (a real box keeps 0.05 s).
SIM_STALE_S = 0.5


def _simulated_box(args, stop: threading.Event):
    """A simulated box on loopback over an arm at rest in free air, stepped in real time (2 records per 2 ms)."""
    arm = ArmModel(None, sensor="ideal")
    box = attach_box(arm, host="127.0.0.1", port=0, sensor=args.sensor, seed=args.seed,
                     sensor_pose_flange=SIM_SENSOR_POSE_FLANGE, records_per_step=2)

    def tick():
        t_next = time.perf_counter()
        while not stop.is_set():
            arm.step()
            t_next += arm.period_s
            time.sleep(max(0.0, t_next - time.perf_counter()))
    threading.Thread(target=tick, daemon=True, name="sim-netft").start()
    return box


def run(args) -> int:
    _check(args)
    check_output_file(args.json, "--json")
    stop = threading.Event()
    box = None
    if args.ft.host:
        if args.ft_range_n is None or args.ft_range_nm is None:
            args.ft_range_n = args.ft_range_n or float("inf")
            args.ft_range_nm = args.ft_range_nm or float("inf")
            print("palpate ft: saturation not checked (give --ft-range-n and --ft-range-nm to check it)",
                  file=sys.stderr)
        cfg = real_config(args)
    else:
        box = _simulated_box(args, stop)
        cfg = sim_config("127.0.0.1", box.address[1], args.sensor, stale_s=SIM_STALE_S)
    reader = NetFtReader(cfg)
    rows, fault = [], None
    t0 = time.monotonic()
    try:
        reader.start()
        seen = reader.count - 1
        while time.monotonic() - t0 < args.duration_s:
            reader.latest()
            n = reader.count
            rows += [reader.ft[i % cfg.buffer_len].copy() for i in range(max(seen, n - cfg.buffer_len), n)]
            seen = n
            time.sleep(0.002)
    except SensorFault as e:
        fault = {"kind": e.kind, "message": e.message}
    finally:
        elapsed = time.monotonic() - t0
        reader.stop()
        stop.set()
        if box is not None:
            box.close()
    a = np.array(rows).reshape(-1, 6)
    rep = {"host": cfg.host, "port": cfg.port, "simulated": box is not None, "duration_s": round(elapsed, 3),
           "rate_hz": round(len(a) / elapsed, 1) if elapsed > 0 else None, **reader.report(),
           "counts_per_force": cfg.calibration.counts_per_force, "counts_per_torque": cfg.calibration.counts_per_torque,
           "force_mean_n": a[:, :3].mean(axis=0).tolist() if len(a) else None,
           "force_std_n": a[:, :3].std(axis=0).tolist() if len(a) else None,
           "torque_mean_nm": a[:, 3:].mean(axis=0).tolist() if len(a) else None,
           "torque_std_nm": a[:, 3:].std(axis=0).tolist() if len(a) else None, "fault": fault}
    out = sys.stderr if args.json == "-" else sys.stdout
    print(f"Net F/T at {cfg.host}:{cfg.port}{' (simulated)' if box else ''}: {rep['records']} records in "
          f"{elapsed:.2f} s ({rep['rate_hz']} Hz), {rep['lost']} lost, {rep['reordered']} reordered", file=out)
    if len(a):
        fm, fs = np.array(rep["force_mean_n"]), np.array(rep["force_std_n"])
        print("  force  (sensor frame) mean " + " ".join(f"{v:+.4f}" for v in fm) + " N, std "
              + " ".join(f"{v:.4f}" for v in fs) + " N", file=out)
        print("  torque (sensor frame) mean " + " ".join(f"{v:+.5f}" for v in rep["torque_mean_nm"]) + " N m, std "
              + " ".join(f"{v:.5f}" for v in rep["torque_std_nm"]) + " N m", file=out)
    if fault:
        print(f"FAULT {fault['kind']}: {fault['message']}", file=out)
    write_json(args.json, rep)
    return 1 if fault else 0
