"""Proof that the evaluator is right: scripted drives in real SUMO on tiny networks, each with
exactly the infraction it provokes."""

import math

import libsumo as ls
import numpy as np
import pytest

from datagen.world.towns import build_plain_network, network_sha256
from drive.evaluate import Task, drive_route
from drive.policy import PolicySpec, constant_waypoints
from drive.routes import Route

QUIET = dict(n_vehicles=0, n_pedestrians=0, warmup_s=0.0)


def _cross(out, junction_type):
    """A single-lane cross with junction C at (0, 0) and arms of 200 m."""
    nodes = [dict(id="W", x=-200, y=0), dict(id="E", x=200, y=0), dict(id="N", x=0, y=200)]
    nodes += [dict(id="S", x=0, y=-200), dict(id="C", x=0, y=0, type=junction_type)]
    edges = [
        {"id": f + t, "from": f, "to": t, "numLanes": 1, "speed": 13.89}
        for a in "WENS"
        for f, t in ((a, "C"), ("C", a))
    ]
    return build_plain_network(nodes, edges, out)


@pytest.fixture(scope="module")
def nets(tmp_path_factory):
    d = tmp_path_factory.mktemp("nets")
    return {
        "light": _cross(d / "light.net.xml", "traffic_light"),
        "stop": _cross(d / "stop.net.xml", "allway_stop"),
    }


def _route(net, edges=("WC", "CE")):
    return Route(
        "scripted",
        None,
        str(net),
        network_sha256(net),
        edges,
        0.0,
        1,
        "short",
        1,
        "sunny",
        "normal",
    )


def _drive(net, tmp_path, planner, on_start=None, edges=("WC", "CE"), **task_options):
    task = Task(_route(net, edges), PolicySpec("constant"), str(tmp_path), False, **task_options)
    return drive_route(task, planner=planner, on_start=on_start, world_options=QUIET)


def _counts(doc):
    return {k: v for k, v in doc["counts"].items() if v}


@pytest.mark.slow
def test_driving_through_a_red_light_is_exactly_one_red_light_infraction(nets, tmp_path):
    def all_red():
        ls.trafficlight.setRedYellowGreenState(
            "C", "r" * len(ls.trafficlight.getRedYellowGreenState("C"))
        )

    doc = _drive(nets["light"], tmp_path, lambda f: constant_waypoints(8.0), all_red)
    assert _counts(doc) == {"red_light": 1}, doc["events"]
    assert doc["ended"] == "route_complete"
    ev = doc["events"][0]
    assert ev["detail"] == "C" and abs(ev["y_m"]) < 3.0 and -20.0 < ev["x_m"] < 0.0
    assert doc["is"] == pytest.approx(0.70)


def test_the_same_drive_on_green_is_clean(nets, tmp_path):
    def all_green():
        ls.trafficlight.setRedYellowGreenState(
            "C", "G" * len(ls.trafficlight.getRedYellowGreenState("C"))
        )

    doc = _drive(nets["light"], tmp_path, lambda f: constant_waypoints(8.0), all_green)
    assert _counts(doc) == {} and doc["ds"] == 100.0


def test_rolling_through_a_stop_sign_is_a_stop_infraction(nets, tmp_path):
    doc = _drive(nets["stop"], tmp_path, lambda f: constant_waypoints(8.0))
    assert _counts(doc) == {"stop_sign": 1}, doc["events"]


def test_driving_into_a_stopped_car_is_a_vehicle_collision(nets, tmp_path):
    def park():
        ls.route.add("r_parked", ["WC", "CE"])
        ls.vehicle.add(
            "parked", "r_parked", typeID="car", depart="now", departPos="100", departSpeed="0"
        )
        ls.simulationStep()
        ls.vehicle.setSpeed("parked", 0.0)

    doc = _drive(nets["light"], tmp_path, lambda f: constant_waypoints(8.0), park)
    c = _counts(doc)
    assert c.get("collision_vehicle") == 1, doc["events"]
    assert doc["events"][0]["detail"] == "parked (vehicle)"
    assert c.keys() <= {"collision_vehicle", "red_light", "agent_blocked", "route_timeout"}


