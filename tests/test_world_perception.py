"""What the ego perceives (datagen/world/perception.py), pure: no SUMO.

The ego drives east along y = 0 from x = 0; its path is a 100 m straight line. A crossing
":J_c0_0" runs north from (20, -6) to (20, 6), across the path 20 m ahead.
"""

import math

import numpy as np
import pytest
import shapely

from datagen.world import perception, route
from datagen.world.fleet import EGO_DIMS_M
from datagen.world.route import Lane
from datagen.world.sumo import AgentReading, Leader

PATH = route.Path(np.array([[0.0, 0.0], [100.0, 0.0]]), np.array([0.0, 100.0]), (60.0,), ())
CROSSING = ":J_c0_0"


class Net:
    def lane(self, lane_id):
        assert lane_id == CROSSING
        return Lane(np.array([[20.0, -6.0], [20.0, 6.0]]), 12.0, 2.78)


def _kerb(lane_id):
    return perception.is_kerb(lane_id, ("pedestrian",) if lane_id == "side_0" else ("passenger",))


def _ped(x, y, yaw, speed, lane, next_edge=""):
    return AgentReading("p1", "ped", (x, y), yaw, speed, lane, next_edge)


def _car(x, y, yaw, speed, lane="road_0"):
    return AgentReading("v1", "car", (x, y), yaw, speed, lane)


def _crossing(*agents, ego_speed=8.0):
    return perception.crossing_obstacles(agents, Net(), _kerb, PATH, ego_speed)


def test_kerb_is_a_walking_area_or_a_pedestrian_only_lane():
    assert perception.is_kerb(":J_w0_0", None) and not perception.is_kerb(":J_c0_0", None)
    assert perception.is_kerb("side_0", ("pedestrian",))
    assert not perception.is_kerb("road_0", ("passenger", "pedestrian"))
    assert perception.is_crossing(CROSSING) and not perception.is_crossing(":J_3_0")


def test_vehicle_on_the_path_ahead_is_an_obstacle_with_its_speed_along_the_path():
    # a car whose rear is 30 m ahead (front bumper at x = 30 + 4.5), driving east at 5 m/s
    car = _car(34.5, 0.3, 0.0, 5.0)
    (o,) = perception.obstacles([car], _kerb, False, PATH, None)
    assert o.kind == "vehicle" and o.speed_mps == pytest.approx(5.0)
    assert o.distance_m == pytest.approx(30.0)  # to its rear bumper
    # one lane over (3.2 m to the left) it is not in the way
    assert perception.obstacles([_car(34.5, 3.2, 0.0, 5.0)], _kerb, False, PATH, None) == []


def test_a_skewed_bus_beside_the_ego_is_on_its_path_only_by_the_part_ahead_in_the_corridor():
    # spider, build seed 0, episode 33: a 12 m bus 3 degrees off the opposite direction, its
    # centre 2.8 m left; its corner near the ego's lane lies 5.7 m behind the ego's front
    # (beside the car), where braking cannot help: the loose extents made it a -5.9 m obstacle,
    # the ego stopped, and the turning bus hit its rear ("v214 hit ego (junction)")
    yaw = math.radians(180.0 + 3.0)
    centre = np.array([0.2, 2.8])
    front = centre + 6.0 * np.array([math.cos(yaw), math.sin(yaw)])
    bus = AgentReading("v214", "bus", tuple(front), yaw, 3.0, ":J_2_0")
    assert perception.obstacles([bus], _kerb, False, PATH, None) == []
    span = perception.corridor_span(centre, yaw, 12.0, 2.55, PATH, 0.5 * EGO_DIMS_M[1] + 0.35)
    assert span is not None and span[1] < 0.0  # the sliver in the corridor is behind the front
    # the same bus turned 25 degrees across the path ahead is an obstacle where it enters it
    yaw = math.radians(180.0 - 25.0)
    centre = np.array([12.0, 3.0])
    front = centre + 6.0 * np.array([math.cos(yaw), math.sin(yaw)])
    bus = AgentReading("v214", "bus", tuple(front), yaw, 3.0, ":J_2_0")
    (o,) = perception.obstacles([bus], _kerb, False, PATH, None)
    lo, hi = perception.corridor_span(centre, yaw, 12.0, 2.55, PATH, 0.5 * EGO_DIMS_M[1] + 0.35)
    assert o.distance_m == pytest.approx(lo) and 0.0 < lo < hi


