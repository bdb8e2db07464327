"""Closed-loop evaluation, the parts that need no SUMO: scoring, PID and kinematics, box
geometry, and the infraction tracker on scripted ground truth."""

import math
from dataclasses import replace

import numpy as np
import pytest
import shapely

from datagen.state import AgentState, FrameState, Pose
from drive import score
from drive.controller import (
    Control,
    Controller,
    Creep,
    CreepConfig,
    Plan,
    VehicleConfig,
    VehicleState,
    bicycle_step,
    safety_box_clear,
)
from drive.geometry import RouteGeometry, StopLine
from drive.infractions import InfractionTracker, time_to_collision
from drive.layout import Layout, boxes_overlap
from schemas.dataset import box_corners

_NO_DRAG = VehicleConfig(coast_decel_mps2=0.0)

# --- scoring ---------------------------------------------------------------------------------


def test_penalties_are_the_leaderboard_table():
    assert score.PENALTIES == {
        "collision_pedestrian": 0.50,
        "collision_vehicle": 0.60,
        "collision_layout": 0.65,
        "red_light": 0.70,
        "stop_sign": 0.80,
    }


def test_driving_score_multiplies_completion_by_penalties_and_off_route_share():
    s = score.score_route(50.0, {"collision_vehicle": 2, "red_light": 1}, 0.1, 1000.0)
    assert s.infraction_score == pytest.approx(0.6**2 * 0.7 * 0.9)
    assert s.ds == pytest.approx(50.0 * 0.6**2 * 0.7 * 0.9)
    assert s.km_driven == pytest.approx(0.5)
    almost = score.score_route(99.5, {}, 0.0, 300.0)
    assert almost.rc == 99.5 and almost.ds == 99.5  # only the tracker grants 100 (complete)
    assert score.score_route(80.0, {"route_timeout": 1}, 0.0, 300.0).ds == 80.0  # no penalty
    with pytest.raises(ValueError, match="unknown infraction"):
        score.score_route(10.0, {"speeding": 1}, 0.0, 100.0)


def test_benchmark_ds_is_the_mean_of_route_scores_not_mean_rc_times_mean_is():
    a = score.score_route(100.0, {"collision_pedestrian": 1}, 0.0, 1000.0)  # DS 50
    b = score.score_route(20.0, {}, 0.0, 1000.0)  # DS 20
    s = score.summarise([a, b])
    assert s.ds == pytest.approx(35.0)
    assert s.rc * s.is_ / 100 != pytest.approx(s.ds)
    # per km: 1 event / 1 km and 0 / 0.2 km, averaged over routes
    assert s.per_km["collision_pedestrian"] == pytest.approx(0.5)
    assert s.ds_ci > 0 and score.ci95([3.0]) == 0.0
    table = score.format_table([("x", s)])
    assert "Ped" in table and "Block" in table and "35.00" in table


def test_route_timeout_follows_the_leaderboard_estimate():
    assert score.route_timeout_s(1000.0) == pytest.approx(5.0 + 0.8 * 1000.0)


# --- controller and kinematics ---------------------------------------------------------------


def test_bicycle_goes_straight_without_steering_and_turns_left_with_positive_steer():
    s = VehicleState(Pose(0.0, 0.0, 0.0), 10.0)
    s1 = bicycle_step(s, Control(0.0, 0.0, False), 0.1)
    assert s1.pose.y_m == pytest.approx(0.0) and 0.9 < s1.pose.x_m < 1.0
    left = bicycle_step(s, Control(0.5, 0.0, False), 0.1)
    assert left.pose.yaw_rad > 0 and left.pose.y_m > 0
    braked = s
    for _ in range(30):
        braked = bicycle_step(braked, Control(0.0, 0.0, True), 0.1)
    assert braked.speed_mps == 0.0  # never reverses


