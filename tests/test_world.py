"""The driving world with real SUMO: the expert's rules on tiny hand-made networks, safety over
random episodes in the built-in towns, user networks, determinism and FrameState conventions."""

import dataclasses
import math
from pathlib import Path

import libsumo as ls
import numpy as np
import pytest

from datagen.errors import UserError
from datagen.state import Pose
from datagen.world import (
    AGENT_RADIUS_M,
    COLLISION_DROP_S,
    EGO_DIMS_M,
    EGO_ID,
    EgoCommand,
    World,
    WorldConfig,
    expert,
    record,
)
from datagen.world.towns import TOWN_NAMES, build_plain_network, town_net_path
from schemas import BOX_CLASSES, COMMANDS, EXPERT_REASONS, TRAFFIC_LIGHTS

SUMO_GAME = Path(__import__("sumo").SUMO_HOME) / "tools" / "game"


def _cross(out: Path, junction_type: str) -> Path:
    """A 400 m x 400 m single-lane cross with one junction C of the given type at (0, 0)."""
    nodes = [
        dict(id="W", x=-200, y=0),
        dict(id="E", x=200, y=0),
        dict(id="N", x=0, y=200),
        dict(id="S", x=0, y=-200),
        dict(id="C", x=0, y=0, type=junction_type),
    ]
    edges = []
    for a in "WENS":
        for f, t in ((a, "C"), ("C", a)):
            edges.append({"id": f + t, "from": f, "to": t, "numLanes": 1, "speed": 13.89})
    return build_plain_network(nodes, edges, out)


def _quiet(net: Path, route: tuple[str, ...], behaviour: str = "normal") -> WorldConfig:
    """An empty world with the ego on a fixed route."""
    return WorldConfig(
        net_path=net,
        seed=1,
        weather="sunny",
        behaviour=behaviour,
        n_vehicles=0,
        n_pedestrians=0,
        warmup_s=0.0,
        ego_route=route,
        reroute=False,
    )


@pytest.fixture(scope="module")
def nets(tmp_path_factory):
    d = tmp_path_factory.mktemp("nets")
    straight = build_plain_network(
        [
            dict(id="A", x=-200, y=0),
            dict(id="M", x=0, y=0, type="priority"),
            dict(id="B", x=200, y=0),
        ],
        [
            {"id": f + t, "from": f, "to": t, "numLanes": 1, "speed": 13.89}
            for f, t in (("A", "M"), ("M", "A"), ("M", "B"), ("B", "M"))
        ],
        d / "crossing.net.xml",
        crossings=[dict(node="M", edges="AM MA", priority="true")],
    )
    return {
        "light": _cross(d / "light.net.xml", "traffic_light"),
        "stop": _cross(d / "stop.net.xml", "allway_stop"),
        "crossing": straight,
    }


def _ego():
    return ls.vehicle.getLaneID(EGO_ID), ls.vehicle.getLanePosition(EGO_ID)


def test_red_light_stops_before_the_line_then_goes_on_green(nets):
    with World(_quiet(nets["light"], ("WC", "CE"))) as world:
        n = len(ls.trafficlight.getRedYellowGreenState("C"))
        ls.trafficlight.setRedYellowGreenState("C", "r" * n)
        stopped_at = None
        for _ in range(600):
            world.advance(0.1)
            lane, pos = _ego()
            assert not lane.startswith(":"), "entered the junction at red"
            if world.state().ego.speed_mps < 0.1 and pos > 100:
                stopped_at = (lane, pos)
                break
        assert stopped_at is not None, "never stopped at the red light"
        lane, pos = stopped_at
        assert lane.startswith("WC_") and ls.lane.getLength(lane) - 5.0 < pos <= ls.lane.getLength(
            lane
        )
        frame = world.state()
        assert frame.traffic_light == "red" and frame.expert_reason == "red_light"
        assert 0.0 < frame.light_distance_m < 5.0
        world.advance(5.0)  # stays
        assert _ego()[1] == pytest.approx(pos)
        ls.trafficlight.setRedYellowGreenState("C", "G" * n)
        for _ in range(300):
            world.advance(0.1)
            if ls.vehicle.getRoadID(EGO_ID) == "CE":
                break
        assert ls.vehicle.getRoadID(EGO_ID) == "CE", "did not go on green"
        assert world.stats["red_light_violations"] == 0 and world.stats["collisions"] == 0