def test_corridor_span_of_an_aligned_box_is_its_length():
    assert perception.corridor_span(np.array([20.0, 0.5]), 0.0, 4.5, 1.8, PATH, 1.3) == (
        pytest.approx(17.75),
        pytest.approx(22.25),
    )
    assert perception.corridor_span(np.array([20.0, -3.2]), 0.0, 4.5, 1.8, PATH, 1.3) is None


def _shapely_extent(corners, half_width_m):
    inside = shapely.Polygon(corners).intersection(
        shapely.box(-1e6, -half_width_m, 1e6, half_width_m)
    )
    return None if inside.is_empty else tuple(float(v) for v in inside.bounds[::2])


def band_cases(n: int, seed: int = 0):
    """Random boxes in a path's frame around a 1.275 m corridor, as corridor_span builds them:
    aligned, skewed and across, some with a corner on the border."""
    rng = np.random.default_rng(seed)
    hw = 0.5 * EGO_DIMS_M[1] + 0.35
    for k in range(n):
        along0, lat0 = rng.uniform(-30.0, 120.0), rng.uniform(-6.0, 6.0)
        rel = (0.0, math.pi, rng.normal(0.0, 0.05), rng.uniform(-math.pi, math.pi))[k % 4]
        half_l, half_w = rng.choice([2.25, 2.45, 2.8, 4.25, 6.0, 0.85]), rng.uniform(0.3, 1.3)
        corners = perception.path_box(along0, lat0, rel, half_l, half_w)
        if k % 7 == 0:  # move a corner onto the border
            x, y = corners[0]
            corners = [(cx, cy + hw - y) for cx, cy in corners]
        yield corners, hw


def test_band_extent_is_shapelys_bit_for_bit_where_it_is_sure():
    n_sure = 0
    for corners, hw in band_cases(4000):
        sure, span = perception.band_extent(corners, hw)
        if sure:
            n_sure += 1
            assert span == _shapely_extent(corners, hw)
    assert n_sure > 2000  # the fast path is the common one


def test_leader_gap_gets_back_the_ego_min_gap():
    (o,) = perception.obstacles([], _kerb, False, PATH, Leader("v9", 12.0, 3.0))
    assert (o.distance_m, o.speed_mps, o.track_id) == (13.0, 3.0, "lead:v9")


def test_person_at_the_kerb_counts_only_where_they_will_be():
    standing = _ped(30.0, 2.0, -math.pi / 2, 0.0, "side_0")
    assert perception.obstacles([standing], _kerb, False, PATH, None) == []
    walking_in = _ped(30.0, 2.0, -math.pi / 2, 1.2, "side_0")  # on the road within 1-2 s
    obs = perception.obstacles([walking_in], _kerb, False, PATH, None)  # at 1 s and/or 2 s
    assert obs and all(o.kind == "pedestrian" and 29.0 < o.distance_m < 31.0 for o in obs)
    # inside a junction the ego does not brake for someone still on the kerb
    assert perception.obstacles([walking_in], _kerb, True, PATH, None) == []


def _right_turn(radius=6.0):
    """5 m east, a quarter circle of `radius` turning right (centre (5, -radius)), 30 m south."""
    th = np.linspace(0.0, math.pi / 2, 40)
    arc = np.stack([5.0 + radius * np.sin(th), -radius + radius * np.cos(th)], 1)
    pts = np.vstack([[0.0, 0.0], arc, arc[-1] + [0.0, -30.0]])
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
    return route.Path(pts, s, (), ())


def test_person_standing_at_the_kerb_inside_a_turn_is_swept_by_the_body():
    # 1.3 m from the front's path at the corner: the front clears them, the car's body (the
    # chord from its front back one length, as SUMO's box) cuts the corner and would not
    path = _right_turn()
    c, r = np.array([5.0, -6.0]), 6.0
    diag = np.array([math.sqrt(0.5), math.sqrt(0.5)])
    inside = _ped(*(c + (r - 1.3) * diag), -math.pi / 4, 0.0, "side_0")
    obs = perception.obstacles([inside], _kerb, True, path, None)
    assert [o.kind for o in obs] == ["pedestrian"] and 2.0 < obs[0].distance_m < 12.0
    outside = _ped(*(c + (r + 1.9) * diag), -math.pi / 4, 0.0, "side_0")
    assert perception.obstacles([outside], _kerb, True, path, None) == []
    # beside a straight path the body is the front's path: 0.8 m off is under it, 2 m is not
    assert perception.obstacles([_ped(30.0, 0.8, 0.0, 0.0, "side_0")], _kerb, False, PATH, None)
    assert (
        perception.obstacles([_ped(30.0, 2.0, 0.0, 0.0, "side_0")], _kerb, False, PATH, None) == []
    )


