"""LiDAR sweeps and the paper's 3-sweep BEV histogram: geometry, alignment, weather."""

from __future__ import annotations

import numpy as np

from datagen.sensors import lidar
from datagen.sensors.raycast import SceneBuilder
from datagen.state import Pose
from schemas import bev_pixel_centres, ego_to_bev_px
from tests.scenes import EGO_POSE, agent_at, flat_scene, frame_at

SUNNY = lidar.LIDAR_WEATHER["sunny"]


def _sweep(static, frame, weather=SUNNY, seed=0):
    fs = SceneBuilder(static, reach_m=100.0).build(frame)
    return lidar.Lidar().sweep(fs, frame.ego.pose, weather, np.random.default_rng(seed))


def _inside_box(x, y, cx, cy, yaw, length, width, margin=0.0):
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dy = x - cx, y - cy
    u, v = c * dx + s * dy, -s * dx + c * dy
    return (np.abs(u) <= length / 2 + margin) & (np.abs(v) <= width / 2 + margin)


def test_rays_cover_the_configured_field_of_view():
    cfg = lidar.LidarConfig()
    d = lidar.ray_directions(cfg)
    assert d.shape == (cfg.channels * cfg.azimuth_steps, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-9)
    el = np.degrees(np.arcsin(d[:, 2]))
    assert abs(el.max() - cfg.upper_fov_deg) < 1e-6 and abs(el.min() - cfg.lower_fov_deg) < 1e-6


def test_box_hits_land_inside_its_footprint_in_the_bev():
    car = agent_at("car", 12.0, 3.0, 0.4)
    frame = frame_at(agents=(car,))
    sweep = _sweep(flat_scene(), frame)
    bev = lidar.bev_histogram([sweep])
    above = bev[..., 1] > 0
    x, y = bev_pixel_centres()
    half_px = 0.5 / 8 * np.sqrt(2)  # a pixel's half diagonal
    foot = _inside_box(x, y, 12.0, 3.0, 0.4, car.length_m, car.width_m, half_px)
    assert above.sum() > 50
    assert not above[~foot].any(), "above-ground returns outside the car's footprint"
    # every above-ground return on the grid came from the car (the scene is otherwise flat)
    assert sweep.actor_hits["car"] >= int(bev[..., 1].sum())
    # ground returns everywhere else, none from under the car's body
    assert bev[..., 0][~foot].sum() > 1000


def test_points_are_in_the_world_frame_at_the_right_range():
    car = agent_at("car", 20.0, 0.0, 0.0, dims=(4.0, 2.0, 3.0))
    sweep = _sweep(flat_scene(), frame_at(agents=(car,)))
    ego = EGO_POSE.ego_from_world(sweep.points_m[:, :2].astype(np.float64))
    on_car = sweep.points_m[:, 2] > 0.6
    # the rear face of the car is 18 m ahead of the ego's centre
    assert np.abs(ego[on_car, 0] - 18.0).min() < 0.01
    assert ego[on_car, 0].min() > 18.0 - 1e-3


def test_a_static_pole_stays_on_one_bev_pixel_while_the_ego_drives_past():
    pole_xy = EGO_POSE.world_from_ego(np.array([[22.0, 4.0]]))[0]
    static = flat_scene([((pole_xy[0], pole_xy[1], 1.5), (0.3, 0.3, 3.0), 0.0)])
    poses = [  # t-2, t-1, t: driving forward 5 m per frame, turning a little
        Pose(*EGO_POSE.world_from_ego(np.array([[-10.0, 0.5]]))[0], EGO_POSE.yaw_rad - 0.1),
        Pose(*EGO_POSE.world_from_ego(np.array([[-5.0, 0.2]]))[0], EGO_POSE.yaw_rad - 0.05),
        EGO_POSE,
    ]
    sweeps = [_sweep(static, frame_at(p)) for p in poses]
    bev = lidar.bev_histogram(sweeps[::-1])  # newest first
    row, col = ego_to_bev_px(np.array([22.0]), np.array([4.0]))
    expected = np.array([row[0], col[0]])
    for ch in (1, 2, 3):
        rows, cols = np.nonzero(bev[..., ch])
        assert len(rows) > 0, f"channel {ch} sees no pole"
        w = bev[rows, cols, ch].astype(float)
        centroid = np.array([np.average(rows + 0.5, weights=w), np.average(cols + 0.5, weights=w)])
        assert np.abs(centroid - expected).max() < 1.5, (ch, centroid, expected)


def test_ground_t_holds_only_the_current_sweeps_ground_hits():
    static = flat_scene()
    poses = [EGO_POSE, Pose(EGO_POSE.x_m + 5.0, EGO_POSE.y_m, EGO_POSE.yaw_rad)]
    now, past = (_sweep(static, frame_at(p)) for p in poses)
    counts = lidar.bev_counts([now, past, past])
    ground_t = lidar.ground_channel(counts)
    alone = lidar.bev_histogram([now])  # a single sweep: ch0 is its ground alone
    np.testing.assert_array_equal(ground_t, alone[..., 0])
    summed = lidar.lidar_bev_channels(counts)[..., 0].astype(int)
    assert (summed >= ground_t).all() and summed.sum() > 2 * ground_t.sum()  # ch0 has the past too
    assert ground_t.sum() > 1000


