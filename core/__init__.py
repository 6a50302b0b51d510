"""core: the plain data every package shares (core.contracts) and the UR5e's kinematics (core.ur5e). Imports no
other palpate package."""
from core.lazy import lazy_exports

_EXPORTS = {
    "Plan": "contracts", "Probe": "contracts", "Frames": "contracts", "Limits": "contracts", "Motion": "contracts",
    "PlanOptions": "contracts", "PlanError": "contracts", "ProbeRecord": "contracts", "ProbeStatus": "contracts",
    "RunStatus": "contracts", "FaultKind": "contracts", "SensorSpec": "contracts", "SENSORS": "contracts",
    "sensor_spec": "contracts", "MEASURED": "contracts",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
