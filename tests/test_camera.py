"""The front camera: geometry of the crop, weather looks, traffic-light lamps."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from datagen.sensors import camera
from datagen.sensors.raycast import SceneBuilder
from datagen.state import Pose
from tests.scenes import EGO_POSE, agent_at, flat_scene, frame_at

CFG = camera.CameraConfig()
SUN = np.array([0.3, 0.5, 0.81])


def _render(static, frame, weather="sunny", seed=0):
    fs = SceneBuilder(static, reach_m=160.0).build(frame)
    cam = camera.Camera(CFG)
    img = cam.render(
        fs, frame.ego.pose, camera.CAMERA_WEATHER[weather], np.random.default_rng(seed), SUN
    )
    return img, fs, cam


def project(x_m: float, y_m: float, z_m: float) -> tuple[float, float]:
    """Ego-frame point -> continuous (row, col) in the 256x256 crop (pinhole, no pitch)."""
    f = CFG.focal_px
    fwd, right, down = x_m - CFG.mount_x_m, -y_m, CFG.mount_z_m - z_m
    u = f * right / fwd + CFG.width_px / 2 - (CFG.width_px - CFG.crop_px) / 2
    v = f * down / fwd + CFG.height_px / 2 - (CFG.height_px - CFG.crop_px) / 2
    return v, u


def test_crop_is_the_centre_of_a_100_degree_400x300_image():
    d = camera.ray_directions(CFG)
    assert d.shape == (256 * 256, 3)
    # the full image's edge would be at 50 degrees; the crop's edge column sits at atan(128/f)
    half = math.degrees(math.atan(128 / CFG.focal_px))
    edge = d.reshape(256, 256, 3)[128, 0]
    assert abs(math.degrees(math.atan2(edge[1], edge[0])) - half) < 0.3
    assert abs(CFG.focal_px - 200 / math.tan(math.radians(50))) < 1e-9
    centre = d.reshape(256, 256, 3)[127:129, 127:129].mean((0, 1))
    assert centre[0] > 0.9999  # the optical axis points straight ahead


def test_box_appears_at_the_expected_pixels():
    car = agent_at("car", 15.0, 2.5, 0.3, dims=(4.5, 1.8, 1.5))
    frame = frame_at(agents=(car,))
    img, fs, cam = _render(flat_scene(), frame)
    empty, _, _ = _render(flat_scene(), frame_at())
    origins, dirs = cam.rays(frame.ego.pose)
    _, prim = fs.cast(origins, dirs, CFG.range_m)
    is_car = (prim >= 0) & (fs.actor_of(prim) == 0)
    is_car = is_car.reshape(256, 256)
    # the box's centre projects onto a car pixel, and the car's pixels sit where the box is
    r, c = project(15.0, 2.5, 0.9)
    assert is_car[int(r), int(c)]
    rows, cols = np.nonzero(is_car)
    corners = [
        project(15.0 + dx, 2.5 + dy, z)
        for dx in (-2.6, 2.6)
        for dy in (-1.5, 1.5)
        for z in (0, 1.5)
    ]
    rs, cs = zip(*corners)
    assert rows.min() >= min(rs) - 2 and rows.max() <= max(rs) + 2
    assert cols.min() >= min(cs) - 2 and cols.max() <= max(cs) + 2
    # and the rendered image differs from the empty road exactly there (up to edge blending)
    diff = np.abs(img.astype(int) - empty.astype(int)).sum(2) > 30
    assert diff[is_car].mean() > 0.9 and diff[~is_car].mean() < 0.01


def _contrast_pair(weather):
    near = EGO_POSE.world_from_ego(np.array([[10.0, -3.0]]))[0]
    far = EGO_POSE.world_from_ego(np.array([[60.0, 8.0]]))[0]
    yaw = EGO_POSE.yaw_rad
    static = flat_scene(
        [((*near, 1.0), (1.0, 1.0, 2.0), yaw), ((*far, 6.0), (6.0, 6.0, 12.0), yaw)]
    )
    img, _, _ = _render(static, frame_at(), weather)
    rn, cn = project(10.0 - 0.5, -3.0, 1.0)
    rf, cf = project(60.0 - 3.0, 8.0, 6.0)
    fog = (
        np.asarray(camera.CAMERA_WEATHER[weather].fog_rgb, float)
        * camera.CAMERA_WEATHER[weather].brightness
    )
    return (
        np.abs(img[int(rn), int(cn)] - fog).mean(),
        np.abs(img[int(rf), int(cf)] - fog).mean(),
        img[int(rn), int(cn)].astype(float),
        img[int(rf), int(cf)].astype(float),
    )


def test_fog_lowers_contrast_with_distance():
    near_fog, far_fog, _, _ = _contrast_pair("foggy")
    assert far_fog < 0.35 * near_fog
    _, _, near_px, far_px = _contrast_pair("sunny")
    assert np.abs(near_px - far_px).mean() < 20  # in clear air the two look alike


def test_the_four_weathers_look_different():
    static = flat_scene([((EGO_POSE.x_m + 30, EGO_POSE.y_m + 20, 5.0), (8.0, 8.0, 10.0), 0.0)])
    frame = frame_at(agents=(agent_at("car", 12.0, -2.0),))
    imgs = {w: _render(static, frame, w)[0].astype(float) for w in camera.CAMERA_WEATHER}
    names = list(imgs)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            assert np.abs(imgs[a] - imgs[b]).mean() > 8, (a, b)
    sky = {w: im[:20].reshape(-1, 3).mean(0) for w, im in imgs.items()}
    assert sky["sunny"][2] > sky["sunny"][0] + 40  # blue sky
    for w in ("cloudy", "rainy", "foggy"):
        assert abs(sky[w][2] - sky[w][0]) < 20, w  # grey skies
    lum = {w: im.mean() for w, im in imgs.items()}
    assert lum["rainy"] < lum["cloudy"] and lum["rainy"] < lum["sunny"]
    # cloudy light is flat: less spread than sunny on the same road and box
    assert imgs["cloudy"][128:].std() < imgs["sunny"][128:].std()


def test_rain_streaks_follow_the_seed():
    static = flat_scene()
    a, _, _ = _render(static, frame_at(), "rainy", seed=1)
    b, _, _ = _render(static, frame_at(), "rainy", seed=1)
    c, _, _ = _render(static, frame_at(), "rainy", seed=2)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def _signals_with(st, k: int, own: str, other: str) -> tuple[tuple[str, str], ...]:
    """A state string for head k's light: `own` on head k's links, `other` on every other."""
    tls = str(st.head_tls[k])
    n = int(st.head_link_index.max()) + 1
    chars = [other] * n
    for i in st.head_link_index[st.head_link_start[k] : st.head_link_start[k + 1]]:
        chars[i] = own
    return ((tls, "".join(chars)),)


def _facing_ego(st, k: int, distance_m: float) -> Pose:
    """The ego approaching head k head-on from `distance_m`."""
    facing = float(st.head_yaw_rad[k])
    hx, hy = st.head_xy_m[k]
    back = facing + math.pi
    return Pose(hx - distance_m * math.cos(back), hy - distance_m * math.sin(back), back)


@pytest.mark.parametrize("own,slot", [("r", 0), ("y", 1), ("G", 2), ("g", 2)])
def test_every_head_shows_its_own_lights_state_whatever_the_label(grid3, own, slot):
    st = grid3[1]
    k = 0
    other = "r" if own != "r" else "G"
    frame = frame_at(_facing_ego(st, k, 80.0), traffic_light="none")  # no light governs it
    frame = dataclasses.replace(frame, signals=_signals_with(st, k, own, other))
    lit = camera.lit_slots(st, frame)
    assert lit[k] == slot
    same = st.head_tls == st.head_tls[k]
    links = [
        set(st.head_link_index[st.head_link_start[h] : st.head_link_start[h + 1]].tolist())
        for h in range(len(lit))
    ]
    cross = np.array([same[h] and not (links[h] & links[k]) for h in range(len(lit))])
    assert cross.any() and (lit[cross] == camera.SUMO_LAMP_SLOT[other]).all()  # cross streets
    assert (lit[~same] == -1).all()  # heads of lights with no state stay dark


def test_a_lit_head_shows_in_the_image_when_the_label_is_none(grid3):
    st = grid3[1]
    k = 0
    frame = frame_at(_facing_ego(st, k, 35.0), traffic_light="none")  # beyond 30 m: "none"
    frame = dataclasses.replace(frame, signals=_signals_with(st, k, "G", "r"))
    fs = SceneBuilder(st, reach_m=160.0).build(frame)
    cam = camera.Camera(CFG)
    w = camera.CAMERA_WEATHER["cloudy"]
    lit = cam.render(
        fs, frame.ego.pose, w, np.random.default_rng(0), SUN, camera.lit_slots(st, frame)
    )
    dark = cam.render(fs, frame.ego.pose, w, np.random.default_rng(0), SUN, None)
    diff = np.abs(lit.astype(int) - dark.astype(int)).sum(2) > 60
    assert diff.sum() >= 1
    assert (lit[diff][:, 1] > lit[diff][:, 0]).all()  # the changed pixels are green


def test_real_sumo_signals_light_heads_in_view_when_the_label_is_none(grid3):
    from datagen.world import World, WorldConfig

    net, st = grid3
    seen_none_lit = seen_cross_differs = False
    with World(WorldConfig(net_path=net, seed=4, weather="sunny", behaviour="normal")) as world:
        for step in range(80):
            if step:
                world.advance(0.5)
            if world.ended:
                break
            frame = world.state()
            states = dict(frame.signals)
            assert set(st.head_tls.tolist()) <= set(states)  # every head's light is read
            lit = camera.lit_slots(st, frame)
            assert (lit >= 0).all()  # SUMO programs here never switch a light off
            if frame.traffic_light == "none":
                seen_none_lit = True
            seen_cross_differs |= len(set(lit.tolist())) > 1
    assert seen_none_lit and seen_cross_differs


def test_actor_pixel_window_loses_no_hits():
    agents = (
        agent_at("ahead", 12.0, 1.0, 0.3),
        agent_at("beside", 2.5, 3.2, 0.0),  # its bounding sphere straddles the camera plane
        agent_at("behind", -9.0, -1.0, 2.0, dims=(12.0, 2.55, 3.2)),
        agent_at("near", 4.0, -1.5, 1.0, cls="pedestrian", dims=(0.4, 0.5, 1.75)),
        agent_at("far", 70.0, -20.0, 0.0),
    )
    frame = frame_at(agents=agents)
    fs = SceneBuilder(flat_scene(), reach_m=160.0).build(frame)
    cam = camera.Camera(CFG)
    origins, dirs = cam.rays(frame.ego.pose)
    window = cam.actor_rays(fs, frame.ego.pose)
    assert len(window) < 0.8 * len(origins)  # close agents: wide windows
    d_all, p_all = fs.cast(origins, dirs, CFG.range_m, None)
    d_win, p_win = fs.cast(origins, dirs, CFG.range_m, window)
    np.testing.assert_array_equal(p_all, p_win)
    np.testing.assert_array_equal(d_all, d_win)
    seen = set(fs.actor_of(p_all[p_all >= fs.n_static]).tolist())
    assert {0, 1, 3} <= seen  # ahead, beside (partly in view), the pedestrian
