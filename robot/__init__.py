"""robot: probing a UR arm through ur_rtde. The driver takes a plan and two interfaces and returns records (it imports
neither fem nor the planner); the simulated arm (sim, simarm) and the simulated controller (simcontroller) hold the
true scene, and simarm is the one part that asks fem for forces. The force comes from the UR's wrist sensor or an
external ATI Net F/T box (forcesource, netft; simnetft simulates the box)."""
from core.lazy import lazy_exports

_EXPORTS = {
    "run_plan": "driver", "preflight": "driver", "DriverConfig": "driver", "RunReport": "driver",
    "RunLog": "records", "read_records": "records", "read_measurements": "records", "done_indices": "records",
    "build_truth_arm": "simarm", "ArmModel": "sim", "SimRTDEControl": "sim", "SimRTDEReceive": "sim",
    "connect": "link", "disconnect": "link", "start_controller": "simlaunch",
    "RtdeForce": "forcesource", "NetFtForce": "forcesource", "Mount": "forcesource", "NetFtReader": "netft",
    "NetFtConfig": "netft", "NetFtCalibration": "netft", "SensorFault": "netft", "SimNetFtBox": "simnetft",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
