"""The two ray backends behind one interface (datagen/sensors/raycast.py): the Embree fast path
(datagen/sensors/embree.py) and trimesh's ray API (datagen/sensors/trimesh_rays.py) give the
same hits on a town scene; the fast path falls back to trimesh with one warning line."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from datagen.sensors import camera, lidar, raycast, trimesh_rays
from datagen.sensors.config import SensorConfig
from datagen.sensors.raycast import SceneBuilder
from datagen.state import Pose
from tests.scenes import agent_at, frame_at

EGO = Pose(100.0, 95.0, 0.3)  # on the grid3 network's middle junction
TIE_M = 1e-4  # distances agree to Embree's float32 (1.5e-5 m measured at 100 m)


def _frame():
    agents = tuple(
        agent_at(f"a{k}", 8.0 + 6 * k, (-1) ** k * 2.0, 0.1 * k, ego=EGO) for k in range(6)
    )
    return frame_at(ego=EGO, agents=agents)


@pytest.fixture(scope="module")
def scenes(grid3) -> dict:
    """The frame's scene on the grid3 town, built by each backend."""
    frame = _frame()
    return {
        name: SceneBuilder(grid3[1], reach_m=160.0, raycaster=name).build(frame)
        for name in raycast.RAYCASTERS
    }


def _same_hits(fs, dist_a, prim_a, dist_b, prim_b):
    """Both hit or both miss; equal distances; a different primitive only in a tie between
    coplanar static triangles of one material and colour (overlapping road polygons; a face
    and its back)."""
    np.testing.assert_array_equal(np.isfinite(dist_a), np.isfinite(dist_b))
    hit = np.isfinite(dist_a)
    np.testing.assert_allclose(dist_a[hit], dist_b[hit], rtol=0, atol=TIE_M)
    other = np.flatnonzero(prim_a != prim_b)
    assert len(other) < 0.5 * hit.sum()
    a, b = prim_a[other], prim_b[other]
    assert (a < fs.n_static).all() and (b < fs.n_static).all(), "an actor hit differs"
    np.testing.assert_array_equal(fs.static_material[a], fs.static_material[b])
    np.testing.assert_array_equal(fs.static_colour_rgb[a], fs.static_colour_rgb[b])
    facing = np.abs((fs.static_normals[a] * fs.static_normals[b]).sum(1))  # one plane
    np.testing.assert_allclose(facing, 1.0, atol=1e-5)


def test_both_backends_give_the_same_hits_on_a_town_scene(scenes):
    fast, portable = scenes["embree"], scenes["trimesh"]
    assert fast.backend.NAME == "embree" and portable.backend is trimesh_rays
    d = lidar.ray_directions(lidar.LidarConfig()).astype(np.float32)  # all round, 32 beams
    origins = raycast.repeat_rows(np.array([EGO.x_m, EGO.y_m, 1.7], np.float32), len(d))

    dist_a, prim_a = fast.cast(origins, d, 100.0)
    dist_b, prim_b = portable.cast(origins, d, 100.0)
    assert (prim_a >= fast.n_static).sum() > 100 and (prim_a < 0).any()  # agents, sky
    _same_hits(fast, dist_a, prim_a, dist_b, prim_b)

    dist_a, actor_a = fast.distances(origins, d, 100.0)
    dist_b, actor_b = portable.distances(origins, d, 100.0)
    np.testing.assert_allclose(dist_a, dist_b, rtol=0, atol=TIE_M)
    np.testing.assert_array_equal(actor_a, actor_b)

    # shadow rays toward one sun from the ground around the ego (some under the agents)
    rng = np.random.default_rng(0)
    xy = np.array([EGO.x_m, EGO.y_m]) + rng.uniform(-40, 40, (5000, 2))
    ground = np.concatenate([xy, np.full((5000, 1), 0.03)], 1).astype(np.float32)
    sun = np.array([[0.3, 0.2, 0.93]], np.float32) / np.float32(np.linalg.norm([0.3, 0.2, 0.93]))
    shadow = fast.occluded(ground, sun, 200.0)
    assert 0 < shadow.sum() < len(shadow)
    np.testing.assert_array_equal(shadow, portable.occluded(ground, sun, 200.0))


def test_both_backends_render_the_same_camera_image_and_lidar_sweep(scenes):
    images, sweeps = [], []
    for fs in scenes.values():
        cam = camera.Camera(camera.CameraConfig())
        w = camera.CAMERA_WEATHER["sunny"]
        images.append(cam.render(fs, EGO, w, np.random.default_rng(0), np.array([0.3, 0.5, 0.8])))
        sun = lidar.LIDAR_WEATHER["sunny"]
        sweeps.append(lidar.Lidar().sweep(fs, EGO, sun, np.random.default_rng(0)))
    differ = (images[0] != images[1]).any(-1)
    assert differ.mean() < 1e-3, f"{differ.sum()} pixels differ"
    np.testing.assert_allclose(sweeps[0].points_m, sweeps[1].points_m, rtol=0, atol=TIE_M)
    np.testing.assert_array_equal(sweeps[0].actor_hits, sweeps[1].actor_hits)


