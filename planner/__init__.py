"""planner: what to probe and what the probes say. Raster planning with CasADi (plan, raster, timing, kinematics; on
a 3D block area and depth3d),
localization of the stone from probe records (localize, surrogate, refine) and detectability before probing. Sees
only the prior tissue, never a simulator's truth. Imports core and fem."""
from core.lazy import lazy_exports

_EXPORTS = {
    "plan_raster": "plan", "replan": "plan",
    "raster_positions": "raster", "interval_positions": "raster", "choose_depths": "raster",
    "default_tissue_pose": "raster",
    "area_raster": "area", "Region": "area", "default_block_pose": "area", "ContactDepths3D": "depth3d",
    "Measurements": "localize", "Localization": "localize", "localize": "localize", "LR_THRESHOLD": "localize",
    "load_surrogate": "surrogate", "adaptive": "refine", "describe": "refine",
    "detectability": "detectability", "probe_sigma_n": "detectability",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