def test_leaving_the_road_is_off_road_and_a_layout_collision(nets, tmp_path):
    heading = math.radians(20.0)  # the road runs east (0); drive 20 degrees left of it

    def veer_left(frame):
        turn = heading - frame.ego.pose.yaw_rad
        return np.array(
            [[8.0 * t * math.cos(turn), 8.0 * t * math.sin(turn)] for t in (0.5, 1.0, 1.5, 2.0)]
        )

    doc = _drive(nets["light"], tmp_path, veer_left)
    c = _counts(doc)
    assert c.get("off_road") == 1 and c.get("collision_layout", 0) >= 1, doc["events"]
    assert doc["events"][0]["detail"] == "kerb"  # the sidewalk first, then whatever is beyond
    assert doc["ended"] == "route_deviation" and c["route_deviation"] == 1
    assert "collision_vehicle" not in c and doc["off_road_share"] > 0.5
    assert doc["is"] < 0.65 + 1e-9


@pytest.mark.slow
def test_a_policy_that_never_moves_is_agent_blocked(nets, tmp_path):
    doc = _drive(nets["light"], tmp_path, lambda f: np.zeros((4, 2)), creep=False)
    assert _counts(doc) == {"agent_blocked": 1}, doc["events"]
    assert doc["ended"] == "agent_blocked" and doc["ds"] < 0.1
    assert 89.0 <= doc["events"][0]["time_s"] <= 92.0


def test_a_policy_that_stands_55_s_creeps_forward_on_an_empty_road(nets, tmp_path):
    doc = _drive(nets["light"], tmp_path, lambda f: np.zeros((4, 2)), max_sim_s=60.0)
    assert doc["creeps"] == 1 and doc["ended"] == "max_sim_s"
    assert 1.0 < doc["distance_m"] < 4.0, doc["distance_m"]  # 1.5 s at throttle 0.4, then brake
    assert _counts(doc) == {}


@pytest.mark.slow
def test_no_creep_into_a_car_parked_just_ahead(nets, tmp_path):
    def park_ahead():
        front = ls.vehicle.getLanePosition("ego")
        ls.route.add("r_ahead", ["WC", "CE"])
        ls.vehicle.add(
            "ahead",
            "r_ahead",
            typeID="car",
            depart="now",
            departSpeed="0",
            departPos=f"{front + 2.0 + 5.0}",
        )  # its rear about 2 m ahead
        ls.simulationStep()
        ls.vehicle.setSpeed("ahead", 0.0)

    doc = _drive(nets["light"], tmp_path, lambda f: np.zeros((4, 2)), park_ahead, max_sim_s=60.0)
    assert doc["creeps"] == 0 and doc["distance_m"] < 0.1
    assert _counts(doc) == {}


# --- the issue-38 cases: one scripted drive per scoring fix ------------------------------------


def _toward(y_m, speed=8.0, turn_at_x=None, north_x=None):
    """A planner keeping the box centre on the world line y = y_m heading east at `speed`; past
    x = turn_at_x it heads north along x = north_x instead."""

    def plan(frame):
        p = frame.ego.pose
        pts = []
        for t in (0.5, 1.0, 1.5, 2.0):
            ahead = speed * t
            if turn_at_x is not None and p.x_m + ahead > turn_at_x:
                gx, gy = north_x, max(p.y_m, 0.0) + ahead
            else:
                gx, gy = p.x_m + ahead, y_m
            dx, dy = gx - p.x_m, gy - p.y_m
            c, s = math.cos(p.yaw_rad), math.sin(p.yaw_rad)
            pts.append([c * dx + s * dy, -s * dx + c * dy])
        return np.array(pts)

    return plan


