"""A short real episode: SUMO world -> sensors -> labels -> a validated v1 table."""

from __future__ import annotations

import json

import numpy as np
import pytest

import schemas
from datagen import episode
from datagen.state import Pose
from datagen.world.towns import network_sha256
from schemas import codecs

N_FRAMES = 6


@pytest.fixture(scope="module")
def run(grid3, fresh_cache):
    spec = episode.EpisodeSpec(
        episode_id="grid3-7-0",
        town="grid3",
        net_path=str(grid3[0]),
        seed=7,
        weather="rainy",
        behaviour="cautious",
        n_frames=N_FRAMES,
    )
    progress: list[int] = []
    result = episode.run_episode(spec, progress=progress.append)
    again = episode.run_episode(spec)
    return spec, result, again, progress


def test_episode_table_is_valid_and_complete(grid3, run):
    grid3_net = grid3[0]
    spec, result, _, progress = run
    table = result.table
    schemas.validate(table)
    assert table.num_rows == N_FRAMES and result.end_reason is None
    assert sum(progress) == N_FRAMES
    df = table.to_pandas()
    assert df.frame.tolist() == list(range(N_FRAMES))
    np.testing.assert_allclose(np.diff(df.time_s), 0.5, atol=1e-6)
    assert (df.weather == "rainy").all() and (df.episode_id == spec.episode_id).all()
    meta = {k.decode(): v.decode() for k, v in table.schema.metadata.items()}
    assert meta[schemas.META_NETWORK_HASH] == network_sha256(grid3_net)
    assert meta[schemas.META_SEED] == "7"
    config = json.loads(meta[schemas.META_CONFIG_JSON])
    assert config["lidar"]["channels"] == 64 and config["camera"]["fov_deg"] == 100.0
    assert config["bev_grid"]["px_per_m"] == 8.0 and "rainy" in config["lidar_weather"]
    assert set(result.stats["timing"]) == set(episode.STAGES)


def test_episode_sensor_columns_decode_with_history(run):
    _, result, _, _ = run
    row = result.table.slice(0, 1).to_pylist()[0]
    assert codecs.decode_image(row["image"]).shape == (256, 256, 3)
    lidar = codecs.decode_lidar_bev(row["lidar_bev"])
    assert lidar[..., 0].sum() > 1000  # ground returns of three sweeps
    ground_t = codecs.decode_lidar_ground(row["lidar_ground_t"])
    assert ground_t.shape == (256, 256) and (ground_t <= lidar[..., 0]).all()
    assert 0 < ground_t.sum() < lidar[..., 0].sum()  # the sweep at t alone, not t-1 and t-2
    sem = codecs.decode_bev_semantic(row["bev_semantic"])
    assert (sem[230:256, 120:136] > 0).mean() > 0.9  # the ego stands on the road


def test_waypoints_match_the_recorded_future(run):
    _, result, _, _ = run
    df = result.table.to_pandas()
    for k in range(N_FRAMES - 1):
        pose = Pose(df.ego_x[k], df.ego_y[k], float(df.ego_yaw[k]))
        nxt = pose.ego_from_world(np.array([[df.ego_x[k + 1], df.ego_y[k + 1]]]))[0]
        np.testing.assert_allclose(df.waypoints[k][:2], nxt, atol=1e-3)


def test_same_seed_same_table(run):
    _, result, again, _ = run
    assert result.table.equals(again.table)


def test_recovery_frames_are_labelled_in_their_rigs_frame(tmp_path, monkeypatch, grid3):
    """With every frame a recovery frame, the world is the same (the rigs only move the
    sensors), and each label, moved from the rig's frame back into the ego's, is the one the
    frame has without recovery."""
    monkeypatch.setenv("IIDSU_CACHE", str(tmp_path))
    spec = episode.EpisodeSpec("grid3-7-0", "grid3", str(grid3[0]), 7, "sunny", "normal", 4)
    plain = episode.run_episode(spec).table.to_pandas()
    table = episode.run_episode(spec, episode.SensorConfig(recovery_share=1.0)).table
    shifted = table.to_pandas()
    config = json.loads(table.schema.metadata[schemas.META_CONFIG_JSON.encode()])
    assert config["recovery_share"] == 1.0  # the shards say how they were made
    assert (plain.rig_shift_m == 0).all() and (plain.rig_yaw_rad == 0).all()
    assert (shifted.rig_shift_m != 0).all() and (shifted.rig_shift_m.abs() <= 1.0).all()
    assert (shifted.rig_yaw_rad.abs() <= np.radians(5.0) + 1e-6).all()
    np.testing.assert_array_equal(plain.ego_x, shifted.ego_x)
    np.testing.assert_array_equal(plain.ego_speed, shifted.ego_speed)
    for (_, a), (_, b) in zip(plain.iterrows(), shifted.iterrows()):
        rig = Pose(0.0, float(b.rig_shift_m), float(b.rig_yaw_rad))  # the rig in the ego frame
        wp = rig.world_from_ego(np.asarray(b.waypoints, np.float64).reshape(4, 2))
        np.testing.assert_allclose(wp, np.asarray(a.waypoints).reshape(4, 2), atol=1e-3)
        tp = rig.world_from_ego(np.asarray(b.target_point, np.float64))
        np.testing.assert_allclose(tp[0], a.target_point, atol=1e-3)
        assert a.image != b.image  # the camera looked from elsewhere