def test_bicycle_circle_radius_matches_the_kinematic_model():
    # steady turn of the box centre: R = l_r / sin(beta), centre square to the velocity
    s = VehicleState(Pose(0.0, 0.0, 0.0), 5.0)
    pts = []
    for _ in range(400):
        s = bicycle_step(s, Control(0.3, 0.0, False), 0.05, vehicle=_NO_DRAG)
        pts.append((s.pose.x_m, s.pose.y_m))
    pts = np.array(pts)
    delta = 0.3 * _NO_DRAG.max_steer_rad
    beta = math.atan(0.5 * math.tan(delta))
    radius = _NO_DRAG.rear_to_centre_m / math.sin(beta)
    centre = radius * np.array([-math.sin(beta), math.cos(beta)])
    r = np.hypot(*(pts - centre).T)
    assert np.allclose(r, radius, rtol=0.02)


def test_pid_tracks_straight_waypoints_to_their_speed():
    ctrl = Controller()
    s = VehicleState(Pose(0.0, 0.0, 0.0), 0.0)
    wps = np.array([[4.0 * t, 0.0] for t in (0.5, 1.0, 1.5, 2.0)])  # 4 m/s straight
    for _ in range(200):
        c = ctrl.control(s.pose.ego_from_world(s.pose.world_from_ego(wps)), s.speed_mps)
        s = bicycle_step(s, c, 0.1)
    assert s.speed_mps == pytest.approx(4.0, abs=0.5)
    assert abs(s.pose.y_m) < 1e-6


def test_pid_steers_onto_a_lateral_offset_line():
    ctrl = Controller()
    s = VehicleState(Pose(0.0, 2.0, 0.0), 6.0)  # 2 m left of the line y = 0
    for _ in range(150):
        # waypoints on y = 0 ahead of the ego, 0.5 s apart at 6 m/s
        x0 = s.pose.x_m
        world = np.array([[x0 + 3.0 * k, 0.0] for k in (1, 2, 3, 4)])
        c = ctrl.control(s.pose.ego_from_world(world), s.speed_mps)
        s = bicycle_step(s, c, 0.1)
    assert abs(s.pose.y_m) < 0.3 and abs(s.pose.yaw_rad) < 0.1


def test_plan_held_in_world_frame_is_transfusers_two_waypoints_when_fresh():
    pose = Pose(10.0, 5.0, math.pi / 2)
    wps = np.array([[2.0, 0.0], [4.0, 0.5], [6.0, 1.0], [8.0, 1.5]])
    plan = Plan.from_ego(3.0, pose, wps)
    assert np.allclose(plan.at(3.0, pose), wps[:2])
    # 0.25 s later, from the same pose, the points have moved half a waypoint on
    later = plan.at(3.25, pose)
    assert np.allclose(later[0], 0.5 * (wps[0] + wps[1]))


def _stand_and_creep(clear_ahead, steps: int):
    """A plan that stands still, with the creep: (speeds per step, creeps started)."""
    ctrl, creep = Controller(), Creep(step_s=0.1)
    s = VehicleState(Pose(0.0, 0.0, 0.0), 0.0)
    speeds = []
    for k in range(steps):
        push = creep.step(s.speed_mps, clear_ahead(k))
        s = bicycle_step(s, ctrl.control(np.zeros((4, 2)), s.speed_mps, creep_throttle=push), 0.1)
        speeds.append(s.speed_mps)
    return np.array(speeds), creep.creeps, s


def test_a_car_that_stood_55_s_creeps_for_1_5_s_and_stops_again():
    speeds, creeps, end = _stand_and_creep(lambda k: True, 700)  # 70 s
    moving = np.flatnonzero(speeds > 0.0)
    assert creeps == 1
    assert moving[0] == 549  # the 550th step: 55 s of standing
    assert 15 <= len(moving) <= 25  # 1.5 s of push, then the plan's brake stops it
    # throttle 0.4 x 4 m/s2 for 1.5 s: 2.4 m/s, about 1.8 m, then 6 m/s2 of braking
    assert speeds.max() == pytest.approx(2.4, abs=0.05)
    assert 1.5 < end.pose.x_m < 3.0 and abs(end.pose.y_m) < 1e-9


def test_no_creep_while_the_safety_box_holds_something_and_a_filling_box_stops_it():
    speeds, creeps, end = _stand_and_creep(lambda k: False, 700)
    assert creeps == 0 and speeds.max() == 0.0
    # clear when due, then an obstacle appears 0.5 s into the creep
    speeds, creeps, end = _stand_and_creep(lambda k: k < 555, 700)
    assert creeps == 1 and end.pose.x_m < 0.5 * 1.8


