"""The 3D area planner on a coarse block (fem in ~0.3 s): positions inside the region and the probed patch, serpentine
order, the tool along the normal at every pose, y_m in the plan, the plan's own and the driver's checks, predicted
forces equal to fem's and within the budget, replan over (N, 2), the mapped NLP against the SX one, and the CLI."""
import dataclasses
import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_kinematics import poe_tcp

from app.figure_names import PLAN_FIGURES
from core import ur5e
from core.contracts import Limits, Plan, PlanError
from fem.contact3d import surface_model3d
from fem.scene import load
from planner import area
from planner.depth3d import ContactDepths3D
from planner.plan import Margins, RasterNLP, plan_raster, replan, seed_configurations
from planner.raster import default_tissue_pose, targets
from robot.safety import check_plan

COARSE_TOML = """name = "coarse3d"
[tissue]
width_m = 0.07
length_m = 0.07
height_m = 0.05
youngs_pa = 2500.0
poisson = 0.4
[indenter]
shape = "sphere"
radius_m = 0.005
youngs_pa = 60.0e6
[analysis]
order = 2
mesh_size_m = 0.02
surface_refine = 4.0
patch_m = 0.03
grade = 0.25
"""
LIMITS = Limits(force_limit_n=0.1)      # budget 0.05 N: the force binds before the 4 mm depth limit


@pytest.fixture(scope="module")
def toml(tmp_path_factory):
    p = tmp_path_factory.mktemp("scene") / "coarse3d.toml"
    p.write_text(COARSE_TOML)
    return p


@pytest.fixture(scope="module")
def prior(toml):
    return load(toml).prior()


@pytest.fixture(scope="module")
def plan(prior):
    return plan_raster(prior, grid=(4, 3), limits=LIMITS)


def _tissue_T(plan):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(plan.frames.tissue_pose_base[3:]).as_matrix()
    T[:3, 3] = plan.frames.tissue_pose_base[:3]
    return T


def _inside_triangle(p, a, b, c, tol=1e-9):
    def cross(o, u, v):
        return (u[0] - o[0]) * (v[1] - o[1]) - (u[1] - o[1]) * (v[0] - o[0])
    s = [cross(a, b, p), cross(b, c, p), cross(c, a, p)]
    return all(v >= -tol for v in s) or all(v <= tol for v in s)


def test_polygon_grid_lies_inside_and_is_serpentine(prior):
    tri = [(0.026, 0.026), (0.044, 0.027), (0.034, 0.044)]
    ar = area.area_raster(prior, region=area.Region.polygon(tri), spacing_m=0.003)
    P = ar.positions_m
    assert len(P) >= 10
    assert all(_inside_triangle(p, *tri) for p in P)
    # rows of equal y (or of equal x), each row monotone, consecutive rows in opposite directions
    key = 1 if ar.order == "serpentine-x" else 0
    rows = np.split(P, np.flatnonzero(np.abs(np.diff(P[:, key])) > 1e-12) + 1)
    assert len(rows) == len(np.unique(np.round(P[:, key], 9)))
    dirs = [np.sign(r[-1, 1 - key] - r[0, 1 - key]) for r in rows if len(r) > 1]
    assert all(a != b for a, b in zip(dirs, dirs[1:]))
    assert ar.travel_m <= ar.travel_row_major_m and ar.travel_m >= ar.travel_lower_bound_m - 1e-12


def test_full_grid_order_meets_the_travel_lower_bound(prior):
    ar = area.area_raster(prior, grid=(5, 5))             # equal spacings: every move one step
    assert len(ar.positions_m) == 25
    assert ar.travel_m == pytest.approx(ar.travel_lower_bound_m, rel=1e-9)
    assert ar.travel_row_major_m > 1.5 * ar.travel_m
    x0, x1, y0, y1 = area.probe_bounds(prior)            # default region: the patch shrunk by the tip radius
    assert (x0, x1, y0, y1) == pytest.approx((0.025, 0.045, 0.025, 0.045))
    assert ar.positions_m.min(axis=0) == pytest.approx([x0, y0]) and ar.positions_m.max(axis=0) == pytest.approx([x1, y1])