def test_pose_noise_blurs_only_the_past_sweeps():
    pole_xy = EGO_POSE.world_from_ego(np.array([[15.0, 0.0]]))[0]
    static = flat_scene([((pole_xy[0], pole_xy[1], 1.5), (0.3, 0.3, 3.0), 0.0)])
    sweep = _sweep(static, frame_at())
    exact = lidar.bev_histogram([sweep, sweep, sweep])
    noisy = lidar.bev_histogram(
        [sweep, sweep, sweep], rng=np.random.default_rng(1), pose_noise_m=0.5, pose_noise_rad=0.02
    )
    np.testing.assert_array_equal(exact[..., 1], noisy[..., 1])  # t itself is never perturbed
    assert not np.array_equal(exact[..., 2], noisy[..., 2])


def test_fog_shortens_the_range_and_drops_far_returns():
    walls = []
    for i, r in enumerate((15.0, 30.0, 45.0, 60.0, 75.0)):
        for a in np.linspace(0, 2 * np.pi, 12, endpoint=False) + 0.1 * i:  # rings don't hide rings
            x, y = EGO_POSE.world_from_ego(np.array([[r * np.cos(a), r * np.sin(a)]]))[0]
            walls.append(((x, y, 3.0), (1.0, 6.0, 6.0), float(a)))
    static = flat_scene(walls)
    frame = frame_at()
    clear = _sweep(static, frame, lidar.LIDAR_WEATHER["sunny"])
    fog = _sweep(static, frame, lidar.LIDAR_WEATHER["foggy"])
    rain = _sweep(static, frame, lidar.LIDAR_WEATHER["rainy"])

    def ranges(s):
        o = np.array([*EGO_POSE.world_from_ego(np.array([[1.3, 0.0]]))[0], 2.5])
        return np.linalg.norm(s.points_m - o, axis=1)

    far = {k: (ranges(s) > 30).sum() for k, s in (("clear", clear), ("fog", fog), ("rain", rain))}
    assert far["fog"] < 0.25 * far["clear"]
    assert far["fog"] < far["rain"] < far["clear"]
    assert ranges(fog).max() <= lidar.LIDAR_WEATHER["foggy"].range_m + 0.5
    assert ranges(clear).max() > 70
    # near returns survive the fog far better than far ones
    near_ratio = (ranges(fog) < 12).sum() / max((ranges(clear) < 12).sum(), 1)
    far_ratio = far["fog"] / far["clear"]
    assert near_ratio > 2 * far_ratio


def test_sweeps_are_deterministic_per_seed():
    static = flat_scene([((EGO_POSE.x_m + 20, EGO_POSE.y_m, 2.0), (2.0, 2.0, 4.0), 0.0)])
    frame = frame_at()
    rain = lidar.LIDAR_WEATHER["rainy"]
    a, b = _sweep(static, frame, rain, seed=5), _sweep(static, frame, rain, seed=5)
    c = _sweep(static, frame, rain, seed=6)
    np.testing.assert_array_equal(a.points_m, b.points_m)
    assert len(a.points_m) != len(c.points_m) or not np.array_equal(a.points_m, c.points_m)


def test_histogram_clips_at_255():
    pts = np.tile(
        np.array([[*EGO_POSE.world_from_ego(np.array([[10.0, 0.0]]))[0], 1.0]], np.float32),
        (300, 1),
    )
    bev = lidar.bev_histogram([lidar.Sweep(pts, {}, EGO_POSE)])
    assert bev.dtype == np.uint8 and bev.shape == (256, 256, 4)
    assert bev[..., 1].max() == 255 and bev[..., 0].sum() == 0 and bev[..., 2:].sum() == 0


def test_actor_ray_window_loses_no_hits():
    agents = (
        agent_at("ahead", 12.0, 1.0, 0.3),
        agent_at("beside", 0.5, 3.2, 0.0),
        agent_at("behind", -9.0, -1.0, 2.0, dims=(12.0, 2.55, 3.2)),
        agent_at("near", 3.0, -2.5, 1.0, cls="pedestrian", dims=(0.4, 0.5, 1.75)),
        agent_at("far", 70.0, -20.0, 0.0),
    )
    frame = frame_at(agents=agents)
    fs = SceneBuilder(flat_scene(), reach_m=100.0).build(frame)
    lid = lidar.Lidar()
    origins, dirs = lid.rays(frame.ego.pose)
    window = lid.actor_rays(fs, origins[0].astype(np.float64), frame.ego.pose.yaw_rad)
    assert window is not None and len(window) < 0.8 * len(origins)  # close agents: wide windows
    d_all, a_all = fs.distances(origins, dirs, 85.0, None)
    d_win, a_win = fs.distances(origins, dirs, 85.0, window)
    np.testing.assert_array_equal(a_all, a_win)
    np.testing.assert_array_equal(d_all, d_win)
    assert set(np.unique(a_all[a_all >= 0]).tolist()) == set(range(len(agents)))
