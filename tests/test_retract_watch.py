"""The retract watch (session 56): leaving the tissue, the force is watched too. Before it, a probe's retract, the
safe state's and a resumed run's first move were moves with no watch: a pull towards the tissue of 5 times the force
limit, or the force rising to 10 times it, in a retract ended with the run ok. Each test fails on the code before."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).parent))
from robot_fixtures import make_plan, make_sim  # noqa: E402

from core.contracts import DWELL, RETRACT, Limits  # noqa: E402
from robot.driver import DriverConfig, _Block, _RetractWatch, across_normal, run_plan  # noqa: E402
from robot.records import load_raw, read_records  # noqa: E402
from robot.recovery import ProbeFault  # noqa: E402
from robot.simfaults import inject_arm, parse, trigger  # noqa: E402

XS = (0.02, 0.035, 0.05)
LEAVING = 0.0015              # the trigger: the tip back at 1.5 mm below the surface, on its way out of probe 0


def _run(tmp_path, spec: str | None = None, name="run", config=None, **kw):
    arm, c, r = make_sim(seed=3)
    if spec is not None:
        inject_arm(arm, parse(spec))
    for kind, args in kw.items():
        arm.inject(kind, **args)
    out = tmp_path / name
    return run_plan(make_plan(XS, depth_m=0.003), c, r, out, config=config), arm, c, r, out


def _held_in_tissue(rep, arm, out, kind, words):
    """The fault ``kind`` naming ``words``; stopped and not moved again: the tip still in the tissue, probe 0's
    samples (its dwell's included) on disk."""
    assert rep.status == "fault" and rep.fault["kind"] == kind, rep.fault
    assert words in rep.fault["message"], rep.fault["message"]
    assert rep.fault["stopped"] and not rep.fault["retracted"] and not arm.is_moving
    assert any(n.startswith("not retracted: the retract met a force") for n in rep.fault["notes"]), rep.fault["notes"]
    depth = arm.tip_in_tissue()[1]
    assert 0.0 < depth <= LEAVING + 1e-9            # held where the watch stopped it, in the tissue
    recs = read_records(out)
    assert [x.status for x in recs] == ["fault"] and recs[0].index == 0
    raw = load_raw(out, recs[0])
    phase = np.asarray(raw["phase"])
    assert (phase == DWELL).sum() > 50 and phase[-1] == RETRACT   # the dwell kept, the fault in the retract
    assert raw["depth_m"].max() > 0.0029            # the descent and dwell to 3 mm are kept


@pytest.mark.parametrize("force_n", [-10.0, -5.0])
def test_a_pull_towards_the_tissue_in_a_retract_stops_and_holds(tmp_path, force_n):
    """10 N and 5 N towards the tissue along the normal (the tissue holding the tip; 5 and 2.5 times the 2 N limit)
    as probe 0's tip leaves it: retract_force, stopped within a filter window, and not retracted further."""
    rep, arm, c, r, out = _run(tmp_path, f"force-spike-leaving-depth-m={LEAVING}:{force_n}")
    _held_in_tissue(rep, arm, out, "retract_force", "pulls towards the tissue")
    f = load_raw(out, read_records(out)[0])["force_n"]
    pulled = np.flatnonzero(f < -1.0)
    assert pulled.size and pulled.size <= DriverConfig().filter_window + 2, pulled


def test_a_force_rising_in_a_retract(tmp_path):
    """20 N along the normal as the tip leaves (the tissue rising with it): retract_force, held."""
    rep, arm, c, r, out = _run(tmp_path, f"force-spike-leaving-depth-m={LEAVING}:20")
    _held_in_tissue(rep, arm, out, "retract_force", "rose to")


def test_a_side_push_in_a_retract(tmp_path):
    """40 N across the normal as the tip leaves: lateral_force, named as the retract's, held."""
    rep, arm, c, r, out = _run(tmp_path, f"side-push-leaving-depth-m={LEAVING}:40")
    _held_in_tissue(rep, arm, out, "lateral_force", "in the retract")
    raw = load_raw(out, read_records(out)[0])
    lat = np.linalg.norm(across_normal(raw["wrench"], (0.0, 0.0, 1.0)), axis=1)
    assert 0 < np.count_nonzero(lat > 20.0) <= DriverConfig().filter_window + 2


@pytest.mark.parametrize("spec", [f"force-spike-leaving-depth-m={LEAVING}:-1", f"side-push-leaving-depth-m={LEAVING}:1"])
def test_forces_within_the_limits_in_a_retract_run_on(tmp_path, spec):
    """1 N towards the tissue (half the limit: adhesion a tissue may show) or 1 N across it for 0.2 s as the tip
    leaves: no fault, every probe ok."""
    rep, *_ = _run(tmp_path, spec)
    assert rep.status == "ok" and rep.n_ok == len(XS), rep.fault


def test_a_push_across_that_began_before_the_safe_states_retract(tmp_path):
    """A fault in a descent from a push across the normal still acting when the safe state retracts: the retract
    began under it and does not make it worse, so it retracts (only a force that grows past where it began stops
    it), as before session 56."""
    def in_probe_1(a):
        return abs(a.tip_in_tissue()[0] - XS[1]) < 1e-4 and a.tip_in_tissue()[1] >= 0.0015
    rep, arm, c, r, out = _run(tmp_path, side_push=dict(when=in_probe_1, duration_s=0.2, magnitude_n=40.0))
    assert rep.fault["kind"] == "lateral_force" and rep.fault["retracted"], rep.fault
    assert arm.tip_in_tissue()[1] <= -0.003


def _operator_time(arm, seconds: float = 2.0) -> None:
    """The arm held where it stopped while the operator sees to it (the pull that stopped it long over)."""
    for _ in range(int(seconds / arm.period_s)):
        arm.step()


def _freedrive_out(arm, plan) -> None:
    """What the operator does with freedrive on the pendant: the tip moved out of the tissue, above probe 0."""
    arm.move_linear(plan.probes[0].approach_pose, 0.01, 0.5)
    while arm.is_moving:
        arm.step()


def test_a_resume_does_not_pull_the_tip_out_through_the_force(tmp_path):
    """After a retract held in the tissue by a pull still acting (30 s), an immediate resume refuses to retract (the
    review: it pulled the tip out through the 10 N pull, 5 times the limit): retract_force again, saying to free
    the tip, nothing moved. Freed by hand (freedrive), the same command resumes and finishes, probe 0 probed
    again."""
    arm, c, r = make_sim(seed=3)
    leaving = trigger(parse(f"nan-leaving-depth-m={LEAVING}"))
    arm.inject("force_spike", when=leaving, duration_s=30.0, magnitude_n=-10.0)
    out = tmp_path / "run"
    plan = make_plan(XS, depth_m=0.003)
    rep = run_plan(plan, c, r, out)
    assert rep.fault["kind"] == "retract_force" and rep.fault["retract_blocked"]
    held = arm.tip_in_tissue()[1]
    rep2 = run_plan(plan, c, r, out)
    assert rep2.fault["kind"] == "retract_force" and "free the tip" in rep2.fault["message"], rep2.fault
    assert not rep2.fault["retracted"] and rep2.n_ok == 0 and arm.tip_in_tissue()[1] == held
    _operator_time(arm, 30.0)
    _freedrive_out(arm, plan)
    rep3 = run_plan(plan, c, r, out)
    assert rep3.status == "ok" and rep3.n_ok == len(XS), rep3.fault
    assert [x.status for x in read_records(out)] == ["fault", "ok", "ok", "ok"]     # (the refusal pressed none)


def test_a_resumed_runs_first_retract_is_watched(tmp_path):
    """A run stopped in a descent by a protective stop (the tip left in the tissue, not retracted); the stop cleared,
    the resumed run's first move retracts the tip, watched with the sensor not yet zeroed (changes from where it
    began count), and finishes; and the same with a pull of 20 N towards the tissue as it leaves (more than twice the
    limit below where it began): stopped, held, no probe run."""
    for pull, name in ((None, "clean"), (-20.0, "pulled")):
        arm, c, r = make_sim(seed=3)
        arm.inject("protective_stop", when=lambda a: a.tip_in_tissue()[1] >= 0.002)
        out = tmp_path / name
        rep = run_plan(make_plan(XS, depth_m=0.003), c, r, out)
        assert rep.fault["kind"] == "protective_stop" and arm.tip_in_tissue()[1] > 0.0019
        arm.clear_protective_stop()
        if pull is not None:
            inject_arm(arm, parse(f"force-spike-leaving-depth-m={arm.tip_in_tissue()[1] - 2e-4}:{pull}"))
        rep2 = run_plan(make_plan(XS, depth_m=0.003), c, r, out)
        if pull is None:
            assert rep2.status == "ok" and rep2.n_ok == len(XS), rep2.fault
            continue
        assert rep2.fault["kind"] == "retract_force" and not rep2.fault["retracted"], rep2.fault
        assert "the sensor not zeroed yet" in rep2.fault["message"]
        assert rep2.n_ok == 0 and arm.tip_in_tissue()[1] > 0.0 and not arm.is_moving


def test_a_push_arriving_with_the_retracts_first_readings(tmp_path):
    """40 N across the normal starting 2 ms before probe 0's retract begins (the review: the retract's first filter
    window set where it began, with the push in it, and the run ended ok): lateral_force, held, the message saying
    what the bound is."""
    arm, c, r = make_sim(seed=3)
    inject_arm(arm, parse("side-push-at-s=4.477:40"))   # (the review's: 2 ms before probe 0's retract's moveL)
    out = tmp_path / "run"
    rep = run_plan(make_plan(XS, depth_m=0.003), c, r, out)
    assert rep.fault["kind"] == "lateral_force" and "in the retract" in rep.fault["message"], rep.fault
    assert "the lateral limit 2 N, or the force across where the retract began" in rep.fault["message"]
    assert rep.fault["retract_blocked"] and not rep.fault["retracted"]


def test_the_leaving_trigger_fires_on_the_way_out_only():
    """leaving-depth-m=D: not on the way down through D, nor at D without having been deeper; on the way back up."""
    f = parse("nan-leaving-depth-m=0.002")
    assert f.text() == "nan-leaving-depth-m=0.002"

    class Arm:
        width_m = 0.07
        depth = 0.0

        def tip_in_tissue(self):
            return 0.035, self.depth
    arm, when = Arm(), trigger(f)
    fired = []
    for d in (-0.004, 0.001, 0.002, 0.003, 0.003, 0.0025, 0.002, 0.001):
        arm.depth = d
        fired.append(when(arm))
    assert fired == [False, False, False, False, False, False, True, True]


def test_run_json_keeps_the_limit_the_retract_used(tmp_path):
    """The retract's bounds are the plan's force limit (run.json's force_stop_threshold_n): a run with a limit of
    0.8 N faults on a 2 N pull that the default 2 N limit lets pass."""
    rep, *_ = _run(tmp_path, f"force-spike-leaving-depth-m={LEAVING}:-1.6", name="default")
    assert rep.status == "ok", rep.fault
    arm, c, r = make_sim(seed=3)
    inject_arm(arm, parse(f"force-spike-leaving-depth-m={LEAVING}:-1.6"))
    rep = run_plan(make_plan(XS, depth_m=0.003, limits=Limits(force_limit_n=0.8)), c, r, tmp_path / "low")
    assert rep.fault["kind"] == "retract_force", rep.fault


class _Driver:
    """What the watch reads of a driver (robot.driver.Driver), and its stop and fault calls recorded."""

    def __init__(self, zeroed: bool):
        self.lim = Limits()
        self.lat_limit_n = 2.0
        self.contact_thr = 0.02
        self.cfg = DriverConfig()
        self.zeroed_ts = 0.0 if zeroed else None
        self.retract_blocked = ""
        self.stopped = 0

    def _stop(self):
        self.stopped += 1

    def _lateral(self, lat, limit, filt, where, *args, **kwargs):
        self._stop()
        raise ProbeFault("lateral_force", where)


@settings(max_examples=200, deadline=None)
@given(zeroed=st.booleans(), watched=st.booleans(), n=st.integers(1, 40), seed=st.integers(0, 2 ** 31 - 1),
       scale=st.sampled_from([0.5, 3.0]))
def test_the_block_path_stops_where_the_period_path_does(zeroed, watched, n, seed, scale):
    """``quiet`` on a block of periods (the fast-forward) finds the first period whose reading ``__call__`` stops on
    (a fault), the same for any forces."""
    rng = np.random.default_rng(seed)
    filt, lat = rng.normal(0.0, scale, n) + rng.normal(0.0, 1.0), np.abs(rng.normal(0.0, scale, n))
    one, block = (_RetractWatch(_Driver(zeroed), zeroed, watched) for _ in range(2))
    first = None
    for k in range(n):
        try:
            one({"filt": float(filt[k]), "lat": float(lat[k])})
        except ProbeFault:
            first = k
            break
    w = DriverConfig().filter_window
    for k in range(min(w, n)):         # where the retract began: read one period at a time (quiet takes none)
        b = _Block(*[np.zeros(1)] * 4, filt[k:k + 1], lat[k:k + 1], *[np.zeros(1)] * 3, [0])
        assert block.quiet(b, 1) == 0
        try:
            block({"filt": float(filt[k]), "lat": float(lat[k])})
        except ProbeFault:             # (judged against the limits (watched), or the last of them: bounds set)
            assert first == k and (watched or k == w - 1)
            return
    if n <= w:
        assert first is None
        return
    rest = slice(w, n)
    b = _Block(*[np.zeros(n - w)] * 4, filt[rest], lat[rest], *[np.zeros(n - w)] * 3, [0] * (n - w))
    k = block.quiet(b, n - w)
    assert k == (n - w if first is None else first - w)