def test_stop_sign_full_stop_at_the_line_before_entering(nets):
    with World(_quiet(nets["stop"], ("WC", "CE"))) as world:
        stopped_near_line = False
        reasons = set()
        for _ in range(600):
            world.advance(0.1)
            lane, pos = _ego()
            frame = world.state()
            reasons.add(frame.expert_reason)
            if lane.startswith(":"):
                break
            if frame.ego.speed_mps < 0.1 and ls.lane.getLength(lane) - pos < 3.0:
                stopped_near_line = True
                assert frame.stop_sign and frame.stop_distance_m < 3.0
        assert stopped_near_line, "entered the stop-controlled junction without a full stop"
        assert "stop_sign" in reasons
        for _ in range(300):
            world.advance(0.1)
            if ls.vehicle.getRoadID(EGO_ID) == "CE":
                break
        assert ls.vehicle.getRoadID(EGO_ID) == "CE", "never proceeded after stopping"


def test_yields_to_pedestrian_on_crossing(nets):
    with World(_quiet(nets["crossing"], ("AM", "MB"))) as world:
        length = ls.lane.getLength("AM_0")
        ped_added = yielded = False
        reasons = set()
        for _ in range(500):
            world.advance(0.1)
            lane, pos = _ego()
            if not ped_added and lane.startswith("AM") and pos > length - 45.0:
                # someone steps off the kerb right in front of the approaching car
                ls.person.add("walker", "AM", length - 2.0, typeID="ped")
                for stage in ls.simulation.findIntermodalRoute(
                    "AM", "MA", pType="ped", departPos=length - 2.0, arrivalPos=5.0
                ):
                    ls.person.appendStage("walker", stage)
                ped_added = True
            if not ped_added or "walker" not in ls.person.getIDList():
                continue
            frame = world.state()
            reasons.add(frame.expert_reason)
            on_crossing = ls.person.getLaneID("walker").startswith(":M_c")
            if on_crossing and frame.ego.speed_mps < 0.1 and lane.startswith("AM"):
                yielded = True
            if ls.vehicle.getRoadID(EGO_ID) == "MB":
                break
        assert yielded, "did not wait before the crossing while the pedestrian was on it"
        assert "pedestrian" in reasons
        assert ls.vehicle.getRoadID(EGO_ID) == "MB", "did not go on after the pedestrian"
        assert world.stats["collisions"] == 0


@pytest.mark.slow
def test_cautious_drives_slower_with_longer_gaps_than_aggressive():
    net = town_net_path("downtown")
    speed, gap = {}, {}
    for behaviour in ("aggressive", "cautious"):
        s, g = [], []
        for seed in range(3):
            cfg = WorldConfig(net_path=net, seed=seed, weather="sunny", behaviour=behaviour)
            with World(cfg) as world:
                world.advance(90.0)
                s.append(world.stats["mean_speed_mps"])
                if world.stats["median_time_gap_s"] is not None:
                    g.append(world.stats["median_time_gap_s"])
        speed[behaviour], gap[behaviour] = np.mean(s), np.mean(g)
    assert speed["cautious"] < speed["aggressive"]
    assert gap["cautious"] > gap["aggressive"]


@pytest.mark.slow
def test_random_episodes_in_every_town_have_no_collision_or_red_light_violation():
    ends = []
    for i in range(20):
        town = TOWN_NAMES[i % len(TOWN_NAMES)]
        weather, behaviour = [("sunny", "normal"), ("cloudy", "aggressive"), ("rainy", "cautious")][
            i % 3
        ]
        cfg = WorldConfig(town_net_path(town), seed=100 + i, weather=weather, behaviour=behaviour)
        with World(cfg) as world:
            frames = list(record(world, 120))  # 60 s
            st = world.stats
        assert st["collisions"] == 0, (town, i, st["end_detail"])
        assert st["red_light_violations"] == 0, (town, i)
        assert world.ended in (None, "route_end"), (town, i, world.ended, world.end_detail)
        assert len(frames) == 120
        ends.append(world.ended)