def test_the_expert_driving_into_an_obstacle_scores_a_collision_and_drives_on(nets, tmp_path):
    """Issue 38 item 1: the expert's collision is judged (it ended the route unscored before)."""
    state = {"placed": None}

    def park_far():
        ls.route.add("r_far", ["NC", "CS"])
        ls.vehicle.add("obstacle", "r_far", typeID="car", depart="now", departPos="5")
        ls.simulationStep()
        ls.vehicle.setSpeed("obstacle", 0.0)

    def hook(_n):  # every plan (2 Hz): drop a standing car 1 m in front of the moving expert
        x, y = ls.vehicle.getPosition("ego")
        t = ls.simulation.getTime()
        if state["placed"] is None and x > -150.0 and ls.vehicle.getSpeed("ego") > 5.0:
            ls.vehicle.moveToXY("obstacle", "WC", 0, x + 1.0 + 4.5, y, 90.0, keepRoute=2)
            ls.vehicle.setSpeed("obstacle", 0.0)
            state["placed"] = t
        elif state["placed"] is not None and t > state["placed"] + 3.0:
            if "obstacle" in ls.vehicle.getIDList():
                ls.vehicle.remove("obstacle")  # cleared: the expert can go on

    task = Task(_route(nets["light"]), PolicySpec("expert"), str(tmp_path), False)
    doc = drive_route(task, on_start=park_far, world_options=QUIET, progress=hook)
    c = _counts(doc)
    assert state["placed"] is not None
    assert c.get("collision_vehicle") == 1, doc["events"]
    assert doc["events"][0]["detail"] == "obstacle (vehicle)"
    assert doc["ended"] == "route_complete" and doc["complete"]  # a collision ends no route
    assert doc["is"] == pytest.approx(0.60) and doc["rc"] == 100.0


def test_a_policy_that_stops_20_m_short_of_the_end_does_not_complete(nets, tmp_path):
    """Issue 38 item 2."""
    end_x = 200.0  # the route WC, CE ends at E

    keep_lane, stand = _toward(-1.6), _toward(-1.6, speed=0.0)

    def stop_short(frame):
        front = frame.ego.pose.x_m + 0.5 * frame.ego.length_m
        go = front < end_x - 20.0 - 6.0  # braking from 8 m/s takes about 5 m
        return keep_lane(frame) if go else stand(frame)

    def all_green():
        ls.trafficlight.setRedYellowGreenState(
            "C", "G" * len(ls.trafficlight.getRedYellowGreenState("C"))
        )

    doc = _drive(nets["light"], tmp_path, stop_short, all_green, max_sim_s=70.0, creep=False)
    assert not doc["complete"] and doc["ended"] == "max_sim_s", doc["ended"]
    assert 85.0 < doc["rc"] < 97.0, doc["rc"]  # about 20 m short of 400 m: ~95 %
    assert doc["ds"] == doc["rc"]


def test_two_wheels_on_the_kerb_are_a_layout_infraction(nets, tmp_path):
    """Issue 38 item 4: the box centre stays on the road, the right wheels on the sidewalk."""
    from datagen.sensors.scene import load_static_scene
    from drive.layout import Layout

    doc = _drive(nets["light"], tmp_path, _toward(-3.0), max_sim_s=14.0)
    c = _counts(doc)
    assert c.get("collision_layout") == 1 and c.get("off_road") == 1, doc["events"]
    kerb = doc["events"][0]
    assert kerb["kind"] == "collision_layout" and kerb["detail"] == "kerb"
    layout = Layout.from_static(load_static_scene(nets["light"]))
    assert layout.on_road(kerb["x_m"], kerb["y_m"])  # the centre alone would have seen nothing
    assert "route_deviation" not in c


def test_a_cyclist_contact_is_a_vehicle_collision(nets, tmp_path):
    """Issue 38 item 3: in CARLA a bicycle is a vehicle (0.60)."""

    def park_bike():
        ls.route.add("r_bike", ["WC", "CE"])
        ls.vehicle.add(
            "bike", "r_bike", typeID="bicycle", depart="now", departPos="100", departSpeed="0"
        )
        ls.simulationStep()
        ls.vehicle.setSpeed("bike", 0.0)

    doc = _drive(nets["light"], tmp_path, lambda f: constant_waypoints(8.0), park_bike)
    c = _counts(doc)
    assert c.get("collision_vehicle") == 1 and "collision_pedestrian" not in c, doc["events"]
    assert doc["events"][0]["detail"] == "bike (bicycle)"