@pytest.mark.parametrize("kw, match", [
    (dict(region=(0.02, 0.03, 0.04, 0.04)), r"--region: waypoint .* outside fem's probed patch.*x 0\.025\.\.0\.045"),
    (dict(margin_m=0.002), r"--margin-m: waypoint .*analysis\.patch_m = 0\.03"),
    (dict(polygon=[(0.03, 0.03), (0.045, 0.045), (0.045, 0.03), (0.03, 0.036)]), r"--polygon.*edges 0 and 2 cross"),
    (dict(positions_m=[[0.035, 0.035], [0.035, 0.08]]), r"positions_m: waypoint .* off the block's top face"),
    (dict(n_waypoints=5), r"n_waypoints \(--waypoints\) is for a 2D section"),
])
def test_positions_off_the_probed_patch_are_refused_naming_the_option(prior, kw, match):
    with pytest.raises(PlanError, match=match):
        plan_raster(prior, limits=LIMITS, **kw)


def test_plan_carries_y_and_passes_its_own_and_the_drivers_checks(plan, prior, tmp_path):
    ar = area.area_raster(prior, grid=(4, 3))
    np.testing.assert_allclose([[p.x_m, p.y_m] for p in plan.probes], ar.positions_m, rtol=0, atol=1e-15)
    assert len({p.y_m for p in plan.probes}) == 3
    plan.save(tmp_path / "plan.json")
    back = Plan.load(tmp_path / "plan.json")          # Plan.check on read
    assert [p.y_m for p in back.probes] == [p.y_m for p in plan.probes]
    problems, per_probe = check_plan(back)
    assert problems == [] and per_probe == {}
    assert plan.notes["solver"]["used"] == "nlp" and plan.notes["solver"]["nlp"] == "mapped"


def test_default_pose_puts_the_block_middle_in_front_of_the_arm(plan, prior):
    t = prior.tissue
    mid = _tissue_T(plan) @ [t.width_m / 2, t.length_m / 2, 0, 1]
    assert mid[:3] == pytest.approx([0.40, 0.0, t.height_m])
    assert plan.frames.tissue_pose_base == pytest.approx(area.default_block_pose(t.width_m, t.length_m, t.height_m))


def test_tool_along_the_normal_and_tip_on_target_at_every_pose(plan):
    Tt = _tissue_T(plan)
    n_in = -Tt[:3, 2]
    h = plan.motion.approach_height_m
    for p in plan.probes:
        for q, pose, want in ((p.q_approach_rad, p.approach_pose, [p.x_m, p.y_m, h, 1]),
                              (p.q_indent_rad, p.indent_pose, [p.x_m, p.y_m, -p.depth_m, 1])):
            T = poe_tcp(q, plan.frames.tcp_offset)                  # independent FK
            assert math.acos(min(1.0, float(T[:3, 2] @ n_in))) <= plan.options.tilt_tol_rad + 1e-9
            assert np.linalg.norm(T[:3, 3] - (Tt @ want)[:3]) < 1e-6
            assert np.linalg.norm(T[:3, 3] - pose[:3]) < 1e-6


def test_predicted_forces_are_fems_and_within_the_budget(plan, prior):
    model = surface_model3d(prior)
    budget = plan.options.force_fraction * plan.limits.force_limit_n
    assert set(plan.notes["depth_limited_by"]) == {"force"}
    for p in plan.probes:
        f = model.force_n(p.x_m, p.y_m, p.depth_m)                  # fem's own LCP at the planned depth
        assert p.predicted_force_n == pytest.approx(f, rel=1e-9, abs=1e-15)
        assert f <= budget and f > 0.999 * budget
        assert plan.options.min_depth_m <= p.depth_m <= plan.limits.depth_limit_m


def test_depth_choice_at_the_depth_limit_and_below_a_useful_depth(prior):
    cd = ContactDepths3D(surface_model3d(prior))
    d, f = cd.depth_for((0.035, 0.035), 1.0, 0.004)                   # budget far above: the depth limit binds
    assert d == 0.004 and f == pytest.approx(cd.force_n(0.035, 0.035, 0.004), rel=1e-12)
    with pytest.raises(PlanError, match=r"too low.*x = 25\.0 mm, y = 25\.0 mm.*--force-limit-n"):
        plan_raster(prior, grid=(2, 2), limits=Limits(force_limit_n=0.005))


def test_an_elastic_tip_plans_on_fems_elastic_tip_forces(toml):
    """A tip as stiff as the tissue (fem.tip3d): the planned depths' predicted forces are fem's with the elastic tip
    (not the rigid tip's, about twice as high at one depth), within the budget."""
    soft = load(toml).prior()
    soft = dataclasses.replace(soft, indenter=dataclasses.replace(soft.indenter, youngs_pa=2500.0, poisson=0.4))
    model = surface_model3d(soft)
    assert not model.rigid_tip
    cd = ContactDepths3D(model)
    d, f = cd.depth_for((0.035, 0.035), 0.03, 0.004)
    assert f == pytest.approx(model.force_n(0.035, 0.035, d), rel=1e-9) and 0.999 * 0.03 < f <= 0.03
    rigid = surface_model3d(load(toml).prior())
    assert rigid.force_n(0.035, 0.035, d) > 1.5 * f