def test_swept_contact_is_where_the_front_has_travelled_at_first_touch():
    pts = np.array([[20.0, 1.0], [-2.0, 1.0], [-2.0, 1.3], [20.0, 1.3], [20.0, 3.0]])
    far = perception.swept_contact(pts, np.full(5, 0.25), PATH, 4.7, 0.9, clearance_m=0.3)
    # ahead, 1 m off (within 0.9 + 0.25): touched when the front is within 0.57 m of x = 20
    assert 19.0 <= far[0] <= 20.0
    assert far[1] == 0.0  # touching the body now: hold
    assert far[2] == math.inf  # beside the body within the clearance, left behind: go
    assert far[0] < far[3] <= 20.0  # ahead within the clearance: held before touching
    assert far[4] == math.inf  # 3 m off never touches


def test_person_on_the_crossing_walking_towards_the_path_is_yielded_to():
    ped = _ped(20.0, -4.0, math.pi / 2, 1.2, CROSSING)  # 4 m south of the path, walking north
    (o,) = _crossing(ped)
    assert o.kind == "pedestrian" and o.distance_m == pytest.approx(20.0 - 2.0)


def test_person_past_the_corridor_or_standing_off_it_is_not():
    band = 0.5 * EGO_DIMS_M[1] + perception.CORRIDOR_SLACK_M
    assert _crossing(_ped(20.0, band + 0.5, math.pi / 2, 1.2, CROSSING)) == []  # walking away
    assert _crossing(_ped(20.0, -4.0, math.pi / 2, 0.0, CROSSING)) == []  # standing, off it
    assert len(_crossing(_ped(20.0, 0.5, math.pi / 2, 0.0, CROSSING))) == 1  # standing in it


def test_person_about_to_step_onto_the_crossing_from_the_kerb():
    ped = _ped(20.5, -7.0, math.pi / 2, 1.2, ":J_w0_0", next_edge=":J_c0")
    (o,) = _crossing(ped)
    assert o.track_id == "p1" and o.distance_m == pytest.approx(18.0)
    # walking elsewhere, or still far from the crossing: not yet
    assert _crossing(_ped(20.5, -7.0, math.pi / 2, 1.2, ":J_w0_0", next_edge="other")) == []
    assert _crossing(_ped(20.5, -12.0, math.pi / 2, 1.2, ":J_w0_0", next_edge=":J_c0")) == []
    # inside a junction only people already on the crossing count
    inside = perception.crossing_obstacles([ped], Net(), _kerb, PATH, 8.0, ego_in_junction=True)
    assert inside == []
    on_it = _ped(20.0, -4.0, math.pi / 2, 1.2, CROSSING)
    assert perception.crossing_obstacles([on_it], Net(), _kerb, PATH, 8.0, ego_in_junction=True)


def test_ego_goes_first_only_when_it_clears_the_crossing_well_before_them():
    ped = _ped(20.0, -5.9, math.pi / 2, 0.6, CROSSING)  # slow, 5.9 m from the path
    # at 14 m/s the ego clears the crossing (20 + 2 + 4.7 m) in 1.9 s; they need 6.6 s
    assert _crossing(ped, ego_speed=14.0) == []
    assert len(_crossing(ped, ego_speed=2.0)) == 1  # 13 s: yield


def test_crossing_behind_the_ego_is_ignored():
    behind = route.Path(np.array([[30.0, 0.0], [130.0, 0.0]]), np.array([0.0, 100.0]), (), ())
    ped = _ped(20.0, -1.0, math.pi / 2, 1.2, CROSSING)
    assert perception.crossing_obstacles([ped], Net(), _kerb, behind, 8.0) == []


