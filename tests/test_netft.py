"""The external force source (issue 18): the RDT wire format, the Net F/T reader's checks, the frame transform, and
the driver probing with the simulated Net F/T box on loopback -- sensor faults end safe with the records kept."""
from __future__ import annotations

import json
import math
import socket
import sys
import threading
from http.server import BaseHTTPRequestHandler, HTTPServer
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from robot_fixtures import TCP, make_plan, make_sim  # noqa: E402
from test_driver_faults import DEPTH, XS, at_probe, check_safe_end  # noqa: E402

from app.ftoptions import inmemory_source, sim_config  # noqa: E402
from core import ur5e  # noqa: E402
from robot.driver import DriverConfig, run_plan  # noqa: E402
from robot.forcesource import Mount, NetFtForce, sensor_to_base  # noqa: E402
from robot.netft import NetFtCalibration, NetFtConfig, NetFtReader, SensorFault, fetch_calibration  # noqa: E402
from robot.rdt import (  # noqa: E402
    CMD_START_REALTIME,
    RdtRecord,
    pack_record,
    pack_request,
    seq_ahead,
    unpack_records,
    unpack_request,
)
from robot.simfaults import parse  # noqa: E402
from robot.simforce import standin_force_model  # noqa: E402
from robot.simnetft import SIM_SENSOR_POSE_FLANGE, attach_box  # noqa: E402

CAL = NetFtCalibration(counts_per_force=1e6, counts_per_torque=2e6)


def test_wire_round_trip_and_sequence_arithmetic():
    recs = [RdtRecord(2**32 - 1, 7, 0, (1, -2, 3, -4, 5, -6)), RdtRecord(0, 8, 0x20, (0, 0, -1_000_000, 0, 0, 0))]
    data = b"".join(pack_record(r) for r in recs)
    assert len(data) == 72 and unpack_records(data) == recs
    with pytest.raises(ValueError, match="36-byte"):
        unpack_records(data[:-1])
    assert unpack_request(pack_request(CMD_START_REALTIME)) == (CMD_START_REALTIME, 0)
    assert unpack_request(b"\x12\x35" + pack_request(2)[2:]) is None          # wrong header
    assert seq_ahead(0, 2**32 - 1) == 1 and seq_ahead(5, 2) == 3 and seq_ahead(2, 5) == -3 and seq_ahead(4, 4) == 0


def test_calibration_from_the_box_page():
    page = "<netft><cfgcpf>1000000</cfgcpf><cfgcpt>1000</cfgcpt><cfgfu>N</cfgfu><cfgtu>Nm</cfgtu></netft>"
    assert NetFtCalibration.from_xml(page) == NetFtCalibration(1e6, 1e3)
    with pytest.raises(ValueError, match="cfgfu.*lbf"):
        NetFtCalibration.from_xml(page.replace("<cfgfu>N<", "<cfgfu>lbf<"))
    with pytest.raises(ValueError, match="counts_per_force"):
        NetFtCalibration.from_xml(page.replace("1000000", "0"))


def test_calibration_fetched_over_http():
    page = b"<?xml version='1.0'?><netft><cfgcpf>1000000</cfgcpf><cfgcpt>1000</cfgcpt><cfgfu>N</cfgfu>" \
           b"<cfgtu>Nm</cfgtu></netft>"

    class Page(BaseHTTPRequestHandler):
        def do_GET(self):
            ok = self.path == "/netftapi2.xml"
            self.send_response(200 if ok else 404)
            self.end_headers()
            self.wfile.write(page if ok else b"")

        def log_message(self, *a):
            pass
    srv = HTTPServer(("127.0.0.1", 0), Page)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        assert fetch_calibration("127.0.0.1", port=srv.server_address[1]) == NetFtCalibration(1e6, 1e3)
    finally:
        srv.shutdown()
        srv.server_close()


