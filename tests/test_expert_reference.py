"""Regression tests for the expert reference of issue 38: every expert event on the held-out
benchmarks that was the world's or the expert's fault, fixed, with a test each (the judge's
own fixes are in tests/test_drive_pure.py and tests/test_drive_scripted.py)."""

import math
from pathlib import Path

import libsumo as ls
import numpy as np
import pytest

from datagen.world import World, WorldConfig
from datagen.world.towns import build_plain_network
from datagen.world.traffic import edges_near


def test_no_vehicle_spawns_on_an_edge_that_reaches_into_the_spawn_ring():
    """boulevard-long-04, v176: an edge starting at the ego, its middle 65 m away (beyond the
    60 m spawn ring), got a vehicle 3 m before the ego's front."""
    mids = np.array([[0.0, 65.0], [0.0, 100.0], [0.0, 65.0]])
    lens = np.array([130.0, 60.0, 20.0])  # from the ego to 130 m; 70-130 m; 55-75 m
    assert edges_near(mids, lens, (0.0, 0.0), 60.0, 300.0).tolist() == [1]
    # the start-up population (r0 = 0) takes every edge whose middle is near, as before
    assert edges_near(mids, lens, (0.0, 0.0), 0.0, 300.0).tolist() == [0, 1, 2]


def _priority_stop(out: Path) -> Path:
    """A minor road S -> C (stop sign) meets a two-lane major road W <-> E (car lanes 1 and 2;
    lane 0 is the sidewalk)."""
    nodes = [dict(id="W", x=-250, y=0), dict(id="E", x=250, y=0), dict(id="S", x=0, y=-200)]
    nodes += [dict(id="C", x=0, y=0, type="priority_stop")]
    major = {"numLanes": 2, "speed": 13.89, "priority": 3}
    edges = [
        {"id": "WC", "from": "W", "to": "C", **major},
        {"id": "CE", "from": "C", "to": "E", **major},
        {"id": "EC", "from": "E", "to": "C", **major},
        {"id": "CW", "from": "C", "to": "W", **major},
        {"id": "SC", "from": "S", "to": "C", "numLanes": 1, "speed": 13.89, "priority": 1},
        {"id": "CS", "from": "C", "to": "S", "numLanes": 1, "speed": 13.89, "priority": 1},
    ]
    return build_plain_network(nodes, edges, out)


@pytest.mark.slow
def test_at_a_stop_sign_the_expert_waits_only_for_passages_that_conflict(tmp_path):
    """boulevard-short-04, -long-05: the ego at a stop sign waited for a 5 s gap in every
    vehicle approaching the junction, on a busy road never saw one, and stood until SUMO took
    it away. Turning right it need not wait for the other direction of the major road, which
    here carries a car every 2 s (SUMO's right-of-way model lets it go; the old rule, any
    vehicle approaching or inside the junction, held it for good)."""
    net = _priority_stop(tmp_path / "stop.net.xml")
    cfg = WorldConfig(
        net_path=net,
        seed=3,
        weather="sunny",
        behaviour="normal",
        n_vehicles=0,
        n_pedestrians=0,
        reroute=False,
        warmup_s=0.0,
        ego_route=("SC", "CE"),
    )
    entered = None
    with World(cfg) as world:
        ls.route.add("back", ["EC", "CW"])
        for k in range(1200):  # 120 s
            if k % 20 == 0:
                ls.vehicle.add(f"b{k}", "back", depart="now", departLane="best",
                               departPos="150", departSpeed="max")  # fmt: skip
            world.step()
            if world.ended:
                break
            if world.truth().road_id == "CE":
                entered = world.time_s
                break
        assert world.stats["collisions"] == 0
    assert entered is not None and entered < 60.0, entered


@pytest.mark.slow
def test_a_standing_expert_changes_lanes_only_for_its_route(tmp_path):
    """boulevard-long-04, v18, and -long-06, v321: standing at a stop line, the ego made a
    keep-right lane change; SUMO turns a car changing lanes at standstill up to ~40 degrees and
    leaves it so, its rear in the next lane, and the next car there drove into it. Slower than
    1 m/s (SLOW_LANE_CHANGE_MPS) the ego now changes lanes only for its route (SUMO lane-change
    mode 1537). The spawn fix changed this route's traffic, so the v18 scene itself no longer
    occurs: the test pins the mode on the route where it did, and that the standing ego stays
    aligned with its lane and hits nothing."""
    from drive.routes import ROUTES_DIR, load_routes, resolve_net

    _, routes = load_routes(ROUTES_DIR / "heldout_long.json")
    route = next(r for r in routes if r.route_id == "boulevard-long-04")
    cfg = WorldConfig(
        net_path=resolve_net(route),
        seed=route.seed,
        weather=route.weather,
        behaviour=route.behaviour,
        reroute=False,
        ego_route=route.edges,
        end_on_collision=False,
    )
    standing = 0
    with World(cfg) as world:
        while world.time_s < 80.0 and not world.ended:
            v0 = world.state().ego.speed_mps
            world.step()
            mode = ls.vehicle.getLaneChangeMode("ego")
            assert mode == (1537 if v0 < 1.0 else 1621), (world.time_s, v0)
            ego = world.state().ego
            if ego.speed_mps < 0.1:
                standing += 1
                lane = ls.vehicle.getLaneID("ego")
                if lane and not lane.startswith(":"):
                    shape = np.array(ls.lane.getShape(lane))
                    d = shape[-1] - shape[-2]
                    off = (ego.pose.yaw_rad - math.atan2(d[1], d[0]) + math.pi) % (2 * math.pi)
                    assert abs(off - math.pi) < math.radians(3.0), (world.time_s, lane)
        assert world.stats["collisions"] == 0
    assert standing > 100  # it did stand at the stop line (over 10 s)