@pytest.mark.parametrize(
    "net, forbidden",
    [
        ("fokr_bs_demo/fokr_bs.net.xml.gz", ("bus", "bicycle")),  # gzipped, bus and bike lanes
        ("DRT/osm.net.xml", ("tram", "bicycle")),  # an OSM import with tram tracks
    ],
)
@pytest.mark.slow
def test_drives_shipped_networks_only_on_lanes_for_cars(net, forbidden):
    cfg = WorldConfig(net_path=SUMO_GAME / net, seed=3, weather="foggy", behaviour="cautious")
    with World(cfg) as world:
        # the network really has lanes the ego must not use
        allowed = {
            ls.lane.getAllowed(f"{e}_{k}")
            for e in ls.edge.getIDList()
            for k in range(ls.edge.getLaneNumber(e))
        }
        for cls in forbidden:
            assert any(cls in a and "passenger" not in a for a in allowed), cls
        for frame in record(world, 120):
            lane = ls.vehicle.getLaneID(EGO_ID)
            if not lane.startswith(":"):
                assert "passenger" in ls.lane.getAllowed(lane), f"ego on {lane}"
            assert frame.command in COMMANDS
        assert world.stats["collisions"] == 0
        assert world.stats["distance_m"] > 100.0


def test_not_a_network_is_a_clear_error_and_leaves_no_simulation_open(tmp_path):
    bad = tmp_path / "routes.xml"
    bad.write_text("<routes/>")
    with pytest.raises(UserError, match="not a SUMO network"):
        World(WorldConfig(bad, seed=0, weather="sunny", behaviour="normal"))
    rail = SUMO_GAME / "rail" / "net.net.xml"
    with pytest.raises(UserError, match="no lane allows passenger cars"):
        World(WorldConfig(rail, seed=0, weather="sunny", behaviour="normal"))
    with World(WorldConfig(town_net_path("grid_small"), 0, "sunny", "normal")) as world:
        with pytest.raises(RuntimeError, match="one simulation per process"):
            World(WorldConfig(town_net_path("grid_small"), 1, "sunny", "normal"))
        world.advance(1.0)


@pytest.mark.slow
def test_sparse_target_is_the_route_plan_ahead_and_dense_the_lane_look_ahead():
    """Same seed, both forms: the trajectories are the same (the target is only a label), the
    sparse target is a plan point ahead that changes in jumps (a point is held until reached),
    the dense one moves with the car 30 m ahead (or 5 m into a junction's exit lane)."""
    runs = {}
    for form in ("sparse", "dense"):
        cfg = WorldConfig(town_net_path("downtown"), 5, "sunny", "normal", target_point=form)
        with World(cfg) as world:
            runs[form] = list(record(world, 120, drop_before_collision_s=0.0))
    sparse, dense = runs["sparse"], runs["dense"]
    assert [f.ego.pose for f in sparse] == [f.ego.pose for f in dense]
    tps = [tuple(f.target_point_xy_m) for f in sparse]
    ahead = [f.ego.pose.ego_from_world(np.array([tp]))[0] for f, tp in zip(sparse, tps)]
    assert all(x > 0.0 and math.hypot(x, y) < 80.0 for x, y in ahead)
    held = sum(a == b for a, b in zip(tps, tps[1:]))
    assert held > len(tps) // 2  # a plan point is the target for several frames
    assert len(set(tps)) >= 4  # ... and the plan moves on
    moving = [f for f in dense if f.ego.speed_mps > 1.0]
    assert all(tuple(f.target_point_xy_m) != tps[0] for f in moving)
    with pytest.raises(UserError, match="target point form"):
        World(WorldConfig(town_net_path("grid_small"), 0, "sunny", "normal", target_point="x"))