class ScriptedBox:
    """A UDP peer on loopback that answers a start request with the records a test gives it."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(2.0)
        self.client = None

    def cfg(self, **kw) -> NetFtConfig:
        kw.setdefault("max_identical", 0)            # its records are noiseless
        return NetFtConfig(host="127.0.0.1", port=self.sock.getsockname()[1], calibration=CAL, **kw)

    def send(self, seq, counts=(0, 0, 0, 0, 0, 0), status=0):
        if self.client is None:
            data, self.client = self.sock.recvfrom(64)
            assert unpack_request(data) == (CMD_START_REALTIME, 0)
        self.sock.sendto(pack_record(RdtRecord(seq, seq, status, tuple(counts))), self.client)


@pytest.fixture
def box():
    b = ScriptedBox()
    yield b
    b.sock.close()


def started(box, clock=None, **kw) -> NetFtReader:
    reader = NetFtReader(box.cfg(**kw), **({"clock": clock} if clock else {}))
    reader.wait = lambda: box.send(1) if box.client is None else None     # the first record, once asked
    reader.start()
    return reader


def test_reader_scales_counts_and_counts_lost_and_reordered_records(box):
    r = started(box)
    box.send(2, (250_000, -500_000, 1_000_000, 2_000, -4_000, 6_000))
    assert np.allclose(r.latest(), [0.25, -0.5, 1.0, 0.001, -0.002, 0.003])
    box.send(5, (0, 0, 3_000_000, 0, 0, 0))       # 3 and 4 lost
    box.send(4, (0, 0, 9_000_000, 0, 0, 0))       # arrives late: dropped
    assert r.latest()[2] == pytest.approx(3.0)
    assert (r.n_lost, r.n_reordered, r.count) == (2, 1, 3)
    mean, n = r.mean(1.0)
    assert n == 3 and mean[2] == pytest.approx((1.0 + 3.0) / 3)
    r.stop()


@pytest.mark.parametrize("record, kind", [
    (dict(status=0x8001), "sensor_status"),
    (dict(counts=(0, 0, -35_000_000, 0, 0, 0)), "sensor_saturated"),      # at the 35 N range
])
def test_reader_refuses_status_and_saturation(box, record, kind):
    r = started(box, range_n=35.0)
    box.send(2, **record)
    with pytest.raises(SensorFault) as e:
        r.latest()
    assert e.value.kind == kind
    r.stop()


def test_reader_refuses_a_box_that_stopped_sampling(box):
    """Fresh RDT records, changing counts, but the box's own F/T sample counter stuck: frozen after 5 records."""
    r = started(box, max_identical=5)
    with pytest.raises(SensorFault) as e:
        for seq in range(2, 8):
            box.sock.sendto(pack_record(RdtRecord(seq, 1, 0, (seq, 0, 0, 0, 0, 0))), box.client)
            r.poll()
    assert e.value.kind == "sensor_frozen" and seq == 6
    r.stop()


def test_reader_stale_and_packet_loss(box):
    now = [0.0]
    r = started(box, clock=lambda: now[0], stale_s=0.05, loss_window=200, max_lost_fraction=0.5)
    now[0] = 0.049
    r.latest()                                     # 49 ms without a record: still fresh
    now[0] = 0.051
    with pytest.raises(SensorFault, match="no new Net F/T record") as e:
        r.latest()
    assert e.value.kind == "sensor_lost"
    seq = 1
    with pytest.raises(SensorFault) as e:          # every other record lost: 50 %, then more
        for _ in range(150):
            seq += 2 if seq < 200 else 3
            box.send(seq)
            r.poll()
    assert e.value.kind == "sensor_packet_loss" and seq > 200
    r.stop()
    with pytest.raises(SensorFault, match="not streaming"):
        r.poll()


def test_reader_resynchronises_after_the_host_was_away(box):
    """Between runs the host does not read: the socket fills with old records and the kernel drops the newer ones.
    That is no network loss: the reader discards what it holds and waits for a fresh record."""
    now = [0.0]
    r = started(box, clock=lambda: now[0], loss_window=200)
    for seq in range(2, 40):                       # what the socket holds when the host comes back...
        box.send(seq, (0, 0, 1_000_000, 0, 0, 0))
    fresh = iter(range(5000, 5100))                # ... and, after the kernel dropped thousands, fresh ones
    r.wait = lambda: box.send(next(fresh), (0, 0, 2_000_000, 0, 0, 0))
    now[0] = 5.0
    assert r.latest()[2] == pytest.approx(2.0)     # the fresh record, not the old ones
    assert r.resyncs == 1 and r.n_lost == 0
    for seq in range(5001, 5003):
        box.send(seq, (0, 0, 3_000_000, 0, 0, 0))
    now[0] = 5.002
    assert r.latest()[2] == pytest.approx(3.0) and r.resyncs == 1
    r.stop()


def test_no_box_is_a_sensor_fault():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()                                      # nothing listens there now
    cfg = NetFtConfig(host="127.0.0.1", port=port, calibration=CAL, start_timeout_s=0.2)
    with pytest.raises(SensorFault) as e:
        NetFtReader(cfg).start()
    assert e.value.kind == "sensor_lost"


