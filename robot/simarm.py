"""The simulated TRUE arm: one builder for the in-memory arm of ``palpate run --sim`` and ``palpate-cell --sim`` and
for the simulated controller's arm. It is the one robot part that asks fem for forces (the truth's, stones
included); the driver never sees it.

The truth is the simulator's secret: whoever builds the arm hands it the true scene and its conditions
(robot.truth.TruthConditions: registration error, relaxation, sensor bias and drift, a finite-strain neo-Hookean
tissue), and only the arm's force
model (inside this module's closures) reads them.
"""
from __future__ import annotations

import math

import numpy as np

from core import ur5e
from core.contracts import Frames
from fem import recall
from fem.contact import surface_model
from fem.hypertruth import HyperelasticForce
from fem.scene import BUILTIN, Scene, load
from robot.sim import ArmModel
from robot.simfaults import inject_arm, parse
from robot.simforce import standin_force_model
from robot.truth import Relaxation, TruthConditions, conditions_of

START_CLEARANCE_M = 0.02      # the arm starts this far above the first approach pose
STANDIN_WIDTH_M = 0.07        # the stand-in force model's tissue width


class TruthRangeError(RuntimeError):
    """The simulated tip pressed where the truth's fem model does not reach (a 3D block's probed patch): the
    simulator cannot say what tissue there would push back with."""


def truth_force(truth: Scene | str, mesh_m: float | None = None, hyperelastic: bool = False):
    """(force_n(x_m, depth_m), width_m) of the TRUE scene from fem (zero outside the tissue's top surface); for a 3D
    block force_n(x_m, y_m, depth_m) over its probed patch (TruthRangeError elsewhere on the block).
    ``hyperelastic``: the tissue as a finite-strain neo-Hookean solid (fem.hypertruth; 2D only)."""
    sc = truth if isinstance(truth, Scene) else load(truth)
    if mesh_m:
        sc = sc.with_analysis(mesh_size_m=mesh_m)
    width, height = sc.tissue.width_m, sc.tissue.height_m
    if sc.is_3d:                   # fem's 3D code (25 ms of imports) for a block only
        from fem import recall3d
        from fem.contact3d import surface_model3d
        from fem.mesh3d import patch_bounds
        surface_model3d(sc)        # built (or restored) now: its errors before the run, not as a force model's
        length, R = sc.tissue.length_m, sc.indenter.radius_m
        x0, x1, y0, y1 = patch_bounds(width, length, sc.analysis.patch_m)

        def force3(x_m: float, y_m: float, depth_m: float) -> float:
            if not (0.0 <= x_m <= width and 0.0 <= y_m <= length and 0.0 < depth_m < height):
                return 0.0
            if not (x0 + R - 1e-9 <= x_m <= x1 - R + 1e-9 and y0 + R - 1e-9 <= y_m <= y1 - R + 1e-9):
                raise TruthRangeError(f"the simulated tip pressed at (x, y) = ({x_m * 1e3:.2f}, {y_m * 1e3:.2f}) mm, "
                                      f"outside the truth's fem patch (analysis.patch_m = {sc.analysis.patch_m} m "
                                      f"less the tip radius): plan inside it")
            return recall3d.force_n(sc, x_m, y_m, depth_m)
        return force3, width
    if hyperelastic:
        of = HyperelasticForce(sc).force_n
    else:
        surface_model(sc)          # built (or restored) now: its errors before the run, not as a force model's

        def of(x_m: float, depth_m: float) -> float:
            return recall.force_n(sc, x_m, depth_m)

    def force_n(x_m: float, depth_m: float) -> float:
        return of(x_m, depth_m) if 0.0 <= x_m <= width and 0.0 < depth_m < height else 0.0
    return force_n, width


def start_configuration(tissue_pose, width_m: float, tcp_offset=None, above_pose=None) -> np.ndarray | None:
    """Joint angles to start from: ``START_CLEARANCE_M`` above ``above_pose`` (a plan's first approach pose) or,
    without one, the flange 0.2 m above the middle of the tissue, tool pointing in."""
    if above_pose is not None:
        start = list(above_pose[:2]) + [above_pose[2] + START_CLEARANCE_M] + list(above_pose[3:])
        return ur5e.ik(start, ur5e.IK_SEED, tcp_offset or (0, 0, 0, 0, 0, 0))
    T = ur5e.pose_to_T(tissue_pose) @ ur5e.pose_to_T([0.5 * width_m, 0.0, 0.2, math.pi, 0.0, 0.0])
    return ur5e.ik(ur5e.T_to_pose(T), ur5e.IK_SEED)


def build_truth_arm(truth: Scene | str = "paper", *, force: str = "fem", sensor: str = "nano17", seed: int = 0,
                    tissue_pose=None, tcp_offset=None, start_above_pose=None, q0=None, mesh_m: float | None = None,
                    inject=(), tool_offset=None, conditions: TruthConditions | None = None) -> ArmModel:
    """The simulated arm over the TRUE scene (``force="fem"``) or a Hertz-like stand-in (``"standin"``), with its
    sensor model and any injected faults (robot.simfaults syntax; controller faults are left to the simulated
    controller, external sensor faults to the simulated Net F/T box). ``conditions``: what the world adds to the
    scene (robot.truth); None: the ``[truth]`` table of a
    TOML ``truth`` (ideal for anything else)."""
    if conditions is not None:
        cond = conditions
    else:        # a built-in scene's name has no [truth] table (even if a file of that name lies here)
        cond = TruthConditions() if isinstance(truth, str) and truth in BUILTIN else conditions_of(truth)
    tissue_pose = list(tissue_pose or Frames().tissue_pose_base)
    length = None
    if force == "fem":
        sc = load(truth)
        cond.check_scene(sc)
        f, width = truth_force(sc, mesh_m, hyperelastic=cond.hyperelastic)
        length = sc.tissue.length_m
    elif force == "standin":
        f, width = standin_force_model(), STANDIN_WIDTH_M
    else:
        raise ValueError(f"force model {force!r}: fem or standin")
    if q0 is None:
        q0 = start_configuration(tissue_pose, width, tcp_offset, start_above_pose)
    kw = {} if tcp_offset is None else {"tcp_offset": list(tcp_offset)}
    if length is not None:
        kw["length_m"] = length
    if tool_offset is not None:            # the probe as mounted (default: the TCP the arm starts with)
        kw["tool_offset"] = list(tool_offset)
    if cond.surface_offset_m or cond.surface_tilt_rad:
        kw["surface_height_m"] = lambda x_m: cond.surface_height_m(x_m, width)
        kw["surface_tilt_rad"] = cond.surface_tilt_rad          # (the same plane: the force along its normal)
    if cond.relaxation_fraction > 0:
        kw["relaxation"] = Relaxation(cond.relaxation_fraction, cond.relaxation_tau_s)
    arm = ArmModel(f, tissue_pose_base=tissue_pose, width_m=width, sensor=sensor, seed=seed,
                   q0=None if q0 is None else np.asarray(q0, dtype=float), **kw)
    arm.normal_bias_n, arm.normal_drift_n_per_s = cond.sensor_bias_n, cond.sensor_drift_n_per_s
    arm.sensor.bias[:3] += cond.sensor_bias_n * arm.n_base          # along the tissue normal, on top of the preset's
    arm.sensor.drift[:3] += cond.sensor_drift_n_per_s * arm.n_base
    for spec in inject:
        f = parse(spec)
        if f.on_arm:
            inject_arm(arm, f)
    return arm