@pytest.mark.slow
def test_same_seed_same_trajectory():
    def run(seed):
        cfg = WorldConfig(
            town_net_path("roundabout"), seed=seed, weather="rainy", behaviour="cautious"
        )
        with World(cfg) as world:
            return [
                (f.time_s, f.ego.pose, f.ego.speed_mps, len(f.agents), f.expert_reason)
                for f in record(world, 60)
            ]

    a, b, c = run(5), run(5), run(6)
    assert a == b
    assert a != c


def test_frame_state_conventions():
    cfg = WorldConfig(town_net_path("downtown"), seed=2, weather="sunny", behaviour="normal")
    with World(cfg) as world:
        # no hold-back: the last frame is SUMO's state now, compared with libsumo below
        frames = list(record(world, 40, drop_before_collision_s=0.0))
        assert [round(f.time_s - frames[0].time_s, 3) for f in frames] == [
            0.5 * k for k in range(40)
        ]
        f = frames[-1]
        # ego pose is the box centre: SUMO's front bumper lies half a length ahead along the yaw
        fx, fy = ls.vehicle.getPosition(EGO_ID)
        e = f.ego.pose
        assert math.hypot(fx - e.x_m, fy - e.y_m) == pytest.approx(f.ego.length_m / 2, abs=1e-6)
        assert (fx - e.x_m) * math.cos(e.yaw_rad) + (fy - e.y_m) * math.sin(e.yaw_rad) > 0
        nav = ls.vehicle.getAngle(EGO_ID)  # degrees, 0 = north, clockwise
        assert math.cos(e.yaw_rad - math.radians(90 - nav)) == pytest.approx(1.0)
        for fr in frames:
            assert fr.command in COMMANDS and fr.traffic_light in TRAFFIC_LIGHTS
            assert fr.expert_reason in EXPERT_REASONS
            assert (fr.traffic_light == "none") == (fr.light_distance_m is None)
            assert fr.stop_sign == (fr.stop_distance_m is not None)
            if fr.light_distance_m is not None:
                assert 0 <= fr.light_distance_m <= 30.0
            ids = [a.track_id for a in fr.agents]
            assert EGO_ID not in ids and len(set(ids)) == len(ids)
            for a in fr.agents:
                assert a.cls in BOX_CLASSES
                d = math.hypot(a.pose.x_m - fr.ego.pose.x_m, a.pose.y_m - fr.ego.pose.y_m)
                assert d <= AGENT_RADIUS_M + a.length_m + fr.ego.length_m
                assert a.length_m > 0 and a.width_m > 0 and a.height_m > 0
            tp = fr.ego.pose.ego_from_world(np.array([fr.target_point_xy_m]))[0]
            assert -10.0 < tp[0] < 80.0 and abs(tp[1]) < 60.0  # <= 40 m to the junction + exit
        classes = {a.cls for fr in frames for a in fr.agents}
        assert {"vehicle", "pedestrian"} <= classes


def test_record_stops_when_the_world_ends(nets):
    with World(_quiet(nets["stop"], ("WC", "CE"))) as world:
        frames = list(record(world, 10_000))
        assert world.ended == "route_end"
        assert len(frames) < 10_000
        assert frames[-1].expert_reason == "route_end"
        assert ls.vehicle.getSpeed(EGO_ID) < expert.STOPPED_MPS


def _external(net: Path, route: tuple[str, ...]) -> WorldConfig:
    return dataclasses.replace(_quiet(net, route), ego_driver="external")