def test_frame_transform_undoes_the_mounting():
    """The simulated box computes its reading from the flange and the tip; the force source goes back through the
    TCP: the base-frame force must come back, with no torque about the TCP (the tip)."""
    arm, c, r = make_sim(sensor="ideal")
    box = attach_box(arm, host="127.0.0.1", port=0, sensor="ideal")
    tilt = ur5e.T_to_pose(ur5e.pose_to_T(arm.tcp_pose) @ ur5e.pose_to_T([0, 0, 0, 0.3, -0.2, 0.1]))
    arm.T_tcp = ur5e.pose_to_T(tilt)                            # any orientation
    f_base = np.array([0.3, -1.2, 2.0])
    arm.true_wrench = lambda: np.concatenate([f_base, np.zeros(3)])
    w_s = box.wrench_sensor(0.0)
    assert not np.allclose(w_s[:3], f_base, atol=0.1)          # the mounting does turn it
    w = sensor_to_base(w_s, arm.tcp_pose, Mount(SIM_SENSOR_POSE_FLANGE, tuple(TCP)).tcp_sensor())
    assert np.allclose(w[:3], f_base, atol=1e-9) and np.allclose(w[3:], 0.0, atol=1e-9)
    box.close()



def test_the_box_reads_the_truths_sensor_bias_and_drift():
    """A truth condition's sensor bias and drift (robot.truth: along the tissue normal) are in the external box's
    readings too, not only the wrist sensor's (session 38: with --ft netft they were dropped): an ideal box on a
    tilted tool reads, back in the base frame, bias + drift t along the normal, and its torque channels are
    unchanged (a force channel's error)."""
    arm, c, r = make_sim(sensor="ideal")
    box = attach_box(arm, host="127.0.0.1", port=0, sensor="ideal")
    arm.T_tcp = ur5e.pose_to_T(ur5e.T_to_pose(ur5e.pose_to_T(arm.tcp_pose) @ ur5e.pose_to_T([0, 0, 0, 0.2, 0.1, 0])))
    f_base = np.array([0.1, 0.0, 0.5])
    arm.true_wrench = lambda: np.concatenate([f_base, np.zeros(3)])
    mount = Mount(SIM_SENSOR_POSE_FLANGE, tuple(TCP)).tcp_sensor()
    clean_s = box.wrench_sensor(10.0)
    clean = sensor_to_base(clean_s, arm.tcp_pose, mount)
    arm.normal_bias_n, arm.normal_drift_n_per_s = 0.02, 1e-3
    for t in (0.0, 10.0):
        w_s = box.wrench_sensor(t)
        w = sensor_to_base(w_s, arm.tcp_pose, mount)
        assert np.allclose(w[:3] - clean[:3], (0.02 + 1e-3 * t) * arm.n_base, atol=1e-9)
        assert np.allclose(w_s[3:], clean_s[3:], atol=1e-12)
    box.close()

def netft_sim(faults=(), max_identical=50, **arm_kw):
    """The in-memory arm with a simulated Net F/T box, and the driver's force source reading it (as app.cell and
    palpate run build them)."""
    arm, c, r = make_sim(**arm_kw)
    fs, box = inmemory_source(SimpleNamespace(sensor="nano17", seed=0, ft_sensor_pose=None), arm, c, TCP,
                              [parse(f) for f in faults], max_identical=max_identical)
    return arm, c, r, fs, box


def test_probing_with_the_net_ft_box_measures_what_the_wrist_sensor_does(tmp_path):
    arm, c, r, fs, box = netft_sim()
    rep = run_plan(make_plan(XS, depth_m=DEPTH), c, r, tmp_path / "netft", force_source=fs)
    fs.close()
    box.close()
    arm2, c2, r2 = make_sim()
    rep2 = run_plan(make_plan(XS, depth_m=DEPTH), c2, r2, tmp_path / "rtde")
    assert rep.status == rep2.status == "ok"
    for a, b in zip(rep.records, rep2.records):     # the same tissue, two sensors with independent noise
        assert a.force_mean_n > 0.1 and abs(a.force_mean_n - b.force_mean_n) < 0.02
        assert abs(a.contact_depth_m - b.contact_depth_m) < 2e-4
    run_json = json.loads((tmp_path / "netft" / "run.json").read_text())
    src = run_json["force_source"]
    assert src["source"] == "netft" and src["lost"] == 0 and src["zeros"] >= len(XS)
    assert src["records"] > 1000 and 20 <= src["zero_records"] <= 21     # 40 ms at 500 Hz
    assert json.loads((tmp_path / "rtde" / "run.json").read_text())["force_source"] == {"source": "rtde"}


@pytest.mark.parametrize("fault, kind", [
    ("ft-silent-at-depth-m=0.0015", "sensor_lost"),
    ("ft-status-at-depth-m=0.0015:4096", "sensor_status"),
    ("ft-spike-at-depth-m=0.0015:60", "sensor_saturated"),
    ("ft-loss-at-depth-m=0.0015:0.65", "sensor_packet_loss"),
    ("ft-freeze-at-depth-m=0.0015", "sensor_frozen"),    # 0.9 would as well be a silent box
])
def test_sensor_faults_end_safe_with_the_records_kept(tmp_path, fault, kind):
    """In the second probe's descent the box goes silent, reports a problem, saturates or loses most records: the
    driver stops, keeps the probe's samples, retracts out of the tissue (no force is needed to move away)."""
    f = parse(fault)
    arm, c, r, fs, box = netft_sim()
    # the trigger: the second probe at depth (the box's faults fire on the arm's state, like the arm's own)
    box.faults = [[f, at_probe(1, f.value), False]]
    rep = run_plan(make_plan(XS, depth_m=DEPTH), c, r, tmp_path, force_source=fs)
    recs = check_safe_end(rep, arm, tmp_path, kind)
    assert rep.fault["stopped"] is True
    assert math.isfinite(recs[-1].force_peak_n) and arm.max_contact_force_n < 2.0
    fs.close()
    box.close()