def test_creep_comes_again_after_another_55_s_of_standing():
    _, creeps, end = _stand_and_creep(lambda k: True, 1150)  # 115 s
    assert creeps == 2 and end.pose.x_m > 3.0


def test_safety_box_is_just_ahead_of_the_bumper_and_ignores_ground_and_overhead():
    cfg = CreepConfig()
    pose = Pose(10.0, 20.0, math.pi / 2)  # facing +y; the car is 4.5 m x 1.8 m
    ahead = 2.25 + 2.0  # 2 m past the front bumper

    def clear(x_ego, y_ego, z):
        world = pose.world_from_ego(np.array([[x_ego, y_ego]]))[0]
        return safety_box_clear(np.array([[*world, z]]), pose, 4.5, 1.8, cfg)

    assert not clear(ahead, 0.0, 1.0)
    assert not clear(ahead, 1.05, 1.0)  # within the 0.2 m side margin
    assert clear(ahead, 1.2, 1.0)  # beside the box
    assert clear(ahead, 0.0, 0.2) and clear(ahead, 0.0, 3.0)  # ground, overhead
    assert clear(2.25 + 4.5, 0.0, 1.0) and clear(-ahead, 0.0, 1.0)  # beyond it, behind
    assert clear(0.0, 0.0, 1.0)  # inside the car itself: not ahead of its front
    assert safety_box_clear(np.zeros((0, 3)), pose, 4.5, 1.8, cfg)


# --- geometry --------------------------------------------------------------------------------


def test_box_overlap_separating_axes():
    a = box_corners(0.0, 0.0, 0.0, 4.0, 2.0)
    b = np.stack(
        [
            box_corners(3.9, 0.0, 0.0, 4.0, 2.0),  # overlaps by 0.1 m
            box_corners(4.1, 0.0, 0.0, 4.0, 2.0),  # 0.1 m apart
            box_corners(4.0, 3.5, math.pi / 4, 4.0, 2.0),  # diagonal, apart
            box_corners(2.0, 1.5, math.pi / 4, 4.0, 2.0),  # diagonal, corner inside
        ]
    )
    assert boxes_overlap(a, b).tolist() == [True, False, False, True]
    ref = [shapely.Polygon(a).intersects(shapely.Polygon(q)) for q in b]
    assert boxes_overlap(a, b).tolist() == ref


def _agent(tid, x, y, yaw=0.0, speed=0.0, cls="vehicle", length=4.5, width=1.8):
    return AgentState(tid, cls, Pose(x, y, yaw), length, width, 1.5, speed)


def test_time_to_collision_of_a_closing_pair_and_none_for_parallel_lanes():
    ego = _agent("ego", 0.0, 0.0, speed=10.0, length=4.7, width=1.85)
    ahead = _agent("a", 24.6, 0.0, speed=0.0)  # gap 24.6 - 2.35 - 2.25 = 20 m at 10 m/s
    assert time_to_collision(ego, [ahead]) == pytest.approx(2.0, abs=0.11)
    beside = _agent("b", 5.0, 3.5, speed=10.0)
    assert time_to_collision(ego, [beside]) == math.inf


# --- the tracker on scripted ground truth ------------------------------------------------------


def _straight_route(length=200.0, lights=(), stops=()):
    """A route along y = 0 from x = 0 to `length`, a 3.2 m lane, optional stop lines."""
    xs = np.linspace(0.0, length, 41)
    centre = np.stack([xs, np.zeros_like(xs)], 1)
    lane = shapely.LineString(centre).buffer(1.6, cap_style=2)
    shapely.prepare(lane)
    east = np.array([1.0, 0.0])
    lines = [
        StopLine("light", s, "J", np.array([[s, 1.6], [s, -1.6]]), None, east, "J", ((0,),))
        for s in lights
    ]
    lines += [StopLine("stop", s, "K", np.array([[s, 1.6], [s, -1.6]])) for s in stops]
    lines.sort(key=lambda ln: ln.s_m)
    return RouteGeometry(("e",), centre, xs.copy(), tuple(lines), lane, 1)


