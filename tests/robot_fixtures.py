"""Helpers for the robot tests: plans built directly (no CasADi planner) and simulated arms."""
from __future__ import annotations

import math

import numpy as np

from core import ur5e
from core.contracts import Frames, Limits, Motion, Plan, Probe
from robot.sim import ArmModel, SimRTDEControl, SimRTDEReceive
from robot.simforce import standin_force_model

TCP = [0.0, 0.0, 0.10, 0.0, 0.0, 0.0]
TISSUE_POSE = [0.35, -0.035, 0.05, 0.0, 0.0, 0.0]
SCENE = {"name": "paper-prior", "tissue": {"width_m": 0.07, "height_m": 0.05, "youngs_pa": 2500.0, "poisson": 0.4},
         "stone": [],
         # (a plan file's scene holds its tip and analysis: core.contracts.PLAN_SCENE_TABLES; the paper's)
         "indenter": {"shape": "cylinder", "radius_m": 0.005, "youngs_pa": 60e6, "poisson": 0.3, "thickness_m": 0.02},
         "analysis": {"plane": "strain", "order": 2, "mesh_size_m": 0.002, "surface_refine": 4.0,
                      "top_displacement_m": 0.005, "formulation": "displacement"}}


def tissue_point_pose(tissue_pose, x_m, z_m) -> list[float]:
    """Base-frame pose of the tip at tissue-frame point (x_m, 0, z_m), tool z along the inward normal."""
    T = ur5e.pose_to_T(tissue_pose)
    Tt = np.eye(4)
    Tt[:3, :3] = T[:3, :3] @ ur5e.rotvec_to_matrix([math.pi, 0, 0])
    Tt[:3, 3] = T[:3, :3] @ [x_m, 0.0, z_m] + T[:3, 3]
    return ur5e.T_to_pose(Tt)


def make_plan(xs=(0.02, 0.035, 0.05), depth_m=0.003, predicted=0.1, tissue_pose=TISSUE_POSE, motion=None,
              limits=None, solve_q=True) -> Plan:
    mo = motion or Motion(approach_height_m=0.004, dwell_s=0.2)
    probes, q = [], ur5e.Q_HOME
    for i, x in enumerate(xs):
        a = tissue_point_pose(tissue_pose, x, mo.approach_height_m)
        d = tissue_point_pose(tissue_pose, x, -depth_m)
        if solve_q:
            qa = ur5e.ik(a, q, TCP)
            qd = ur5e.ik(d, qa, TCP)
            q = qa
        else:
            qa = qd = [0.0] * 6  # placeholders: refused by robot.safety.check_plan (the joints must reach the poses)
        probes.append(Probe(index=i, x_m=float(x), depth_m=float(depth_m), predicted_force_n=float(predicted),
                            approach_pose=a, indent_pose=d, q_approach_rad=[float(v) for v in qa],
                            q_indent_rad=[float(v) for v in qd]))
    return Plan(scene=SCENE, frames=Frames(tissue_pose_base=list(tissue_pose), tcp_offset=list(TCP)),
                limits=limits or Limits(), motion=mo, probes=probes)


def solve_joints(plan: Plan) -> Plan:
    """Each probe's joint targets solved again for its poses (as the planner does): after a test edits the poses,
    robot.safety.check_plan would otherwise refuse the plan (its joints no longer reach them)."""
    tcp = plan.frames.tcp_offset
    q = ur5e.Q_HOME
    for p in plan.probes:
        p.q_approach_rad = [float(v) for v in ur5e.ik(p.approach_pose, q, tcp)]
        p.q_indent_rad = [float(v) for v in ur5e.ik(p.indent_pose, p.q_approach_rad, tcp)]
        q = p.q_approach_rad
    return plan


def start_q(tissue_pose=TISSUE_POSE, x_m=0.035, height_m=0.02):
    return ur5e.ik(tissue_point_pose(tissue_pose, x_m, height_m), ur5e.IK_SEED, TCP)


def make_sim(force_model=None, sensor="nano17", seed=0, tissue_pose=TISSUE_POSE, **kw):
    arm = ArmModel(force_model or standin_force_model(), tissue_pose_base=tissue_pose, sensor=sensor, seed=seed,
                   q0=start_q(tissue_pose), tcp_offset=TCP, **kw)
    return arm, SimRTDEControl(arm), SimRTDEReceive(arm)