def test_external_driver_places_the_ego_and_gets_signals_and_route_progress(nets):
    with World(_external(nets["light"], ("WC", "CN"))) as world:
        with pytest.raises(RuntimeError, match="step"):
            world.advance(0.1)
        n = len(ls.trafficlight.getRedYellowGreenState("C"))
        ls.trafficlight.setRedYellowGreenState("C", "r" * n)
        start = world.state().ego.pose
        x, y, v = start.x_m, start.y_m, 10.0
        lanes, remaining, red = [], [], 0
        for k in range(400):
            yaw = 0.0 if x < 1.6 else math.pi / 2  # east on WC, then left (north) onto CN
            x, y = x + v * 0.1 * math.cos(yaw), y + v * 0.1 * math.sin(yaw)
            y += 0.25 if 40 < k <= 50 else -0.25 if 50 < k <= 60 else 0.0  # swerve and back
            world.step(EgoCommand(Pose(x, y, yaw), v))
            ego, truth = world.state().ego, world.truth()
            assert (ego.pose.x_m, ego.pose.y_m) == pytest.approx((x, y), abs=1e-6)
            assert ego.pose.yaw_rad == pytest.approx(yaw, abs=1e-6)
            assert ego.speed_mps == pytest.approx(v)
            lanes.append(truth.lane_id)
            remaining.append(truth.remaining_route_m)
            red += truth.entered_on_red
            if y > 100:
                break
        assert any(lane.startswith("CW") for lane in lanes), "never mapped to the opposite lane"
        assert red == 1 and world.stats["red_light_violations"] == 1
        assert truth.lane_id.startswith("CN") and truth.route_index == 1
        assert truth.remaining_route_m == pytest.approx(
            ls.lane.getLength(truth.lane_id) - (y - 2.35), abs=3.0
        )
        on_wc = [r for r, lane in zip(remaining, lanes) if lane.startswith("WC")]
        assert all(a > b for a, b in zip(on_wc, on_wc[1:])), "route progress not monotone"
        assert None in remaining  # off the route (opposite lane): no progress reported


def test_traffic_sees_an_externally_placed_ego(nets):
    with World(_external(nets["light"], ("WC", "CE"))) as world:
        ls.trafficlight.setRedYellowGreenState(
            "C", "G" * len(ls.trafficlight.getRedYellowGreenState("C"))
        )
        ego = world.state().ego.pose
        stand = Pose(ego.x_m + 100.0, ego.y_m, 0.0)
        ls.route.add("r_follow", ["WC", "CE"])
        ls.vehicle.add("follower", "r_follow", typeID="car", departSpeed="13")
        for _ in range(300):  # the ego stands 100 m down the road; the follower comes up
            world.step(EgoCommand(stand, 0.0))
        assert "follower" in ls.vehicle.getIDList()
        gap = stand.x_m - EGO_DIMS_M[0] / 2 - ls.vehicle.getPosition("follower")[0]
        assert ls.vehicle.getSpeed("follower") < 0.1 and 0.0 < gap < 5.0
        assert world.stats["collisions"] == 0


def test_record_drops_the_frames_before_an_ego_collision(nets):
    with World(_quiet(nets["crossing"], ("AM", "MB"))) as world:
        frames = []
        for frame in record(world, 1000):
            if not frames:  # a car that ignores every safety rule rams the ego from behind
                ls.route.add("r_ram", ["AM", "MB"])
                ls.vehicle.add("ram", "r_ram", typeID="car", departSpeed="20", departPos="0")
                ls.vehicle.setSpeedMode("ram", 0)
                ls.vehicle.setSpeed("ram", 25.0)
            frames.append(frame)
        assert world.ended == "collision" and "ram" in world.end_detail
        crash_s = world.time_s
        assert frames, "frames long before the collision are kept"
        assert frames[-1].time_s <= crash_s - COLLISION_DROP_S
        assert world.stats["dropped_frames"] == round(COLLISION_DROP_S / 0.5)
    # without a collision nothing is dropped: every state up to the end is yielded
    with World(_quiet(nets["stop"], ("WC", "CE"))) as world:
        frames = list(record(world, 10_000))
        assert world.ended == "route_end" and world.stats["dropped_frames"] == 0
        assert frames[-1].time_s == pytest.approx(world.time_s, abs=0.51)