def _layout():
    road = [shapely.box(-50, -5, 300, 5)]
    kerb = [shapely.box(-50, 5, 300, 8), shapely.box(-50, -8, 300, -5)]
    building = [shapely.box(100, 9, 120, 30)]
    return Layout(road, kerb, building)


def _frame(
    t, x, y=0.0, yaw=0.0, speed=10.0, agents=(), light="none", light_d=None, stop_d=None, sig=""
):
    """The ego's box centre at (x, y); `sig`: the state of traffic light J's one link."""
    ego = AgentState("ego", "vehicle", Pose(x, y, yaw), 4.7, 1.85, 1.5, speed)
    return FrameState(
        time_s=t,
        ego=ego,
        agents=tuple(agents),
        command="follow",
        target_point_xy_m=(x + 30.0, 0.0),
        traffic_light=light,
        light_distance_m=light_d,
        stop_sign=stop_d is not None,
        stop_distance_m=stop_d,
        expert_reason="none",
        signals=(("J", sig),) if sig else (),
    )


def _drive(tracker, frames):
    for f in frames:
        tracker.step(f)
        if tracker.ended:
            break
    return tracker


def test_driving_through_a_red_light_is_one_red_light_infraction():
    geom = _straight_route(lights=(100.0,))
    frames = [_frame(k * 0.1, 10.0 + k * 1.0, sig="r") for k in range(150)]  # 10 m/s
    t = _drive(InfractionTracker(geom, _layout()), frames)
    assert t.counts() == {"red_light": 1}
    assert t.events[0].x_m == pytest.approx(98.0)  # the front (centre + 2.35 m) crossed at 100
    # the same drive on green is clean, and so is one where only another light is red
    green = [_frame(k * 0.1, 10.0 + k * 1.0, sig="G") for k in range(150)]
    assert _drive(InfractionTracker(geom, _layout()), green).counts() == {}
    other = [replace(f, signals=(("J", "G"), ("X", "r"))) for f in frames]
    assert _drive(InfractionTracker(geom, _layout()), other).counts() == {}


def test_a_red_light_run_beside_the_lane_is_counted_and_the_state_is_read_before_crossing():
    geom = _straight_route(lights=(100.0,))
    # the box centre 1.9 m left of the lane's centre: centre and left corner beside the line,
    # the right front corner (0.925 m right of the centre) crosses it
    frames = [_frame(k * 0.1, 10.0 + k * 1.0, y=1.9, sig="r") for k in range(150)]
    assert _drive(InfractionTracker(geom, _layout()), frames).counts() == {"red_light": 1}
    # fully beside it (3 m left): no crossing of this line, nothing to judge
    beside = [_frame(k * 0.1, 10.0 + k * 1.0, y=3.0, sig="r") for k in range(150)]
    assert "red_light" not in _drive(InfractionTracker(geom, _layout()), beside).counts()
    # red only from the step the front crosses: it saw green before, no infraction
    crossing = int(100.0 - 2.35 - 10.0) + 1  # first step with the front past x = 100
    late = [
        replace(f, signals=(("J", "r" if k >= crossing else "G"),)) for k, f in enumerate(frames)
    ]
    assert _drive(InfractionTracker(geom, _layout()), late).counts() == {}
    early = [
        replace(f, signals=(("J", "r" if k >= crossing - 1 else "G"),))
        for k, f in enumerate(frames)
    ]
    assert _drive(InfractionTracker(geom, _layout()), early).counts() == {"red_light": 1}
    # driving back over the line the wrong way is no crossing
    back = [_frame(k * 0.1, 160.0 - k * 1.0, yaw=math.pi, sig="r") for k in range(150)]
    assert "red_light" not in _drive(InfractionTracker(geom, _layout()), back).counts()


