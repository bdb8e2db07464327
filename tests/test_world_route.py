"""The route ahead as pure geometry (datagen/world/route.py): no SUMO, a dict-backed network.

The toy network: lane A_0 runs east from (0, 0) to (100, 0); at junction J it either turns left
through internal lane :J_0_0 onto B_0 (north, from (105, 5) to (105, 105)) or goes straight
through :J_1_0 onto C_0 (east, from (110, 0) to (210, 0)).
"""

import math

import numpy as np
import pytest

from datagen.world import route
from datagen.world.route import Lane, Link


def _lane(*pts, speed=13.89):
    p = np.asarray(pts, dtype=np.float64)
    return Lane(p, float(np.hypot(*np.diff(p, axis=0).T).sum()), speed)


class ToyNet:
    def __init__(self):
        self.lanes = {
            "A_0": _lane((0, 0), (100, 0)),
            ":J_0_0": _lane((100, 0), (103.5, 1.5), (105, 5), speed=8.0),
            "B_0": _lane((105, 5), (105, 105), speed=8.33),
            ":J_1_0": _lane((100, 0), (110, 0)),
            "C_0": _lane((110, 0), (210, 0)),
        }
        self.out = {
            "A_0": (Link("B_0", ":J_0_0", "", "l"), Link("C_0", ":J_1_0", "", "s")),
            ":J_0_0": (Link("B_0", "", "", "l"),),
            ":J_1_0": (Link("C_0", "", "", "s"),),
        }

    def lane(self, lane_id):
        return self.lanes[lane_id]

    def links(self, lane_id):
        return self.out.get(lane_id, ())

    def allowed(self, lane_id):
        return ("passenger",)

    def lane_count(self, edge_id):
        return 1


NET = ToyNet()
LEFT = (Link("B_0", ":J_0_0", "G", "l"),)


def _path_left(pos=40.0):
    return route.path_ahead(NET, "A_0", pos, LEFT, (pos, 0.0), 0.0)


def test_cut_starts_at_the_position_along_the_lane():
    pts = route.cut(NET.lane("A_0"), 25.0)
    assert pts[0] == pytest.approx((25.0, 0.0))
    assert pts[-1] == pytest.approx((100.0, 0.0))
    assert len(route.cut(NET.lane("A_0"), 150.0)) == 1  # beyond the end: its last point


def test_project_gives_along_lateral_heading_and_negative_behind():
    pts = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    s = np.array([0.0, 10.0, 20.0])
    along, lat, head = route.project(np.array([[5.0, 2.0], [12.0, 5.0], [-3.0, 1.0]]), pts, s)
    assert along == pytest.approx([5.0, 15.0, -3.0])
    assert lat == pytest.approx([2.0, 2.0, 1.0])
    assert head[:2] == pytest.approx([0.0, math.pi / 2])


def test_path_ahead_runs_through_the_junction_onto_the_exit_lane():
    path = _path_left(40.0)
    assert path.pts[0] == pytest.approx((40.0, 0.0))
    assert path.s[0] == 0.0 and np.all(np.diff(path.s) > 0)
    assert path.link_dist == (pytest.approx(60.0),)
    assert [lane for _, lane in path.seg_lanes] == ["A_0", "B_0"]
    via = NET.lane(":J_0_0").length_m
    assert path.seg_lanes[1][0] == pytest.approx(60.0 + via)
    assert path.pts[-1] == pytest.approx((105.0, 105.0))
    assert path.s[-1] == pytest.approx(60.0 + via + 100.0, abs=1e-6)


def test_path_inside_a_junction_walks_out_to_the_exit_lane_first():
    path = route.path_ahead(NET, ":J_0_0", 1.0, (), (101.0, 0.5), 0.5)
    assert [lane for _, lane in path.seg_lanes] == [":J_0_0", "B_0"]
    assert path.pts[-1] == pytest.approx((105.0, 105.0))