def test_the_wrist_sensor_backs_up_a_stuck_box(tmp_path):
    """A box that repeats itself unnoticed (its own check off) in very stiff tissue: the external force stays where
    it froze while the true one climbs; the wrist sensor, zeroed with it, ends the probe once it reads the limit
    + 5 N -- below the 10 N hard cap and before the controller's own 30 N protective stop."""
    arm, c, r, fs, box = netft_sim(["ft-freeze-at-depth-m=0.00005"], max_identical=0,
                                   force_model=standin_force_model(k_n_per_m15=1e6))
    rep = run_plan(make_plan(XS, depth_m=DEPTH), c, r, tmp_path, force_source=fs)
    assert rep.fault["kind"] == "sensor_disagrees" and rep.fault["stopped"] is True, rep.fault
    assert 7.0 < arm.max_contact_force_n < 10.0 and not arm.protective_stopped
    assert rep.records[-1].status == "fault" and rep.records[-1].force_peak_n < 1.0    # what the stuck box said
    fs.close()
    box.close()


def test_a_side_push_through_the_box_is_caught(tmp_path):
    """A push across the normal in the second probe's descent, through the external sensor: the box feels it (the
    simulator puts it on the tool since session 55's review: before, only the wrist sensor's reading had it, and
    with --ft netft it did nothing), the driver turns it into the base frame and stops: 3 N growing over the filter
    points the force far off the normal first (force_direction)."""
    arm, c, r, fs, box = netft_sim()
    arm.inject("side_push", when=at_probe(1, 0.0015), duration_s=0.2, magnitude_n=3.0)
    rep = run_plan(make_plan(XS, depth_m=DEPTH), c, r, tmp_path, force_source=fs)
    check_safe_end(rep, arm, tmp_path, "force_direction")
    assert "degrees from the tissue normal" in rep.fault["message"] and "--ft-sensor-pose" in rep.fault["message"]
    fs.close()
    box.close()


@pytest.mark.parametrize("turn_deg, lateral_limit_n, kind", [(20.0, None, None), (60.0, None, "force_direction"),
                                                             (90.0, math.inf, "force_direction")])
def test_a_sensor_pose_stated_turned_from_its_mounting(tmp_path, turn_deg, lateral_limit_n, kind):
    """The Net F/T's stated pose turned from its true mounting about the sensor's x: the force along the normal is
    read cos(turn) short and the rest across it. 60 degrees (read half: the force limit doubled; session 55's review:
    every probe ok) is the fault force_direction in probe 0's descent; so is 90 degrees (the axes swapped: nothing
    along the normal; the direction judged on the force's length, since the check's review), even with the lateral
    watch off; 20 degrees (read 6 % short) runs, its forces that much short."""
    arm, c, r = make_sim()
    box = attach_box(arm, faults=(), host="127.0.0.1", port=0, sensor="nano17", seed=0,
                     sensor_pose_flange=SIM_SENSOR_POSE_FLANGE)
    T = ur5e.pose_to_T(list(SIM_SENSOR_POSE_FLANGE))
    T[:3, :3] = T[:3, :3] @ ur5e.rotvec_to_matrix([math.radians(turn_deg), 0.0, 0.0])
    fs = NetFtForce(sim_config("127.0.0.1", box.address[1], "nano17"), Mount(tuple(ur5e.T_to_pose(T)), tuple(TCP)),
                    clock=lambda: c.initPeriod().total_seconds(), wait=lambda: c.waitPeriod(c.initPeriod()))
    try:
        rep = run_plan(make_plan(XS, depth_m=DEPTH), c, r, tmp_path, force_source=fs,
                       config=DriverConfig(lateral_force_limit_n=lateral_limit_n))
    finally:
        fs.close()
        box.close()
    if kind is None:
        assert rep.status == "ok" and rep.n_ok == len(XS)
        true = arm.max_contact_force_n
        assert 0.9 * true < max(x.force_mean_n for x in rep.records) < true
    else:
        assert rep.fault["kind"] == kind and rep.n_ok == 0 and rep.fault["stopped"], rep.fault
        assert arm.max_contact_force_n < 0.2            # stopped early in the descent