def test_the_portable_backend_keeps_the_fast_paths_contract():
    empty = trimesh_rays.Scene(np.zeros((0, 3, 3), np.float32))
    tfar = np.full(3, 10, np.float32)
    prim = trimesh_rays.intersect(
        empty, np.zeros((1, 3), np.float32), np.eye(3, dtype=np.float32), tfar
    )
    assert (prim == -1).all() and (tfar == 10).all()
    with pytest.raises(ValueError, match="directions"):
        trimesh_rays.intersect(empty, np.zeros((1, 3), np.float32), np.eye(3), tfar)
    # a far bound short of the hit is a miss, and leaves tfar as it was
    wall = np.array([[[5, -1, -1], [5, 1, -1], [5, 0, 2]]], np.float32)
    scene = trimesh_rays.Scene(wall)
    ray = np.array([[1, 0, 0]], np.float32)
    tfar = np.array([4.0, 6.0], np.float32)
    prim = trimesh_rays.intersect(scene, np.zeros((1, 3), np.float32), np.repeat(ray, 2, 0), tfar)
    np.testing.assert_array_equal(prim, [-1, 0])
    np.testing.assert_allclose(tfar, [4.0, 5.0], atol=1e-6)


def test_without_the_fast_path_trimesh_casts_after_one_warning_line(monkeypatch, capsys):
    monkeypatch.setattr(raycast, "_backends", {})
    monkeypatch.setitem(sys.modules, "datagen.sensors.embree", None)  # it cannot load
    monkeypatch.delenv(raycast._WARNED, raising=False)
    assert raycast.ray_backend("embree") is trimesh_rays
    assert raycast.ray_backend("embree") is trimesh_rays
    assert SensorConfig().to_dict()["raycaster"] == "trimesh"  # the shards say what ran
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("warning: the Embree fast path cannot load")


def test_the_default_config_records_no_raycaster_and_trimesh_is_recorded():
    assert "raycaster" not in SensorConfig().to_dict()  # default shards keep their bytes
    assert SensorConfig(raycaster="trimesh").to_dict()["raycaster"] == "trimesh"
    with pytest.raises(ValueError, match="raycaster must be one of"):
        SensorConfig(raycaster="optix")


def test_a_trimesh_episode_has_the_default_episodes_labels_and_sensor_data(grid3):
    import json

    from datagen import episode
    from schemas import META_CONFIG_JSON, codecs

    net, _ = grid3
    spec = episode.EpisodeSpec("grid3-3-0", "grid3", str(net), 3, "sunny", "normal", 2)
    fast = episode.run_episode(spec).table
    portable = episode.run_episode(spec, sensors=SensorConfig(raycaster="trimesh")).table
    assert fast.num_rows == portable.num_rows == 2
    sensed = {"image", "lidar_bev", "lidar_ground_t"}
    for name in set(fast.column_names) - sensed:
        assert fast.column(name).equals(portable.column(name)), name
    for a, b in zip(fast.column("lidar_bev").to_pylist(), portable.column("lidar_bev").to_pylist()):
        a, b = codecs.decode_lidar_bev(a), codecs.decode_lidar_bev(b)
        assert (a != b).mean() < 1e-4  # measured: equal, or one cell in 131k
    for a, b in zip(fast.column("image").to_pylist(), portable.column("image").to_pylist()):
        a, b = codecs.decode_image(a).astype(int), codecs.decode_image(b).astype(int)
        assert np.abs(a - b).mean() < 0.1  # measured: ~0.01 grey levels
    config = json.loads(portable.schema.metadata[META_CONFIG_JSON.encode()])
    assert config["raycaster"] == "trimesh"
    assert "raycaster" not in json.loads(fast.schema.metadata[META_CONFIG_JSON.encode()])


def test_sensor_raycaster_trimesh_on_the_command_line_forces_it():
    from datagen.errors import UserError
    from datagen.sensors.overrides import parse_sensors

    assert parse_sensors(["raycaster=trimesh"]).raycaster == "trimesh"
    with pytest.raises(UserError, match="raycaster must be one of"):
        parse_sensors(["raycaster=optix"])


def test_drive_takes_a_model_trained_on_either_backends_data():
    from drive.policy import check_sensor_config

    trained = {"sensor_config": SensorConfig().to_dict()}
    check_sensor_config(trained, SensorConfig(raycaster="trimesh").to_dict(), "ckpt")