def test_replan_over_xy_positions(plan):
    pos = np.array([[0.036, 0.030], [0.030, 0.041], [0.040, 0.035]])
    r = replan(plan, pos)
    np.testing.assert_allclose([[p.x_m, p.y_m] for p in r.probes], pos, rtol=0, atol=1e-15)   # the order given
    assert r.frames == plan.frames and r.limits == plan.limits and r.scene == plan.scene
    with pytest.raises(PlanError, match=r"\(N, 2\)"):
        replan(plan, pos[:, 0])


def test_replan_of_a_2d_plan_still_takes_x_only():
    stand_in = lambda x, d: (d / 0.003) ** 1.5                         # noqa: E731
    p2 = plan_raster("paper", n_waypoints=3, force_n=stand_in)
    assert all(p.y_m == 0.0 for p in p2.probes)
    assert len(replan(p2, [0.03, 0.035], force_n=stand_in).probes) == 2
    with pytest.raises(PlanError, match=r"\(N,\) tissue-frame x"):
        replan(p2, [[0.03, 0.03]], force_n=stand_in)
    with pytest.raises(PlanError, match=r"grid \(--grid\) is for a 3D block"):
        plan_raster("paper", grid=(3, 3), force_n=stand_in)


def test_mapped_nlp_equals_the_sx_nlp():
    pose = default_tissue_pose(0.07, 0.05)
    x = np.linspace(0.01, 0.06, 6)
    tg = targets(x, np.full(6, 0.003), pose, 0.01, y_m=np.linspace(0.0, 0.01, 6))
    tcp = [0, 0, 0.10, 0, 0, 0]
    Q0, _ = seed_configurations(tg, ur5e.pose_to_T(pose)[:3, 0], tcp)
    args = (Q0, tg, tcp, ur5e.DEFAULT_BRANCH, Margins(), math.radians(0.5))
    Qa, ia = RasterNLP(6).solve(*args)
    Qb, ib = RasterNLP(6, mapped=True).solve(*args)
    assert ia["success"] and ib["success"] and ia["iterations"] == ib["iterations"]
    assert np.max(np.abs(Qa - Qb)) < 1e-9 and ib["objective"] == pytest.approx(ia["objective"], rel=1e-9)


def test_cli_plans_an_area_and_refuses_bad_values_in_one_line(toml, tmp_path, capsys):
    from app.cli import main
    out, js, figs = tmp_path / "plan.json", tmp_path / "s.json", tmp_path / "figs"
    rc = main(["plan", str(toml), "--out", str(out), "--grid", "3x2", "--region", "0.027,0.028,0.043,0.04",
               "--force-limit-n", "0.1", "--json", str(js), "--plots", str(figs)])
    assert rc == 0
    plan = Plan.load(out)
    assert len(plan.probes) == 6 and sorted({p.y_m for p in plan.probes}) == pytest.approx([0.028, 0.04])
    s = json.loads(js.read_text())
    assert s["y_m"] == [p.y_m for p in plan.probes] and s["raster"]["order"].startswith("serpentine")
    assert (figs / "plan_area.png").stat().st_size > 10_000 and (figs / "plan_joints.png").stat().st_size > 0
    assert {f.name for f in figs.iterdir()} <= set(PLAN_FIGURES)      # (what plan refuses as an output beside --plots)
    capsys.readouterr()
    for argv, want in ((["--grid", "0x3"], "--grid: must be NXxNY"),
                       (["--region", "0.02,0.03,0.04"], "--region: must be x0,y0,x1,y1"),
                       (["--region", "0.01,0.03,0.04,0.04"], "--region: waypoint"),
                       (["--polygon", "0.03,0.03;0.04"], "--polygon: must be"),
                       (["--waypoints", "5"], "--waypoints is for a 2D section")):
        assert main(["plan", str(toml), "--out", str(tmp_path / "bad.json"), *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()     # argparse: its usage, then the one message line
        assert want in err[-1] and err[-1].startswith("palpate"), err
        assert "Traceback" not in "\n".join(err)
    assert main(["plan", "paper", "--out", str(tmp_path / "bad.json"), "--grid", "3x3"]) == 2
    assert "--grid is for a 3D block" in capsys.readouterr().err