def test_too_short_a_path_is_a_stub_along_the_heading():
    short = Lane(np.array([[0.0, 0.0], [0.1, 0.0]]), 0.1, 10.0)

    class One(ToyNet):
        def lane(self, lane_id):
            return short

    path = route.path_ahead(One(), "X_0", 0.0, (), (3.0, 4.0), math.pi / 2)
    assert path.pts == pytest.approx(np.array([[3.0, 4.0], [3.0, 5.0]]))


def test_turn_command_and_exit_target_within_range_then_sticky_inside_the_junction():
    far = _path_left(40.0)  # 60 m to the junction: beyond COMMAND_RANGE_M
    cmd, target, sticky = route.command_and_target(NET, "A_0", far, LEFT, None)
    assert cmd == "follow" and sticky is None
    assert target == pytest.approx((40.0 + route.TARGET_AHEAD_M, 0.0))
    near = _path_left(70.0)
    cmd, target, sticky = route.command_and_target(NET, "A_0", near, LEFT, None)
    assert cmd == "left" and sticky == ("J", "left", "B_0")
    assert target == pytest.approx((105.0, 5.0 + route.EXIT_INTO_M))
    inside = route.path_ahead(NET, ":J_0_0", 1.0, (), (101.0, 0.5), 0.5)
    cmd2, target2, sticky2 = route.command_and_target(NET, ":J_0_0", inside, (), sticky)
    assert (cmd2, target2, sticky2) == (cmd, target, sticky)


def test_no_command_where_the_road_does_not_branch():
    class Bend(ToyNet):
        def links(self, lane_id):
            return super().links(lane_id)[:1] if lane_id == "A_0" else super().links(lane_id)

    cmd, _, _ = route.command_and_target(Bend(), "A_0", _path_left(70.0), LEFT, None)
    assert cmd == "follow"


def test_signals_light_ahead_and_a_stop_entry_only_behind_right_of_way_links():
    path = _path_left(40.0)
    red = (("tls", 3, 60.0, "r"),)
    sig = route.signals(red, LEFT, path.link_dist)
    assert (sig.light, sig.light_distance_m, sig.stop_distance_m) == ("red", 60.0, None)
    stop = (Link("B_0", ":J_0_0", "s", "l"),)
    sig = route.signals((), stop, path.link_dist)
    assert sig.light == "none" and sig.light_distance_m is None
    assert sig.stop_distance_m == pytest.approx(60.0) and sig.stop_junction == "J"
    # a signalled link first: a stop entry behind it does not govern the ego now
    two = (Link("B_0", ":J_0_0", "G", "l"), Link("X_0", ":K_0_0", "s", "s"))
    assert route.signals((), two, (60.0, 200.0)).stop_distance_m is None
    # a right-of-way entry first: the stop entry behind it does
    two = (Link("B_0", ":J_0_0", "M", "l"), Link("X_0", ":K_0_0", "s", "s"))
    assert route.signals((), two, (60.0, 200.0)).stop_distance_m == 200.0


def test_curvature_of_an_arc_is_one_over_its_radius():
    r = 20.0
    th = np.linspace(0.0, math.pi / 2, 40)
    pts = np.stack([r * np.sin(th), r * (1 - np.cos(th))], 1)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
    curv = route.curvature_ahead(route.Path(pts, s, (), ()), 1.0 / 300.0)
    k = np.array([c for _, c in curv])
    assert len(k) == len(pts) - 2
    # segments are 0.8 m < 1.5 m, so the estimate is the floor 1.5 m: k = dth / 1.5
    dth = (math.pi / 2) / 39
    assert k == pytest.approx(dth / 1.5)
    straight = route.Path(
        np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]), np.array([0, 1, 2.0]), (), ()
    )
    assert route.curvature_ahead(straight, 1.0 / 300.0) == ()


def test_speed_limits_lower_ones_ahead_and_the_exit_lane_inside_a_junction():
    path = _path_left(40.0)
    limit, ahead = route.speed_limits(NET, "A_0", path)
    assert limit == 13.89 and ahead == ((path.seg_lanes[1][0], 8.33),)
    inside = route.path_ahead(NET, ":J_0_0", 1.0, (), (101.0, 0.5), 0.5)
    assert route.speed_limits(NET, ":J_0_0", inside) == (8.33, ())


