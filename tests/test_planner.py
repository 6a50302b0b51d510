"""The raster planner: poses, alignment, limits, branch continuity, depth choice, timing, refusals, and the CLI on
the real fem model."""
import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_kinematics import poe_tcp

from core import ur5e
from core.contracts import Frames, Limits, Plan, PlanError
from fem.scene import load
from planner.plan import Margins, plan_raster, replan
from planner.raster import choose_depths, default_tissue_pose, depth_for_force, interval_positions, raster_positions
from planner.timing import trapezoid_time

W = 0.070


def stand_in_force(x_m, depth_m):
    """Hertz-like stand-in for fem (stiffer than the real kidney so the force limit binds): 1 N at 3 mm mid-surface,
    softer towards the free side edges."""
    return (0.6 + 0.4 * math.sin(math.pi * x_m / W)) * (depth_m / 0.003) ** 1.5


@pytest.fixture(scope="module")
def plan():
    return plan_raster("paper", n_waypoints=21, force_n=stand_in_force)


def _tissue_T(plan):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(plan.frames.tissue_pose_base[3:]).as_matrix()
    T[:3, 3] = plan.frames.tissue_pose_base[:3]
    return T


def test_every_joint_vector_maps_to_its_pose(plan):
    for p in plan.probes:
        for q, pose in ((p.q_approach_rad, p.approach_pose), (p.q_indent_rad, p.indent_pose)):
            T = poe_tcp(q, plan.frames.tcp_offset)                     # independent FK
            assert np.linalg.norm(T[:3, 3] - pose[:3]) < 1e-6
            R = Rotation.from_rotvec(pose[3:]).as_matrix()
            assert ur5e.rotation_angle(T[:3, :3], R) < 1e-6


def test_tip_reaches_the_surface_targets(plan):
    Tt = _tissue_T(plan)
    h = plan.motion.approach_height_m
    for p in plan.probes:
        above = Tt @ [p.x_m, 0, h, 1]
        below = Tt @ [p.x_m, 0, -p.depth_m, 1]
        assert np.linalg.norm(poe_tcp(p.q_approach_rad, plan.frames.tcp_offset)[:3, 3] - above[:3]) < 1e-6
        assert np.linalg.norm(poe_tcp(p.q_indent_rad, plan.frames.tcp_offset)[:3, 3] - below[:3]) < 1e-6


def test_tool_axis_along_inward_normal(plan):
    n_in = -_tissue_T(plan)[:3, 2]
    tol = plan.options.tilt_tol_rad
    for p in plan.probes:
        for q in (p.q_approach_rad, p.q_indent_rad):
            z = poe_tcp(q, plan.frames.tcp_offset)[:3, 2]
            assert math.acos(min(1.0, float(z @ n_in))) <= tol + 1e-9


def test_joint_limits_hold(plan):
    Q = np.array([[p.q_approach_rad, p.q_indent_rad] for p in plan.probes])
    assert np.all(Q >= ur5e.JOINT_LOWER_RAD) and np.all(Q <= ur5e.JOINT_UPPER_RAD)


def test_force_and_depth_limits_hold(plan):
    lim = plan.limits
    budget = plan.options.force_fraction * lim.force_limit_n
    by = plan.notes["depth_limited_by"]
    for p, why in zip(plan.probes, by):
        assert plan.options.min_depth_m <= p.depth_m <= lim.depth_limit_m
        assert p.predicted_force_n == pytest.approx(stand_in_force(p.x_m, p.depth_m), rel=1e-12)
        assert p.predicted_force_n <= budget <= lim.force_limit_n
        if why == "force":   # as deep as the budget allows
            assert p.predicted_force_n > 0.999 * budget
    assert "force" in by     # this stand-in is stiff enough that the force budget binds mid-surface