# Episodes that ended in an ego collision before the expert yielded to people stepping onto a
# crossing on its path and kept junctions clear (town, SUMO seed, weather, behaviour, seconds).
FORMER_COLLISIONS = [
    # datagen build --towns 1 --frames 1440 --seed 22, grid_small-22-0000: "ego hit p130
    # (crossing)" at 123 s, the person stepping off a walking area onto the exit crossing
    ("grid_small", 1486197343, "sunny", "normal", 126.0),
    # datagen build --towns 8 --frames 1920 --episode-seconds 120 --seed 11, spider-11-0001:
    # "v77 hit ego (junction)" at 22.7 s, the ego waiting inside the junction to turn left
    ("spider", 2138764776, "cloudy", "aggressive", 30.0),
    # bench/sim.py --episodes 168 --seconds 60, episode 129 (with a first crossing rule that
    # also stopped inside junctions for people on the kerb): "ego hit p146 (crossing)" at 37 s
    ("downtown", 129, "cloudy", "normal", 40.0),
    # bench/sim.py --episodes 420 --seconds 180 --workers 2: someone standing on the walking
    # area at the inside of a right turn, swept by the car's body (before the swept check)
    ("roundabout", 334, "cloudy", "normal", 20.0),  # "ego hit p63 (crossing)" at 16.7 s
    ("roundabout", 294, "rainy", "cautious", 30.0),  # "ego hit p23 (crossing)" at 26.4 s
    ("downtown", 281, "cloudy", "aggressive", 130.0),  # "ego hit p199 (crossing)" at 128.2 s
    # ... and the ego entering a left turn at 1 m/s 0.2 s before its green ended, still inside
    # when the crossing phase began (before the green-left check): "v51 hit ego" at 127.4 s
    ("arterial", 284, "rainy", "cautious", 130.0),
    # datagen build --towns 8 --frames 146000 (seed 0), arterial-0-0009: the ego waiting in a
    # junction for someone at the kerb beside it (who waited for the ego), until "ego hit p145
    # (crossing)" at 119.3 s; and mixed-0-0044: let in at a stop sign ahead of a car turning
    # across it, "ego hit v65 (junction)" at 95.0 s
    ("arterial", 2079518455, "cloudy", "aggressive", 121.0),
    ("mixed", 1859598460, "sunny", "normal", 97.0),
    # bench/sim.py --episodes 420 --seconds 180 --workers 2, arterial seed 172: the ego turning
    # left from a minor link, and an aggressive car standing at the stop sign across starts into
    # it, "v30 hit ego (junction)" at 33.8 s (before standing stop-line foes counted)
    ("arterial", 172, "sunny", "aggressive", 36.0),
    # bench/learn.py --frames 12000 (build seed 21), arterial-21-0005: a car cutting in 15 m
    # ahead, the ego braking at its vType decel only, "ego hit v40" at 6.3 s (before the
    # emergency brake)
    ("arterial", 1005867201, "cloudy", "aggressive", 10.0),
    # datagen build --towns 8 --frames 146000 (seed 0, data v8), spider-0-0033: the ego
    # stopped just past a junction for a bus beside it (its loose box extents), which turned
    # into its rear, "v214 hit ego (junction)" at 175.1 s; arterial-0-0020: a left turn begun
    # at 14 m/s 1 s before yellow, still inside when the cross traffic got green, "v182 hit
    # ego (junction)" at 171.9 s
    ("spider", 1967986422, "cloudy", "normal", 177.0),
    ("arterial", 502562067, "sunny", "aggressive", 173.0),
]


@pytest.mark.slow
@pytest.mark.parametrize("town, seed, weather, behaviour, seconds", FORMER_COLLISIONS)
def test_former_collision_episodes_now_drive_without_one(town, seed, weather, behaviour, seconds):
    cfg = WorldConfig(town_net_path(town), seed=seed, weather=weather, behaviour=behaviour)
    with World(cfg) as world:
        world.advance(seconds)
        assert world.stats["collisions"] == 0, world.end_detail
        assert world.stats["sim_s"] == pytest.approx(seconds)