def test_stop_sign_passed_without_stopping_counts_and_a_full_stop_does_not():
    geom = _straight_route(stops=(100.0,))
    rolling = [_frame(k * 0.1, 10.0 + k, speed=10.0) for k in range(150)]
    assert _drive(InfractionTracker(geom, _layout()), rolling).counts() == {"stop_sign": 1}
    # stop 1 m before the line (front at 99 m), wait, go on
    xs = list(np.arange(10.0, 96.65, 1.0)) + [96.65] * 20 + list(np.arange(97.0, 160.0, 1.0))
    frames = [_frame(k * 0.1, x, speed=0.0 if x == 96.65 else 10.0) for k, x in enumerate(xs)]
    assert _drive(InfractionTracker(geom, _layout()), frames).counts() == {}


def test_hitting_a_stopped_car_is_one_vehicle_collision_however_long_it_lasts():
    geom = _straight_route()
    parked = _agent("v1", 60.0, 0.0)
    frames = [_frame(k * 0.1, min(10.0 + k, 56.0), agents=[parked]) for k in range(80)]
    t = _drive(InfractionTracker(geom, _layout()), frames)
    assert t.counts() == {"collision_vehicle": 1}
    assert t.events[0].detail == "v1 (vehicle)"
    ped = _agent("p1", 60.0, 0.0, cls="pedestrian", length=0.4, width=0.5)
    frames = [_frame(k * 0.1, min(10.0 + k, 59.0), agents=[ped]) for k in range(80)]
    assert _drive(InfractionTracker(geom, _layout()), frames).counts() == {
        "collision_pedestrian": 1
    }


def test_leaving_the_road_is_off_road_and_a_kerb_collision_and_far_off_ends_the_route():
    geom = _straight_route()
    frames = []
    for k in range(200):  # drift left at 30 degrees from x = 20
        x = 20.0 + k * math.cos(0.5)
        y = k * math.sin(0.5)
        frames.append(_frame(k * 0.1, x, y, yaw=0.5))
    t = _drive(InfractionTracker(geom, _layout()), frames)
    c = t.counts()
    assert c["off_road"] == 1 and c["collision_layout"] == 1 and c["route_deviation"] == 1
    assert t.ended == "route_deviation"
    # the box centre leaves the route's 3.2 m lane before a wheel leaves the 10 m road
    assert 0.0 < t.off_road_share < t.off_route_share < 1.0


def test_a_clean_drive_completes_the_route_with_no_infractions():
    geom = _straight_route(lights=(100.0,))
    frames = [_frame(k * 0.1, 2.35 + k, light="green", light_d=None) for k in range(300)]
    t = _drive(InfractionTracker(geom, _layout()), frames)
    assert t.ended == "route_complete" and t.counts() == {}
    assert t.route_completion_pct == 100.0


def test_standing_still_for_90_s_is_agent_blocked():
    geom = _straight_route()
    frames = [_frame(k * 0.1, 20.0, speed=0.0) for k in range(1000)]
    t = _drive(InfractionTracker(geom, _layout()), frames)
    assert t.ended == "agent_blocked" and t.counts() == {"agent_blocked": 1}
    assert t.events[0].time_s == pytest.approx(90.0, abs=0.15)


def test_summary_of_hundreds_of_routes_is_the_mean_of_their_scores():
    from drive.summary import format_summary, summary_doc

    rng = np.random.default_rng(0)
    docs = []
    for i in range(400):
        counts = {k: int(rng.integers(0, 3)) for k in score.INFRACTION_TYPES}
        rc = float(rng.uniform(0, 100))
        s = score.score_route(rc, counts, float(rng.uniform(0, 0.2)), 500.0)
        docs.append(
            {
                "route": {"route_id": f"r{i}", "length_m": 500.0},
                "policy": "x",
                "rc": s.rc,
                "counts": s.counts,
                "off_route_share": s.off_route_share,
                "min_ttc_s": None if i % 3 else 1.5,
                "traffic_delay_s": float(i),
                "traffic_delay_rate": float(i) / 10.0,
                "sim_s": 10.0,
                "timing": {"total": 1.0},
            }
        )
    out = summary_doc("many", docs, baseline={d["route"]["route_id"]: d for d in docs[:10]})
    ds = [score.score_route(d["rc"], d["counts"], d["off_route_share"], 500.0).ds for d in docs]
    assert out["n_routes"] == 400 and out["ds"] == pytest.approx(np.mean(ds))
    assert out["traffic_delay_rate_vs_baseline_mean"] == 0.0
    assert out["min_ttc_s_median"] == 1.5
    assert "400 routes" in format_summary(out)