def test_a_red_run_after_leaving_the_lane_is_counted(nets, tmp_path):
    """Issue 38 item 5: the ego straddles the centre line; SUMO maps it to the opposite lane,
    whose signal reads "none", while its right front corner crosses the route's stop line on
    red."""
    seen = []

    def all_red():
        ls.trafficlight.setRedYellowGreenState(
            "C", "r" * len(ls.trafficlight.getRedYellowGreenState("C"))
        )

    planner = _toward(0.3)  # over the centre line: SUMO maps it to the opposite lane

    def plan(frame):
        if -40.0 < frame.ego.pose.x_m < 0.0:
            seen.append(frame.traffic_light)
        return planner(frame)

    doc = _drive(nets["light"], tmp_path, plan, all_red, max_sim_s=30.0)
    assert seen and set(seen) == {"none"}, seen  # the world read no signal for it
    assert _counts(doc).get("red_light") == 1, doc["events"]


def test_sumo_taking_out_an_ego_off_its_route_is_a_route_deviation(nets, tmp_path):
    """Issue 38 item 6, at the judge: the ego turned left off its route (W -> E) and SUMO took
    it out 20 m from the route, closer than the 30 m deviation. SUMO did not take a placed ego
    out on its own in any probe (dead ends, opposite lanes: moveToXY keeps it in, off the
    network), and libsumo cannot remove it without the next placement failing, so the real
    tracker on the real route is handed the world's end as drive_route hands it."""
    from dataclasses import replace

    from datagen.sensors.scene import load_static_scene
    from datagen.state import AgentState, FrameState, Pose
    from drive.evaluate import judge_world_end
    from drive.geometry import route_geometry
    from drive.infractions import InfractionTracker
    from drive.layout import Layout

    net = nets["light"]
    geom = route_geometry(net, ("WC", "CE"))
    layout = Layout.from_static(load_static_scene(net))

    def frame(t, x, y, yaw):
        ego = AgentState("ego", "vehicle", Pose(x, y, yaw), 4.7, 1.85, 1.5, 6.0)
        return FrameState(t, ego, (), "follow", (0.0, 0.0), "none", None, False, None, "none")

    path = [(-60.0 + 0.6 * k, -1.6, 0.0) for k in range(95)]  # to x = -3.0
    path += [(1.6, 0.6 * k, math.pi / 2) for k in range(1, 35)]  # north to y = 20.4
    tracker = InfractionTracker(geom, layout)
    for k, (x, y, yaw) in enumerate(path):
        tracker.step(frame(0.1 * k, x, y, yaw))
    assert tracker.ended is None  # 20 m off: no deviation yet
    last = frame(0.1 * len(path), *path[-1])
    judge_world_end(tracker, last, "route_end", "SUMO took the placed ego out", external=True)
    assert tracker.ended == "route_deviation" and tracker.counts()["route_deviation"] == 1
    assert "SUMO" in tracker.events[-1].detail
    # taken out on the route's own lanes (e.g. its last edge's end): not a deviation
    on_route = InfractionTracker(geom, layout)
    for k in range(60):
        on_route.step(frame(0.1 * k, -60.0 + 0.6 * k, -1.6, 0.0))
    judge_world_end(on_route, replace(last, ego=replace(last.ego, pose=Pose(-24.6, -1.6, 0.0))),
                    "route_end", "SUMO took the placed ego out", external=True)  # fmt: skip
    assert on_route.ended is None


def test_standing_is_stuck_on_a_clear_road_and_not_before_a_red_light(nets, tmp_path):
    """drive eval's stuck_s: standing where the expert would drive on with nothing to wait for
    (issue 36's inertia measure); waiting a few metres short of a red light's line is not."""

    def all(state):
        def set_all():
            n = len(ls.trafficlight.getRedYellowGreenState("C"))
            ls.trafficlight.setRedYellowGreenState("C", state * n)
            ls.trafficlight.setPhaseDuration("C", 1000.0)

        return set_all

    doc = _drive(
        nets["light"], tmp_path, lambda f: np.zeros((4, 2)), all("G"), creep=False, max_sim_s=20.0
    )
    assert doc["standing_s"] > 15.0 and doc["stuck_s"] == pytest.approx(doc["standing_s"])

    def to_the_light(frame):  # drive east until ~20 m short of the junction, then stand
        return constant_waypoints(8.0) if frame.ego.pose.x_m < -25.0 else np.zeros((4, 2))

    doc = _drive(nets["light"], tmp_path, to_the_light, all("r"), creep=False, max_sim_s=40.0)
    assert doc["standing_s"] > 10.0 and doc["stuck_s"] == 0.0, doc
    assert _counts(doc) == {}