def test_junction_clear_ignores_people_on_crossings():
    assert perception.junction_clear([_ped(0, 0, 0, 1, ":J_c0_0")], "J", _kerb)
    assert perception.junction_clear([_ped(0, 0, 0, 1, ":J_w1_0")], "J", _kerb)
    assert not perception.junction_clear([_car(0, 0, 0, 1, ":J_3_0")], "J", _kerb)
    assert perception.junction_clear([_car(0, 0, 0, 1, ":K_3_0")], "J", _kerb)


def test_hold_attribution():
    ped = _ped(10.0, 2.0, 0.0, 0.0, "side_0")
    assert perception.attribute_hold(5.0, PATH, [], False, ()) == "stop_sign"
    assert perception.attribute_hold(None, PATH, [ped], False, ()) == "pedestrian"
    assert perception.attribute_hold(None, PATH, [], False, (30.0,)) == "junction"
    assert perception.attribute_hold(None, PATH, [], False, (80.0,)) == "vehicle"


class Junction(Net):
    """Edges "in_x" lead to junction J, "away" elsewhere; every lane ends at (0, 0)."""

    def lane(self, lane_id):
        return Lane(np.array([[-50.0, 0.0], [0.0, 0.0]]), 50.0, 13.9)

    def to_junction(self, edge_id):
        return "J" if edge_id.startswith("in") else "K"


def test_foe_eta_is_the_soonest_other_vehicle_into_the_junction():
    cars = [
        _car(-40.0, 0.0, 0.0, 10.0, lane="in_a_0"),  # 40 m at 10 m/s: 4 s
        _car(-30.0, 0.0, 0.0, 5.0, lane="in_b_0"),  # 6 s
        _car(-5.0, 0.0, 0.0, 10.0, lane="own_0"),  # the ego's own edge: not a foe
        _car(-5.0, 0.0, 0.0, 0.5, lane="in_c_0"),  # standing: not a foe
        _car(-5.0, 0.0, 0.0, 10.0, lane="away_0"),  # to another junction
    ]
    assert perception.foe_eta_s(cars, Junction(), "J", "own") == pytest.approx(4.0)
    inside = [_car(0.0, 0.0, 0.0, 3.0, lane=":J_4_0")]
    assert perception.foe_eta_s(inside, Junction(), "J", "own") == 0.0
    assert perception.foe_eta_s(cars[2:], Junction(), "J", "own") is None


def test_a_car_standing_at_a_stop_line_is_a_foe_only_where_the_lane_has_a_stop_sign():
    stop_lanes = {"in_s_0"}.__contains__
    at_line = [_car(-2.0, 0.0, 0.0, 0.0, lane="in_s_0")]  # 2 m before a stop line: may start
    assert perception.foe_eta_s(at_line, Junction(), "J", "own", stop_lanes) == 0.0
    assert perception.foe_eta_s(at_line, Junction(), "J", "own") is None  # not asked for
    queued = [_car(-8.0, 0.0, 0.0, 0.0, lane="in_s_0")]  # further back, in the queue
    assert perception.foe_eta_s(queued, Junction(), "J", "own", stop_lanes) is None
    no_sign = [_car(-2.0, 0.0, 0.0, 0.0, lane="in_a_0")]  # waiting where no stop sign is
    assert perception.foe_eta_s(no_sign, Junction(), "J", "own", stop_lanes) is None
    inside = [_car(0.0, 0.0, 0.0, 0.0, lane=":J_4_0")]  # standing inside: as before, not
    assert perception.foe_eta_s(inside, Junction(), "J", "own", stop_lanes) is None


def test_side_of_the_path_has_numpys_sign_also_right_beside_it():
    rng = np.random.default_rng(1)
    for _ in range(500):
        pts = np.cumsum(rng.normal(0.0, 10.0, (int(rng.integers(2, 10)), 2)), 0) + 300.0
        seg = np.diff(pts, axis=0)
        s = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
        path = route.Path(pts, s, (), ())
        xy = pts[0] + rng.normal(0.0, 30.0, (6, 2))
        xy[0] = pts[int(rng.integers(0, len(pts)))] + rng.normal(0.0, 1e-7, 2)  # on the path
        along, _, head = route.project(xy, pts, s)
        for q, a, h in zip(xy, along, head):
            exact = perception._exact_side(q, float(a), float(h), path)
            side = perception._side(q, float(a), float(h), path)
            assert abs(side) <= perception.BAND_SURE_M or side * exact > 0.0