def test_a_bicycle_contact_is_a_vehicle_collision():
    geom = _straight_route()
    bike = _agent("b1", 60.0, 0.0, cls="bicycle", length=1.7, width=0.65)
    frames = [_frame(k * 0.1, min(10.0 + k, 58.0), agents=[bike]) for k in range(80)]
    t = _drive(InfractionTracker(geom, _layout()), frames)
    assert t.counts() == {"collision_vehicle": 1} and t.events[0].detail == "b1 (bicycle)"


def test_two_wheels_on_the_kerb_is_a_layout_collision_and_off_road():
    geom = _straight_route()
    # the road ends at y = 5; the ego's left wheels (0.775 m left of its centre) are on the
    # sidewalk from a centre at y > 4.225 m, its centre still 0.5 m on the road
    frames = [_frame(k * 0.1, 10.0 + k, y=4.5) for k in range(100)]
    t = _drive(InfractionTracker(geom, _layout()), frames)
    assert t.counts() == {"collision_layout": 1, "off_road": 1}, t.counts()
    assert t.events[0].detail == "kerb" and t.off_road_share > 0.9
    # 0.1 m further right, all four wheels on the road: clean (the body may overhang)
    inside = [_frame(k * 0.1, 10.0 + k, y=4.1) for k in range(100)]
    assert _drive(InfractionTracker(geom, _layout()), inside).counts() == {}


def test_stopping_20_m_short_of_the_end_does_not_complete_the_route():
    geom = _straight_route()  # 200 m, the front starts at 4.7 m
    end_x = 200.0 - 20.0 - 2.35  # the front stops 20 m short
    xs = [min(2.35 + k, end_x) for k in range(400)]
    frames = [_frame(k * 0.1, x, speed=0.0 if x == end_x else 10.0) for k, x in enumerate(xs)]
    t = _drive(InfractionTracker(geom, _layout()), frames)
    assert not t.complete and t.ended is None
    assert t.route_completion_pct == pytest.approx(100 * (180.0 - 4.7) / (200.0 - 4.7), abs=0.1)
    s = score.score_route(t.route_completion_pct, t.counts(), 0.0, geom.length_m)
    assert s.rc < 90.0 and s.ds < 90.0
    # 1 m short: over 99 % and within 10 m of the end, complete
    near = [_frame(k * 0.1, min(2.35 + k, 196.65)) for k in range(400)]
    t = _drive(InfractionTracker(geom, _layout()), near)
    assert t.complete and t.ended == "route_complete" and t.route_completion_pct == 100.0


def test_completion_needs_the_front_within_10_m_of_the_end():
    geom = _straight_route()
    # along the route 12 m to its side (closer than the 30 m deviation), past its end
    frames = [_frame(k * 0.1, 2.35 + k, y=12.0) for k in range(230)]
    t = _drive(InfractionTracker(geom, Layout([shapely.box(-50, -50, 300, 50)], [], [])), frames)
    assert not t.complete and t.route_completion_pct > 99.0


def test_a_shortcut_earns_no_progress_faster_than_the_front_moves():
    geom = _straight_route()
    # 40 m along, the ego jumps 25 m ahead along the route (a shortcut through a block): the
    # search reaches 15 m ahead of the progress so far, the jump earns 15 m; standing there,
    # progress creeps no further than the front moves (0 here) plus 0.1 m a step
    xs = [10.0 + k for k in range(30)] + [65.0 + k for k in range(5)]
    frames = [_frame(k * 0.1, x) for k, x in enumerate(xs)]
    t = InfractionTracker(geom, _layout())
    for f in frames[:30]:
        t.step(f)
    before = t.progress_m
    t.step(frames[30])
    assert t.progress_m == pytest.approx(before + 15.0)
    for k in range(5):
        t.step(_frame((31 + k) * 0.1, 65.0, speed=0.0))
    assert t.progress_m == pytest.approx(before + 15.0 + 0.1 * 5)
    # a long hop earns no more than 1.5 x the front's movement: 50 m ahead along the route
    t = InfractionTracker(geom, _layout())
    for f in frames[:30]:
        t.step(f)
    before = t.progress_m
    t.step(_frame(3.0, 39.0 + 8.0))  # the front moved 8 m: at most 12.1 m of progress
    assert t.progress_m == pytest.approx(before + 8.0)  # on the route, it earns what it drove