def test_one_branch_no_flips_and_singularity_margins(plan):
    m = Margins()
    Q = np.array([[p.q_approach_rad, p.q_indent_rad] for p in plan.probes])
    for q in Q.reshape(-1, 6):
        ind = ur5e.branch_indicators(q) * np.array(ur5e.DEFAULT_BRANCH)
        assert np.all(ind >= m.as_array() - 1e-9)
    assert np.max(np.abs(np.diff(Q[:, 0], axis=0))) < 0.1      # neighbours: no 2 pi jumps, no flips
    assert np.max(np.abs(Q[:, 1] - Q[:, 0])) < 0.1


def test_solver_improves_on_the_closed_form_seed(plan):
    s = plan.notes["solver"]
    assert s["success"] and s["used"] == "nlp"
    assert s["travel_rad"] <= s["travel_seed_rad"] + 1e-9


def test_plan_holds_only_the_prior_and_round_trips(plan, tmp_path):
    assert load("paper").stones and plan.scene["stone"] == []
    plan.save(tmp_path / "plan.json")
    back = Plan.load(tmp_path / "plan.json")
    assert back.probes[3].q_indent_rad == plan.probes[3].q_indent_rad


def test_timing_is_consistent_and_within_joint_limits(plan):
    tm = plan.notes["timing"]
    d = [p.duration_s for p in plan.probes]
    assert plan.total_time_s == pytest.approx(sum(d))
    assert all(b.t_start_s == pytest.approx(a.t_start_s + a.duration_s) for a, b in zip(plan.probes, plan.probes[1:]))
    for k, p in enumerate(plan.probes):
        travel = plan.motion.approach_height_m + p.depth_m
        assert tm["descend_s"][k] >= travel / plan.motion.probe_speed_m_s
        dq = np.max(np.abs(np.subtract(p.q_indent_rad, p.q_approach_rad)))
        assert dq / tm["retract_s"][k] <= ur5e.MAX_JOINT_SPEED_RAD_S
        if k:
            dq = np.max(np.abs(np.subtract(p.q_approach_rad, plan.probes[k - 1].q_approach_rad)))
            assert dq / tm["move_in_s"][k] <= ur5e.MAX_JOINT_SPEED_RAD_S


def test_trapezoid_time():
    assert trapezoid_time(1.0, 0.5, 1.0) == pytest.approx(2.5)            # cruise: 1/0.5 + 0.5/1
    assert trapezoid_time(0.01, 0.5, 1.0) == pytest.approx(2 * math.sqrt(0.01))


def test_depth_for_force_stays_below_the_target_and_is_tight():
    f = lambda x, d: 3e3 * d ** 1.5                                        # noqa: E731
    d, F = depth_for_force(f, 0.0, 0.5, 0.008)
    root = (0.5 / 3e3) ** (2 / 3)
    assert F <= 0.5 and d <= root and root - d < 1e-5
    assert depth_for_force(f, 0.0, 100.0, 0.008) == (0.008, pytest.approx(f(0, 0.008)))


def test_refinement_over_an_interval(plan):
    x = interval_positions(0.030, 0.040, n=7)
    p = plan_raster(load("paper").prior(), x_positions_m=x, force_n=stand_in_force)
    assert [q.x_m for q in p.probes] == pytest.approx(list(x))
    assert p.notes["solver"]["used"] == "nlp"
    r = replan(plan, x, force_n=stand_in_force)       # same frames/limits/options as the coarse plan
    assert r.scene == plan.scene and r.frames == plan.frames
    np.testing.assert_allclose([q.q_indent_rad for q in r.probes], [q.q_indent_rad for q in p.probes], atol=1e-6)


def test_raster_positions():
    assert raster_positions(W, n=5, margin_m=0.005) == pytest.approx([0.005, 0.02, 0.035, 0.05, 0.065])
    x = raster_positions(W, spacing_m=0.004, margin_m=0.005)
    assert np.allclose(np.diff(x), 0.004) and x[0] >= 0.005 and x[-1] <= 0.065
    with pytest.raises(PlanError, match="margin"):
        raster_positions(W, n=3, margin_m=0.04)


