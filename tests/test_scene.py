"""The static town mesh, its tiles and cache, actor boxes and the per-frame scene."""

from __future__ import annotations

import math

import numpy as np
import pytest

from datagen.sensors import actors, raycast, scene
from datagen.sensors.mesh import Material
from datagen.sensors.raycast import SceneBuilder
from datagen.state import Pose
from tests.scenes import EGO_POSE, agent_at, flat_scene, frame_at


def test_town_mesh_has_every_static_material(grid3):
    _, grid3_scene = grid3
    mats = set(np.unique(grid3_scene.material).tolist())
    for m in (
        Material.ROAD,
        Material.MARKING,
        Material.SIDEWALK,
        Material.TERRAIN,
        Material.BUILDING,
        Material.POLE,
        Material.SIGN,
        Material.LAMP,
    ):
        assert m in mats, m.name
    # one or two heads per signalised entry (4 entries at the middle node), lamps tagged
    assert 4 <= len(grid3_scene.head_xy_m) <= 8
    lamps = grid3_scene.tag[grid3_scene.material == Material.LAMP]
    assert lamps.min() >= 0 and lamps.max() < 3 * len(grid3_scene.head_xy_m)


def test_buildings_stay_off_roads_and_sidewalks(grid3):
    _, grid3_scene = grid3
    from shapely import Point, Polygon
    from shapely.strtree import STRtree

    st = grid3_scene
    lm = st.label_map
    rings = [lm.xy_m[lm.start[k] : lm.start[k + 1]] for k in range(len(lm.class_id))]
    tree = STRtree([Polygon(r).buffer(0) for r in rings])
    walls = st.triangles_m[st.material == Material.BUILDING]
    base = walls.reshape(-1, 3)
    base = base[base[:, 2] < 0.01][:, :2]
    hits = tree.query([Point(p) for p in base], predicate="intersects")
    assert hits.shape[1] == 0, "a building corner lies on a road, sidewalk or marking"


def test_tiles_hold_their_triangles_within_reach(grid3):
    st = grid3[1]
    centres = st.tile_centres_m()
    tile_of = np.repeat(np.arange(len(centres)), np.diff(st.tile_start))
    d = np.linalg.norm(st.triangles_m[..., :2] - centres[tile_of][:, None, :], axis=2).max(1)
    assert (d <= st.tile_reach_m[tile_of] + 1e-3).all()


def test_culling_keeps_everything_within_the_sensors_reach(grid3):
    st = grid3[1]
    pose = Pose(130.0, 95.0, 0.3)
    builder = SceneBuilder(st, reach_m=60.0)
    tiles = builder.visible_tiles(np.array([pose.x_m, pose.y_m]), 60.0)
    kept = np.zeros(st.n_triangles, bool)
    for t in tiles:
        kept[st.tile_start[t] : st.tile_start[t + 1]] = True
    near = (np.linalg.norm(st.triangles_m[..., :2] - (pose.x_m, pose.y_m), axis=2) < 60.0).any(1)
    assert kept[near].all()
    assert kept.sum() < st.n_triangles  # and it does cull


def test_static_scene_is_deterministic_and_cached(grid3, tmp_path):
    grid3_net, grid3_scene = grid3
    again = scene.build_static_scene(grid3_net)
    np.testing.assert_array_equal(again.triangles_m, grid3_scene.triangles_m)
    np.testing.assert_array_equal(again.colour_rgb, grid3_scene.colour_rgb)
    scene._loaded.clear()  # another test may have loaded it into this process already
    first = scene.load_static_scene(grid3_net, cache_dir=tmp_path)
    assert list(tmp_path.glob("*.npz")), "no cache file written"
    scene._loaded.clear()
    second = scene.load_static_scene(grid3_net, cache_dir=tmp_path)
    for name in ("triangles_m", "material", "tile_start", "head_xy_m"):
        np.testing.assert_array_equal(getattr(first, name), getattr(second, name))
    for name in ("xy_m", "start", "class_id", "bbox_m"):
        np.testing.assert_array_equal(
            getattr(first.label_map, name), getattr(second.label_map, name)
        )


@pytest.mark.parametrize(
    "cls,dims",
    [
        ("vehicle", (4.5, 1.8, 1.5)),
        ("vehicle", (12.0, 2.55, 3.2)),
        ("pedestrian", (0.4, 0.5, 1.75)),
        ("bicycle", (1.7, 0.65, 1.7)),
    ],
)
def test_actor_boxes_fill_the_agents_extent(cls, dims):
    a = agent_at("a", 10.0, -3.0, 0.5, cls=cls, dims=dims)
    mesh = actors.actor_mesh([a])
    pts = mesh.triangles_m.reshape(-1, 3).astype(np.float64)
    local = a.pose.ego_from_world(pts[:, :2])
    L, W, H = dims
    tol = 1e-3
    assert local[:, 0].min() >= -L / 2 - tol and local[:, 0].max() <= L / 2 + tol
    assert local[:, 1].min() >= -W / 2 - tol and local[:, 1].max() <= W / 2 + tol
    assert pts[:, 2].min() >= -tol and pts[:, 2].max() <= H + tol
    # it spans most of the box (no floating fragments far inside)
    assert local[:, 0].max() - local[:, 0].min() > 0.6 * L
    assert pts[:, 2].max() > 0.95 * H
    assert (mesh.actor == 0).all()


def test_frame_scene_excludes_the_ego_and_far_agents():
    st = flat_scene()
    near = agent_at("near", 10.0, 0.0)
    far = agent_at("far", 400.0, 0.0)
    fs = SceneBuilder(st, reach_m=100.0).build(frame_at(agents=(near, far)))
    assert [a.track_id for a in fs.agents] == ["near"]
    assert (fs.actors.actor == 0).all()


def test_cell_scenes_are_committed_once_per_process_and_reused_across_episodes():
    st = flat_scene()
    before = raycast.cell_commits
    for _episode in range(3):
        builder = SceneBuilder(st, reach_m=100.0)
        for k in range(3):  # three cells apart
            builder.build(frame_at(Pose(EGO_POSE.x_m + raycast.CELL_M * k, EGO_POSE.y_m, 0.0)))
        assert builder.rebuilds == 3
    assert raycast.cell_commits == before + 3


def test_static_scene_is_reused_until_the_ego_leaves_its_cell():
    st = flat_scene()
    builder = SceneBuilder(st, reach_m=100.0)
    x0 = (math.floor(EGO_POSE.x_m / raycast.CELL_M) + 0.1) * raycast.CELL_M
    builder.build(frame_at(Pose(x0, EGO_POSE.y_m, 0.0)))
    first = builder.build(frame_at(Pose(x0 + 10, EGO_POSE.y_m, 1.0)))
    assert builder.rebuilds == 1
    moved = builder.build(frame_at(Pose(x0 + raycast.CELL_M, EGO_POSE.y_m, 0.0)))
    assert builder.rebuilds == 2 and moved.static_embree is not first.static_embree