def test_remaining_route_counts_the_rest_of_this_lane_and_later_edges():
    suffix = route.route_suffix_m(NET, ("A", "C"))
    assert suffix == pytest.approx([200.0, 100.0, 0.0])
    assert route.remaining_route_m(NET, suffix, "A_0", 30.0, 0) == pytest.approx(170.0)
    assert route.remaining_route_m(NET, suffix, "C_0", 90.0, 1) == pytest.approx(10.0)


def test_point_along_a_polyline_clamps_to_its_end():
    pts = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    s = np.array([0.0, 10.0, 20.0])
    assert route.point_along(pts, s, 15.0) == pytest.approx((10.0, 5.0))
    assert route.point_along(pts, s, 50.0) == pytest.approx((10.0, 10.0))


def test_a_minor_turn_with_an_internal_waiting_point_waits_inside():
    class Split(ToyNet):
        def links(self, lane_id):
            if lane_id == ":J_0_0":
                return (Link("B_0", ":J_9_0", "", "l"),)  # the turn's second internal lane
            return super().links(lane_id)

    left = Link("B_0", ":J_0_0", "m", "l")
    assert route.waits_inside(Split(), left)
    assert not route.waits_inside(NET, left)  # one internal lane: no waiting point inside
    assert not route.waits_inside(Split(), left._replace(state="M"))  # major: no giving way
    assert (
        route.junction_of(":J_0_0") == "J"
        and route.junction_of(":cluster_1_2_5_0") == "cluster_1_2"
    )


class TwoLaneNet(ToyNet):
    """ToyNet with a second car lane A_1 (y = 3.2) and a sidewalk A_2 (y = 6) on edge A."""

    def __init__(self):
        super().__init__()
        self.lanes["A_1"] = _lane((0, 3.2), (100, 3.2))
        self.lanes["A_2"] = _lane((0, 6.0), (100, 6.0))

    def allowed(self, lane_id):
        return ("pedestrian",) if lane_id == "A_2" else ("passenger",)

    def lane_count(self, edge_id):
        return 3 if edge_id == "A" else 1


def test_sparse_plan_is_the_road_centre_at_junction_exits_entries_and_every_50_m():
    plan = route.sparse_plan(TwoLaneNet(), ["A", "B"])
    # A: 100 m, two car lanes (the sidewalk is not a car lane): centre y = 1.6 at 0, 50, 100 m
    assert [(p.edge_index, p.pos_m) for p in plan] == [
        (0, 0.0), (0, 50.0), (0, 100.0), (1, 0.0), (1, 50.0), (1, 100.0)
    ]  # fmt: skip
    assert [(p.x_m, p.y_m) for p in plan[:3]] == [(0.0, 1.6), (50.0, 1.6), (100.0, 1.6)]
    assert (plan[3].x_m, plan[3].y_m) == (105.0, 5.0)  # the exit of the left turn


def test_next_plan_point_is_the_first_one_not_yet_reached():
    plan = route.sparse_plan(TwoLaneNet(), ["A", "B"])
    # on A at 20 m: 0 m is behind, 50 m is 30 m ahead
    assert route.next_plan_point(plan, 0, 0, 20.0, (20.0, 0.0)) == 1
    # 45 m: 50 m is less than 7.5 m ahead, reached: the junction entry at 100 m is the target
    assert route.next_plan_point(plan, 1, 0, 45.0, (45.0, 0.0)) == 2
    # inside the junction (no lane position) only distance counts: the entry is 2.6 m away,
    # B's start 7.8 m; 2 m on B's start is reached too (this toy junction is 7 m across)
    assert route.next_plan_point(plan, 2, 0, None, (100.0, -1.0)) == 3
    assert route.next_plan_point(plan, 3, 0, None, (102.0, 1.0)) == 4
    # on B (route index 1) at 10 m: its start is behind; never goes back, keeps the last point
    assert route.next_plan_point(plan, 3, 1, 10.0, (105.0, 15.0)) == 4
    assert route.next_plan_point(plan, 0, 5, None, (0.0, 0.0)) == len(plan) - 1