def test_unreachable_scene_is_refused_with_a_clear_message():
    far = Frames(tissue_pose_base=[0.78, 0.55, 0.05, 0, 0, math.pi / 2])      # inside the workspace box, too far
    msg = r"out of reach of the UR5e \(too far.*move the tissue closer.*--tissue-pose"
    with pytest.raises(PlanError, match=msg):
        plan_raster("paper", n_waypoints=5, force_n=stand_in_force, frames=far)
    near = Frames(tissue_pose_base=[0.05, -0.035, 0.05, 0, 0, math.pi / 2])   # on top of the base
    with pytest.raises(PlanError, match=r"too close to the base.*farther"):
        plan_raster("paper", n_waypoints=5, force_n=stand_in_force, frames=near)
    outside = Frames(tissue_pose_base=[1.2, -0.035, 0.05, 0, 0, math.pi / 2])
    with pytest.raises(PlanError, match=r"workspace box"):
        plan_raster("paper", n_waypoints=5, force_n=stand_in_force, frames=outside)


def test_force_limit_below_any_useful_depth_is_refused():
    with pytest.raises(PlanError, match=r"force limit 0\.1 N is too low.*--force-limit-n"):
        plan_raster("paper", n_waypoints=5, force_n=stand_in_force, limits=Limits(force_limit_n=0.1))
    with pytest.raises(PlanError, match="--depth-limit-m"):
        choose_depths(stand_in_force, [0.035], force_limit_n=2.0, depth_limit_m=0.0005)


def test_cli_refuses_unreachable_before_building_fem(tmp_path, capsys):
    from app.cli import main
    rc = main(["plan", "paper", "--out", str(tmp_path / "p.json"), "--tissue-pose", "1.2", "-0.035", "0.05", "0", "0",
               "1.5708"])
    assert rc == 2
    assert "out of reach" in capsys.readouterr().err


def test_cli_plan_on_the_real_fem_model(tmp_path):
    """`palpate plan` end to end with fem's surface model (a coarse healthy kidney to keep it quick)."""
    from app.cli import main
    from fem.contact import surface_model
    toml = tmp_path / "coarse.toml"
    toml.write_text('name = "coarse"\n[tissue]\nwidth_m = 0.07\nheight_m = 0.05\nyoungs_pa = 2500.0\npoisson = 0.4\n'
                    '[indenter]\nyoungs_pa = 60.0e6\n[analysis]\nmesh_size_m = 0.005\n'
                    '[[stone]]\nx_m = 0.035\ndepth_m = 0.025\ndiameter_m = 0.015\n')
    out, js, figs = tmp_path / "plan.json", tmp_path / "summary.json", tmp_path / "figs"
    rc = main(["plan", str(toml), "--out", str(out), "--waypoints", "5", "--force-limit-n", "0.3",
               "--force-fraction", "0.5", "--json", str(js), "--plots", str(figs)])
    assert rc == 0
    plan = Plan.load(out)
    assert plan.scene["stone"] == [] and plan.scene["name"] == "coarse-prior"
    model = surface_model(load(toml).prior())
    for p in plan.probes:
        assert p.predicted_force_n == pytest.approx(model.force_n(p.x_m, p.depth_m), rel=1e-9)
        assert p.predicted_force_n <= 0.15 and p.depth_m <= 0.008
    assert plan.frames.tissue_pose_base == pytest.approx(default_tissue_pose(0.07, 0.05))
    s = json.loads(js.read_text())
    assert s["n_probes"] == 5 and s["solver"]["success"]
    assert (figs / "plan_raster.png").stat().st_size > 0 and (figs / "plan_joints.png").stat().st_size > 0


def test_an_upside_down_tissue_pose_is_refused():
    """A tissue pose whose surface faces down (a sign slip in the rotation) was planned silently."""
    prior = load("paper").prior()
    frames = Frames(tissue_pose_base=[0.40, -0.035, 0.05, math.pi, 0.0, 0.0])    # flipped about x
    with pytest.raises(PlanError, match="face up"):
        plan_raster(prior, n_waypoints=3, frames=frames)
