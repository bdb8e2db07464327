"""Labels of one frame: BEV semantic raster, boxes, waypoints, and a schema-valid row."""

from __future__ import annotations

import math

import numpy as np
import pyarrow as pa

import schemas
from datagen import labels
from datagen.sensors.mesh import MeshBuilder
from datagen.sensors.scene import assemble_static_scene
from datagen.state import Pose
from schemas import bev_pixel_centres, codecs
from tests.scenes import (
    EGO_POSE,
    agent_at,
    frame_at,
)


def _future(frame, agents_per_step, ego_poses):
    return [
        frame_at(p, agents=a, time_s=frame.time_s + 0.5 * (k + 1))
        for k, (a, p) in enumerate(zip(agents_per_step, ego_poses))
    ]


def test_drivable_lies_under_the_ego_on_a_real_lane(grid3):
    grid3_net, grid3_scene = grid3
    import sumolib

    net = sumolib.net.readNet(str(grid3_net))
    lane = net.getEdge("e01_11").getLane(1)  # eastbound, right car lane (0 is the sidewalk)
    (x0, y0), (x1, y1) = lane.getShape()[0][:2], lane.getShape()[-1][:2]
    yaw = math.atan2(y1 - y0, x1 - x0)
    pose = Pose(x0 + 0.4 * (x1 - x0), y0 + 0.4 * (y1 - y0), yaw)
    sem = labels.bev_semantic(grid3_scene.label_map, pose)
    assert sem.dtype == np.uint8 and sem.shape == (256, 256)
    assert set(np.unique(sem).tolist()) <= {0, 1, 2}
    # the ego's lane ahead of it (3.2 m wide = 25 px, centred on column 128) is road
    patch = sem[200:256, 122:134]
    assert (patch == 1).mean() > 0.95
    # lane markings run along the road, and the sidewalks beside it are not drivable
    assert (sem == 2).sum() > 200
    x, y = bev_pixel_centres()
    beyond = np.abs(y) > 12  # past the sidewalks of a 2+2-lane road
    assert (sem[beyond] == 1).mean() < 0.2


def test_semantic_raster_puts_polygons_at_their_ego_frame_pixels():
    b = MeshBuilder()
    b.add(np.zeros((1, 3, 3)), 0)
    road = EGO_POSE.world_from_ego(np.array([[-5.0, -4.0], [40.0, -4.0], [40.0, 4.0], [-5.0, 4.0]]))
    line = EGO_POSE.world_from_ego(np.array([[0.0, 1.9], [40.0, 1.9], [40.0, 2.1], [0.0, 2.1]]))
    walk = EGO_POSE.world_from_ego(np.array([[10.0, -4.0], [14.0, -4.0], [14.0, 0.0], [10.0, 0.0]]))
    st = assemble_static_scene(b, [road, walk, line], [1, 0, 2], terrain=False)
    sem = labels.bev_semantic(st.label_map, EGO_POSE)
    x, y = bev_pixel_centres()
    inside_road = (np.abs(y) < 3.9) & (x < 31.9)
    assert (sem[(np.abs(y) > 4.2)] == 0).all()
    walk_px = (x > 10.2) & (x < 13.8) & (y > -3.8) & (y < -0.2)
    assert (sem[walk_px] == 0).all()  # painted after the road: a cut-out
    line_px = (np.abs(y - 2.0) < 0.05) & (x > 1) & (x < 31)
    assert (sem[line_px] == 2).all()
    rest = inside_road & ~walk_px & (np.abs(y - 2.0) > 0.3) & ~((x > 9.8) & (x < 14.2) & (y < 0.2))
    assert (sem[rest] == 1).all()


def test_boxes_lie_inside_the_bev_area_in_the_ego_frame():
    inside = agent_at("in", 10.0, -5.0, 0.5, speed_mps=3.0)
    behind = agent_at("behind", -6.0, 0.0)
    aside = agent_at("aside", 10.0, 17.0)
    person = agent_at("p", 5.0, 3.0, cls="pedestrian", dims=(0.4, 0.5, 1.75))
    frame = frame_at(agents=(inside, behind, aside, person))
    out = labels.boxes(frame, [], {"in": 42, "behind": 7})
    got = {(b.track_id, b.t) for b in out}
    assert got == {("in", 0), ("p", 0)}
    b = next(b for b in out if b.track_id == "in")
    assert abs(b.x_m - 10.0) < 1e-9 and abs(b.y_m + 5.0) < 1e-9 and abs(b.yaw_rad - 0.5) < 1e-9
    assert b.lidar_points == 42 and b.length_m == 4.5 and b.speed_mps == 3.0
    assert next(b for b in out if b.track_id == "p").lidar_points == 0