def test_progress_follows_a_lane_past_a_sideways_step_of_the_centreline():
    """The centreline steps 6.4 m sideways where the lane a junction passage enters is not the
    one the next connection leaves from (boulevard-long-09 at E3E4); the ego driving on in its
    own lane keeps gaining progress and completes the route."""
    pts = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 6.4], [300.0, 6.4]])
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
    lane = shapely.LineString(pts).buffer(1.6, cap_style=2)
    geom = RouteGeometry(("e",), pts, s, (), lane, 0)
    road = Layout([shapely.box(-50, -20, 350, 30)], [], [])
    frames = [_frame(k * 0.1, 2.35 + k) for k in range(320)]  # along y = 0 all the way
    t = _drive(InfractionTracker(geom, road), frames)
    assert t.ended == "route_complete" and "route_deviation" not in t.counts()


def test_collisions_are_debounced_as_the_leaderboard_does():
    geom = _straight_route()
    car = _agent("v1", 60.0, 0.0)
    # touch, back off 1 m, touch again 2 s later: the same agent within 5 s, at the same place
    xs = [min(10.0 + k, 56.0) for k in range(50)] + [55.0] * 10 + [56.0] * 20
    t = _drive(
        InfractionTracker(geom, _layout()),
        [_frame(k * 0.1, x, agents=[car]) for k, x in enumerate(xs)],
    )
    assert t.counts() == {"collision_vehicle": 1}
    # two different cars 20 m apart: two collisions
    cars = [_agent("v1", 60.0, 0.0), _agent("v2", 85.0, 0.0)]
    xs = [min(10.0 + k, 56.0) for k in range(50)] + [56.0 + 0.5 * k for k in range(60)]
    frames = [
        _frame(k * 0.1, x, agents=[c for c in cars if c.pose.x_m > x]) for k, x in enumerate(xs)
    ]
    t = _drive(InfractionTracker(geom, _layout()), frames)
    assert t.counts() == {"collision_vehicle": 2}
    # another agent driving into a standing ego at the place of its last collision: not again
    frames = [
        _frame(k * 0.1, 56.0, speed=0.0, agents=[car] if k < 5 else [_agent("v9", 51.0, 0.0)])
        for k in range(20)
    ]
    assert _drive(InfractionTracker(geom, _layout()), frames).counts() == {"collision_vehicle": 1}


def test_driving_a_third_of_the_route_over_15_m_off_it_is_a_route_deviation():
    geom = _straight_route()
    frames = [_frame(k * 0.1, 2.35 + k, y=20.0) for k in range(200)]
    t = _drive(InfractionTracker(geom, Layout([shapely.box(-50, -50, 300, 50)], [], [])), frames)
    assert t.ended == "route_deviation" and "driven over 15 m off it" in t.events[-1].detail
    assert t.far_m > 0.3 * 200.0


def test_repetitions_are_averaged_within_a_route_before_the_interval_over_routes():
    a0 = score.score_route(100.0, {}, 0.0, 1000.0, "a")  # route a: DS 100 and 50
    a1 = score.score_route(100.0, {"collision_pedestrian": 1}, 0.0, 1000.0, "a")
    b0 = score.score_route(20.0, {}, 0.0, 1000.0, "b")  # route b: DS 20 and 40
    b1 = score.score_route(40.0, {}, 0.0, 1000.0, "b")
    s = score.summarise([a0, b0, a1, b1])
    assert s.n_routes == 2 and s.n_drives == 4
    assert s.ds == pytest.approx((75.0 + 30.0) / 2)
    assert s.ds_ci == pytest.approx(score.ci95([75.0, 30.0]))  # two routes, not four drives
    assert s.per_km["collision_pedestrian"] == pytest.approx((0.5 + 0.0) / 2)
    assert s.km_driven == pytest.approx(1.0 + 1.0 + 0.2 + 0.4)


