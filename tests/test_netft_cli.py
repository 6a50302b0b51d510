"""`--ft` on palpate run / palpate-cell and `palpate ft` (issue 18): bad combinations refused in one line with exit 2
before anything runs; the simulated box read by `palpate ft`; a sensor fault in `palpate-cell --sim --ft netft`
ends the run with exit 1, the fault in run.json and the records on disk."""
from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from robot_fixtures import make_plan  # noqa: E402

from app import cell, cli  # noqa: E402
from robot.driver import DriverConfig, watchdog_rate_hz  # noqa: E402
from robot.records import read_records  # noqa: E402
from robot.sim import ArmModel  # noqa: E402
from robot.simcontroller import reaction_times_s, read_events  # noqa: E402
from robot.simnetft import attach_box  # noqa: E402


@pytest.fixture
def plan_file(tmp_path):
    p = tmp_path / "plan.json"
    make_plan((0.02, 0.035), depth_m=0.003).save(p)
    return str(p)


@pytest.mark.parametrize("argv, names", [
    (["run", "--sim", "--ft", "netft:192.0.2.1"], "--ft netft:192.0.2.1"),
    (["run", "--ft", "netft", "--ft-range-n", "25"], "--ft-range-n"),
    (["run", "--ft-sensor-pose", "0,0,0.02,0,0,0"], "--ft-sensor-pose"),
    (["run", "--host", "192.0.2.1", "--ft", "netft"], "--ft netft"),
    (["run", "--host", "192.0.2.1", "--ft", "netft:192.0.2.2", "--ft-range-n", "25", "--ft-range-nm", "0.25"],
     "--ft-sensor-pose"),
    (["run", "--host", "192.0.2.1", "--ft", "netft:192.0.2.2", "--ft-sensor-pose", "0,0,0.02,0,0,0",
      "--ft-range-n", "25", "--ft-range-nm", "0.25", "--ft-counts-per-force", "1e6"], "--ft-counts-per-torque"),
    (["ft", "--ft", "rtde"], "--ft rtde"),
    (["ft", "--ft", "netft", "--ft-port", "49152"], "--ft-port"),
])
def test_bad_ft_combinations_are_refused_in_one_line(tmp_path, capsys, argv, names):
    code = cli.main(argv + ["--out", str(tmp_path / "out")] if argv[0] == "run" else argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and names in err[0], err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("value", ["netfx", "netft:", "rtde:1.2.3.4"])
def test_bad_ft_value_names_the_option(capsys, value):
    assert cli.main(["ft", "--ft", value]) == 2
    err = capsys.readouterr().err
    assert "argument --ft: must be rtde" in err and repr(value) in err and "Traceback" not in err


def test_cell_refuses_a_box_fault_without_the_box(tmp_path, capsys, plan_file):
    code = cell.main(["--sim", "--plan", plan_file, "--out", str(tmp_path / "o"), "--force-model", "standin",
                      "--inject", "ft-silent-at-s=1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--inject ft-silent-at-s=1" in err[0] and "--ft netft" in err[0]


def test_palpate_ft_reads_the_simulated_box(tmp_path, capsys):
    out = tmp_path / "ft.json"
    assert cli.main(["ft", "--ft", "netft", "--duration-s", "0.4", "--json", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert rep["simulated"] and rep["fault"] is None and rep["lost"] == 0
    assert 300 <= rep["rate_hz"] <= 1100                 # 1 kHz stepped by a thread on a busy machine
    assert all(0.001 < s < 0.01 for s in rep["force_std_n"])    # the nano17 preset's 3 mN noise


def test_palpate_ft_reads_a_box_at_an_address(tmp_path):
    """The real-box path (address, port, calibration and ranges given) against a simulated box on loopback."""
    arm = ArmModel(None, sensor="ideal")
    box = attach_box(arm, host="127.0.0.1", port=0, records_per_step=2)
    port = box.address[1]
    stop = threading.Event()

    def tick():
        while not stop.is_set():
            arm.step()
            time.sleep(0.002)
    stepper = threading.Thread(target=tick, daemon=True)
    stepper.start()
    out = tmp_path / "ft.json"
    try:
        # the spelling: --netft HOST --port PORT --seconds S (= --ft netft:HOST --ft-port --duration-s)
        code = cli.main(["ft", "--netft", "127.0.0.1", "--port", str(port), "--ft-counts-per-force",
                         "1e6", "--ft-counts-per-torque", "1e6", "--ft-range-n", "35", "--ft-range-nm", "0.25",
                         "--seconds", "0.3", "--json", str(out)])
    finally:
        stop.set()
        stepper.join()
        box.close()
    rep = json.loads(out.read_text())
    assert code == 0 and not rep["simulated"] and rep["port"] == port and rep["records"] > 100


def test_cell_sensor_fault_ends_safe_with_records(tmp_path, capsys, plan_file):
    out = tmp_path / "run"
    code = cell.main(["--sim", "--plan", plan_file, "--out", str(out), "--force-model", "standin", "--ft", "netft",
                      "--inject", "ft-silent-at-depth-m=0.001", "--json", str(tmp_path / "rep.json")])
    text = capsys.readouterr().out
    assert code == 1 and "FAULT sensor_lost" in text, text
    run_json = json.loads((out / "run.json").read_text())
    assert run_json["fault"]["kind"] == "sensor_lost" and run_json["fault"]["stopped"] is True
    assert run_json["force_source"]["source"] == "netft"
    recs = read_records(out)
    assert recs[-1].status == "fault" and recs[-1].n_samples_total > 0


def test_cell_through_the_simulated_controller_and_its_box(tmp_path, capsys):
    """The real ur_rtde client, the simulated controller serving the Net F/T box in real time: a 5 N spike in the
    first descent is stopped (stopL through ur_rtde) well within the stated bound -- the watchdog's 1/rate, 0.2 s at
    2 mm/s, what a host stalled for good would get -- the second probe is measured through the box, a bad status word
    before the third ends the run safe."""
    plan = tmp_path / "plan.json"
    make_plan((0.02, 0.035, 0.05), depth_m=0.003).save(plan)
    out = tmp_path / "run"
    code = cell.main(["--sim", "controller", "--plan", str(plan), "--out", str(out), "--force-model", "standin",
                      "--ft", "netft", "--inject", "ft-spike-at-depth-m=0.001:5",
                      "--inject", "ft-status-after-probes=2:32768"])
    text = capsys.readouterr().out
    assert code == 1 and "FAULT sensor_status" in text and "0x00008000" in text, text
    run_json = json.loads((out / "run.json").read_text())
    assert run_json["fault"]["stopped"] is True and (run_json["n_force_limit"], run_json["n_ok"]) == (1, 1)
    src = run_json["force_source"]
    assert src["source"] == "netft" and src["records"] > 1000 and src["lost"] == 0
    spiked, measured = read_records(out)[:2]
    assert spiked.status == "force_limit" and measured.status == "ok"
    assert 0.05 < measured.force_mean_n < 1.0                          # the stand-in tissue at 3 mm
    reaction = reaction_times_s(read_events((out / "simcontroller.log").read_text()))
    assert len(reaction) == 1 and 0.002 <= reaction[0] <= 1.0 / watchdog_rate_hz(DriverConfig(), 0.002), reaction