def test_future_boxes_of_a_parked_car_equal_its_current_box():
    parked = agent_at("parked", 14.0, 3.5, 0.2)
    moving = agent_at("moving", 8.0, -2.0, 0.0, speed_mps=4.0)
    moved = [agent_at("moving", 8.0 + 2.0 * k, -2.0, 0.0, speed_mps=4.0) for k in (1, 2)]
    frame = frame_at(agents=(parked, moving))
    # the ego drives on: future boxes are still in the ego frame at t
    ego_future = [
        Pose(*EGO_POSE.world_from_ego(np.array([[3.0 * k, 0.0]]))[0], EGO_POSE.yaw_rad)
        for k in (1, 2, 3, 4)
    ]
    future = _future(frame, [(parked, moved[0]), (parked, moved[1]), (), ()], ego_future)
    out = labels.boxes(frame, future, {"parked": 10})
    by = {(b.track_id, b.t): b.row() for b in out}
    for t in (1, 2):
        for key in ("x", "y", "yaw", "length", "width"):
            assert abs(by[("parked", t)][key] - by[("parked", 0)][key]) < 1e-9
        assert by[("parked", t)]["lidar_points"] == 0
        assert abs(by[("moving", t)]["x"] - (8.0 + 2.0 * t)) < 1e-9


def test_waypoints_of_a_stopped_ego_are_zero_and_of_a_moving_one_ahead():
    frame = frame_at()
    stopped = labels.waypoints(frame, [frame_at() for _ in range(4)])
    assert np.allclose(stopped, 0.0, atol=1e-9)
    ahead = [
        Pose(*EGO_POSE.world_from_ego(np.array([[2.5 * k, 0.1 * k]]))[0], EGO_POSE.yaw_rad)
        for k in (1, 2, 3, 4)
    ]
    wps = np.array(labels.waypoints(frame, [frame_at(p) for p in ahead])).reshape(4, 2)
    np.testing.assert_allclose(wps[:, 0], [2.5, 5.0, 7.5, 10.0], atol=1e-9)
    np.testing.assert_allclose(wps[:, 1], [0.1, 0.2, 0.3, 0.4], atol=1e-9)


def test_a_row_of_labels_satisfies_the_schema():
    frame = frame_at(
        agents=(agent_at("car", 10.0, 1.0),), traffic_light="red", light_distance_m=12.0
    )
    future = [frame_at(agents=(agent_at("car", 10.0, 1.0),)) for _ in range(4)]
    row = labels.frame_labels(frame, future, {"car": 30}).row()
    assert abs(row["target_point"][0] - 20.0) < 1e-6 and abs(row["target_point"][1]) < 1e-6
    row.update(
        episode_id="t-0-0",
        frame=0,
        town="t",
        weather="foggy",
        behaviour="cautious",
        image=codecs.encode_image(np.zeros((256, 256, 3), np.uint8)),
        lidar_bev=codecs.encode_lidar_bev(np.zeros((256, 256, 4), np.uint8)),
        lidar_ground_t=codecs.encode_lidar_ground(np.zeros((256, 256), np.uint8)),
        bev_semantic=codecs.encode_bev_semantic(np.zeros((256, 256), np.uint8)),
    )
    meta = schemas.file_metadata(generator_version="t", config={}, network_sha256="0" * 64, seed=0)
    table = pa.Table.from_pylist([row], schema=schemas.schema(meta))
    schemas.validate(table)


def test_labels_do_not_import_the_render_scene():
    import subprocess
    import sys

    code = (
        "import sys, datagen.labels; "
        "bad = [m for m in ('datagen.sensors.scene', 'datagen.sensors.raycast', 'datagen.sensors.actors') "
        "if m in sys.modules]; assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