def test_a_failed_route_scores_zero_and_a_route_that_drove_nothing_has_no_rate():
    ok = score.score_route(100.0, {"collision_vehicle": 1}, 0.0, 500.0, "ok")  # 2 per km
    stuck = score.score_route(0.0, {"collision_vehicle": 1}, 0.0, 500.0, "stuck")
    failed = score.failed_route("crashed")
    s = score.summarise([ok, stuck, failed])
    assert s.n_routes == 3 and s.n_failed == 1
    assert s.ds == pytest.approx(60.0 / 3)
    # the stuck route drove 0 km: no rate (the leaderboard skips it), not 1000 per km
    assert s.per_km["collision_vehicle"] == pytest.approx(2.0)
    assert failed.ds == 0.0 and failed.rc == 0.0 and failed.infraction_score == 1.0


def test_a_front_stopping_on_the_line_has_not_crossed_it():
    """boulevard-long-03 at C5: SUMO stopped the expert with its front exactly on the stop line
    as the light turned red; 0.1 m past it is a crossing."""
    geom = _straight_route(lights=(100.0,))
    on_line = 100.0 - 2.35
    xs = [min(10.0 + k, on_line) for k in range(120)]
    frames = [
        _frame(k * 0.1, x, speed=0.0 if x == on_line else 10.0, sig="r") for k, x in enumerate(xs)
    ]
    assert _drive(InfractionTracker(geom, _layout()), frames).counts() == {}
    over = [_frame(k * 0.1, min(10.0 + k, on_line + 0.2), sig="r") for k in range(120)]
    assert _drive(InfractionTracker(geom, _layout()), over).counts() == {"red_light": 1}


def test_pure_pursuit_steers_a_circle_at_its_curvature():
    """On a circle of radius R through the rear axle, the wheel angle is atan(L / R)."""
    from drive.controller import ControllerConfig, VehicleConfig, pursuit_steer

    veh, radius = VehicleConfig(), 12.0
    rear = np.array([-veh.rear_to_centre_m, 0.0])
    a = np.linspace(0.0, 1.5, 400)  # a left turn starting at the rear axle, heading +x
    path = rear + radius * np.stack([np.sin(a), 1.0 - np.cos(a)], axis=1)
    steer = pursuit_steer(path, 5.0, ControllerConfig())
    assert steer * veh.max_steer_rad == pytest.approx(math.atan(veh.wheelbase_m / radius), rel=1e-3)
    assert pursuit_steer(path * [1.0, -1.0], 5.0, ControllerConfig()) == pytest.approx(-steer)


def test_pure_pursuit_drives_back_onto_a_line_beside_it():
    ctrl = Controller()  # pure pursuit: the default
    s = VehicleState(Pose(0.0, 2.0, 0.0), 6.0)  # 2 m left of the line y = 0
    for _ in range(150):
        x0 = s.pose.x_m
        world = np.array([[x0 + 3.0 * k, 0.0] for k in (0, 1, 2, 3, 4)])
        ahead = s.pose.ego_from_world(world)
        c = ctrl.control(ahead[1:3], s.speed_mps, path_ego=ahead)
        s = bicycle_step(s, c, 0.1)
    assert abs(s.pose.y_m) < 0.2 and abs(s.pose.yaw_rad) < 0.05


def test_plan_ahead_starts_where_the_plan_is_now():
    pose = Pose(0.0, 0.0, 0.0)
    wps = np.array([[2.0, 0.0], [4.0, 0.0], [6.0, 1.0], [8.0, 2.0]])
    plan = Plan.from_ego(0.0, pose, wps)
    np.testing.assert_allclose(plan.ahead(0.0, pose), np.vstack([[0.0, 0.0], wps]))
    later = plan.ahead(0.75, pose)  # between the first and second waypoint
    np.testing.assert_allclose(later, np.vstack([[3.0, 0.0], wps[1:]]))
