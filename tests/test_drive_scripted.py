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
    assert doc["events"][0]["detail"] == "parked"
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
