"""The front camera: one ray per pixel of the stored 256x256 centre crop of a 400x300,
100-degree image (paper Sec. III-A), shaded per material with a sun, a sky and the weather.

Mounted as TransFuser's CARLA camera: 1.3 m ahead of the ego's box centre, 2.3 m above the
ground, looking straight ahead (no pitch). Only the crop is cast (65,536 rays); its horizontal
and vertical field of view is 2 * atan(128 / f) = 74.6 degrees with f = 200 / tan(50 deg).

Shading (per pixel, in compiled passes: datagen/sensors/shading.py): base colour of the triangle hit x
(ambient + sun * max(0, n.s) * shadow), with shadow rays towards the sun in sunny weather;
building walls get a procedural window grid; every traffic-light head glows with the real state
of its own light's links, whether or not that light governs the ego (`lit_slots`); rays that
hit nothing within `range_m` see the sky.
Then the weather (CAMERA_WEATHER):

- sunny: blue sky, strong sun with shadows, faint haze far away;
- cloudy: flat grey sky, soft light without shadows, desaturated;
- rainy: dark grey, wet road and sidewalks that mirror the sky at grazing angles (Schlick
  Fresnel), haze, and rain streaks drawn per frame from the Generator;
- foggy: everything fades to grey with distance, exp(-3.912 d / visibility).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from datagen.sensors import shading
from datagen.sensors.mesh import Material
from datagen.sensors.raycast import FrameScene, SensorRays
from datagen.sensors.scene import StaticScene
from datagen.state import FrameState, Pose
from schemas import IMAGE_FOV_DEG, IMAGE_FULL_H_PX, IMAGE_FULL_W_PX, IMAGE_SIZE_PX


@dataclass(frozen=True)
class CameraConfig:
    """The front RGB camera (paper Sec. III-A: 400x300, 100 degrees, 256x256 crop stored).

    Attributes:
        width_px, height_px, fov_deg: the full image (horizontal field of view).
        crop_px: side of the centred square crop that is rendered and stored.
        mount_x_m, mount_z_m: position in the ego frame (ahead of the box centre, above ground).
        range_m: geometry beyond this distance is not drawn (the sky shows; haze hides the cut).
        shadows: cast shadow rays in sunny weather.
    """

    width_px: int = IMAGE_FULL_W_PX
    height_px: int = IMAGE_FULL_H_PX
    fov_deg: float = IMAGE_FOV_DEG
    crop_px: int = IMAGE_SIZE_PX
    mount_x_m: float = 1.3
    mount_z_m: float = 2.3
    range_m: float = 150.0
    shadows: bool = True

    @property
    def focal_px(self) -> float:
        return self.width_px / 2 / math.tan(math.radians(self.fov_deg) / 2)


@dataclass(frozen=True)
class CameraWeather:
    """The look of one weather.

    Attributes:
        sky_zenith_rgb, sky_horizon_rgb: sky colour straight up and at the horizon.
        ambient: light from the sky on every surface (0..1).
        sun: direct sun strength (0..1); shadows only if > 0.5 and CameraConfig.shadows.
        saturation: 1 keeps colours, 0 greys them.
        brightness: overall gain.
        visibility_m: meteorological visibility; contrast falls as exp(-3.912 d / visibility).
        fog_rgb: what distance fades to.
        wet: 0 dry, 1 wet surfaces mirroring the sky at grazing angles.
        streaks: rain streaks drawn per frame.
    """

    sky_zenith_rgb: tuple[int, int, int]
    sky_horizon_rgb: tuple[int, int, int]
    ambient: float
    sun: float
    saturation: float
    brightness: float
    visibility_m: float
    fog_rgb: tuple[int, int, int]
    wet: float = 0.0
    streaks: int = 0


CAMERA_WEATHER = {
    "sunny": CameraWeather(
        sky_zenith_rgb=(70, 125, 215),
        sky_horizon_rgb=(175, 205, 235),
        ambient=0.45,
        sun=0.85,
        saturation=1.1,
        brightness=1.0,
        visibility_m=3000.0,
        fog_rgb=(175, 205, 235),
    ),
    "cloudy": CameraWeather(
        sky_zenith_rgb=(150, 153, 160),
        sky_horizon_rgb=(200, 202, 206),
        ambient=0.85,
        sun=0.12,
        saturation=0.7,
        brightness=0.95,
        visibility_m=1500.0,
        fog_rgb=(195, 197, 201),
    ),
    "rainy": CameraWeather(
        sky_zenith_rgb=(72, 76, 84),
        sky_horizon_rgb=(118, 122, 130),
        ambient=0.62,
        sun=0.05,
        saturation=0.6,
        brightness=0.72,
        visibility_m=350.0,
        fog_rgb=(112, 116, 124),
        wet=1.0,
        streaks=260,
    ),
    "foggy": CameraWeather(
        sky_zenith_rgb=(178, 180, 184),
        sky_horizon_rgb=(178, 180, 184),
        ambient=0.8,
        sun=0.1,
        saturation=0.8,
        brightness=1.0,
        visibility_m=90.0,
        fog_rgb=(178, 180, 184),
    ),
}

DEFAULT_SUN = np.array([0.5, 0.3, 0.81])  # towards the sun, world frame (~54 deg up)
F32 = np.float32
LAMP_RGB = np.array([(255, 45, 30), (255, 190, 20), (40, 255, 110)], np.float32) / 255
GLASS_RGB = np.array([0.17, 0.21, 0.26], np.float32)


def ray_directions(config: CameraConfig) -> np.ndarray:
    """(crop_px * crop_px, 3) float64 unit ray directions, ego frame (x forward, y left, z up),
    row-major over the crop (row 0 at the top)."""
    f = config.focal_px
    x0 = (config.width_px - config.crop_px) / 2
    y0 = (config.height_px - config.crop_px) / 2
    u = x0 + np.arange(config.crop_px) + 0.5 - config.width_px / 2  # right, px
    v = y0 + np.arange(config.crop_px) + 0.5 - config.height_px / 2  # down, px
    V, U = np.meshgrid(v, u, indexing="ij")
    d = np.stack([np.full_like(U, f), -U, -V], -1).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def sun_direction(rng: np.random.Generator) -> np.ndarray:
    """A random sun for an episode: (3,) unit vector towards the sun, world frame; elevation
    30-60 degrees, any azimuth."""
    el = rng.uniform(math.radians(30), math.radians(60))
    az = rng.uniform(0, 2 * math.pi)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


# SUMO signal characters (getRedYellowGreenState) -> lamp slot: r red, s stop (right on red),
# u red-yellow, y/Y yellow, g/G green (minor/major); o/O (off) leave the head dark.
SUMO_LAMP_SLOT = {"r": 0, "R": 0, "s": 0, "u": 0, "y": 1, "Y": 1, "g": 2, "G": 2}


def lit_slots(static: StaticScene, frame: FrameState, range_m: float = 160.0) -> np.ndarray:
    """(H,) int8 lamp lit per signal head: 0 red, 1 yellow, 2 green, -1 dark.

    Every head within `range_m` of the ego shows the real state of its own traffic light's
    links (FrameState.signals; StaticScene.head_link_*), whether or not that light governs the
    ego and at any distance the camera sees: a head lights green if any movement of its
    approach may go, else yellow if one shows yellow, else red. So the image shows what a
    driver would see, and the `traffic_light` label alone says which light governs the ego.
    Heads whose light is unknown (no FrameState.signals, hand-made scenes) stay dark."""
    n = len(static.head_xy_m)
    out = np.full(n, -1, np.int8)
    states = dict(frame.signals)
    if not n or not states:
        return out
    d = static.head_xy_m - np.array([frame.ego.pose.x_m, frame.ego.pose.y_m], np.float32)
    start, index = static.head_link_start, static.head_link_index
    for k in np.flatnonzero(np.hypot(d[:, 0], d[:, 1]) <= range_m):
        state = states.get(str(static.head_tls[k]))
        if state is None:
            continue
        slots = [SUMO_LAMP_SLOT.get(state[i], -1) for i in index[start[k] : start[k + 1]]]
        out[k] = max(slots, default=-1)
    return out


class Camera:
    """Renders the crop from fixed ray directions (computed once)."""

    def __init__(self, config: CameraConfig = CameraConfig()):
        self.config = config
        self.directions_ego = ray_directions(config)
        self._rays = SensorRays(self.directions_ego, config.mount_x_m, config.mount_z_m)
        self._cache: dict = {}
        self._dark = np.full(0, -1, np.int8)  # render's lamps=None: no head lit

    @property
    def n_rays(self) -> int:
        return len(self.directions_ego)

    def rays(self, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """World-frame (origins, directions), each (n_rays, 3) float32."""
        return self._rays.world(pose)

    def actor_rays(self, scene: FrameScene, pose: Pose) -> np.ndarray:
        """Indices of the pixels whose ray can hit an agent's bounding sphere: the union of
        each sphere's projected bounding rectangle (pinhole: u = f * right / forward).

        A sphere wholly ahead of the camera projects inside the rectangle spanned by its
        extreme (right, down) over its nearest and farthest depth; one that reaches behind the
        camera plane can appear anywhere on the side(s) it lies on, out to the image border."""
        cfg = self.config
        n = cfg.crop_px
        if not len(scene.agents):
            return np.zeros(0, np.int64)
        cam = pose.ego_from_world(scene.actor_centres_m[:, :2])
        fwd = cam[:, 0] - cfg.mount_x_m
        right = -cam[:, 1]
        down = cfg.mount_z_m - scene.actor_centres_m[:, 2]
        r = scene.actor_radii_m + 0.05
        f = cfg.focal_px
        x0 = (cfg.width_px - n) / 2 + 0.5 - cfg.width_px / 2  # crop column 0's u
        y0 = (cfg.height_px - n) / 2 + 0.5 - cfg.height_px / 2
        big = 1e6
        mask = np.zeros((n, n), bool)
        for a in np.flatnonzero(fwd + r > 0.05):
            near, far = fwd[a] - r[a], fwd[a] + r[a]
            bounds = []
            for c in (right[a], down[a]):
                lo, hi = c - r[a], c + r[a]
                if near > 0.05:
                    vals = (f * lo / near, f * lo / far, f * hi / near, f * hi / far)
                    bounds.append((min(vals), max(vals)))
                else:  # reaches behind the camera: open towards the border on its side(s)
                    bounds.append(
                        (f * lo / far if lo > 0 else -big, f * hi / far if hi < 0 else big)
                    )
            (u0, u1), (v0, v1) = bounds
            c0, c1 = math.floor(u0 - x0), math.ceil(u1 - x0)
            r0, r1 = math.floor(v0 - y0), math.ceil(v1 - y0)
            if c1 < 0 or r1 < 0 or c0 >= n or r0 >= n:
                continue
            mask[max(r0, 0) : r1 + 1, max(c0, 0) : c1 + 1] = True
        return np.flatnonzero(mask)

    def render(
        self,
        scene: FrameScene,
        pose: Pose,
        weather: CameraWeather,
        rng: np.random.Generator,
        sun_dir: np.ndarray = DEFAULT_SUN,
        lamps: np.ndarray | None = None,
    ) -> np.ndarray:
        """(crop_px, crop_px, 3) uint8 RGB image of the scene from the ego at `pose`.

        Args:
            sun_dir: (3,) unit vector towards the sun, world frame.
            lamps: (H,) lit slot per signal head (`lit_slots`); None: all dark.
            rng: draws the rain streaks.
        """
        cfg = self.config
        origins, dirs = self.rays(pose)
        dist, prim = scene.cast(origins, dirs, cfg.range_m, self.actor_rays(scene, pose))
        sky, reflected_sky = self._skies(weather)
        hi = np.flatnonzero(prim >= 0)
        am = scene.actors
        sun = np.asarray(sun_dir, np.float32)
        # Surface: normal towards the camera, albedo with procedural windows on building
        # walls, and the sun's lambert term (datagen/sensors/shading.py).
        n, albedo, mat, tags, facing, pts, lambert = shading.surface(
            hi, prim, dist, dirs, origins[0], scene.n_static, scene.static_normals,
            scene.static_colour_rgb, scene.static_material, scene.static_tag, am.normals,
            am.colour_rgb, am.material, self._glass(weather), sun,
        )  # fmt: skip

        # Light: ambient + sun (with shadows when sunny); walls see half the sky.
        if cfg.shadows and weather.sun > 0.5:
            lit = np.flatnonzero(lambert > 0)
            o = shading.shadow_origins(pts, n, lit)
            near = _shadow_candidates(o, scene, sun)
            lambert[lit[scene.occluded(o, sun[None], 200.0, near)]] = 0
        gain = np.float32(weather.brightness / 255)
        colour = shading.light(albedo, n, lambert, F32(weather.ambient), F32(weather.sun), gain)

        # Wet surfaces: darker, and mirror the sky at grazing angles (Schlick, F0 = 0.04).
        if weather.wet > 0:
            # road, marking and sidewalk are materials 0..2
            flat = np.flatnonzero((mat <= Material.SIDEWALK) & (n[:, 2] > 0.9))
            cos_view = np.abs(facing[flat])
            f = (0.04 + 0.96 * (1 - cos_view) ** 5) * weather.wet  # numpy's powf: keep it here
            dry = F32(1 - 0.35 * weather.wet)
            shading.wet(colour, flat, hi, f, dry, reflected_sky)

        # Lamps glow (unshaded) in their signal's colour; distance fades to the weather's
        # fog/haze colour: fog + (colour - fog) * fade.
        fade = np.exp(dist[hi] * np.float32(-3.912 / weather.visibility_m))
        fog = np.asarray(weather.fog_rgb, np.float32) * gain
        lamps = self._dark if lamps is None else lamps
        rgb = shading.compose(sky, hi, colour, mat, tags, lamps, LAMP_RGB, fade, fog)
        img = cv2.convertScaleAbs(rgb, alpha=255.0).reshape(cfg.crop_px, cfg.crop_px, 3)
        if weather.saturation != 1.0:  # blend with the image's grey (luma), one OpenCV pass
            grey = cv2.cvtColor(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), cv2.COLOR_GRAY2RGB)
            img = cv2.addWeighted(img, weather.saturation, grey, 1.0 - weather.saturation, 0)
        if weather.streaks:
            img = _rain_streaks(img, weather.streaks, rng)
        return img

    def _skies(self, weather: CameraWeather) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel sky colour (N, 3) float32 0..1 (brightness applied) and the sky mirrored
        below the horizon (what wet ground reflects). The camera has no pitch or roll, so both
        depend only on the pixel: computed once per weather."""
        key = ("sky", weather)
        if key not in self._cache:
            dz = self.directions_ego[:, 2]
            self._cache[key] = (
                _sky(dz, weather) * np.float32(weather.brightness),
                _sky(-dz, weather) * np.float32(weather.brightness),
            )
        return self._cache[key]

    def _glass(self, weather: CameraWeather) -> np.ndarray:
        """Window colour (0..255): dark glass reflecting a little of the horizon."""
        return GLASS_RGB * 255 + 0.25 * np.asarray(weather.sky_horizon_rgb, np.float32)


def _shadow_candidates(points: np.ndarray, scene: FrameScene, sun: np.ndarray) -> np.ndarray:
    """Indices of the points (N, 3) that an agent's shadow can reach: those on a 1 m raster
    of capsules from each agent's bounding sphere away from the sun, as long as the agent's
    shadow (height / tan(sun elevation))."""
    if not len(scene.agents):
        return np.zeros(0, np.int64)
    c = scene.actor_centres_m[:, :2]
    r = scene.actor_radii_m + 1.0
    flat = math.hypot(float(sun[0]), float(sun[1]))
    away = -np.asarray(sun[:2], np.float64) / max(flat, 1e-6)
    length = 2 * scene.actor_centres_m[:, 2] * flat / max(float(sun[2]), 0.1)
    ends = c + away * length[:, None]
    lo = np.minimum(c, ends).min(0) - r.max() - 1
    hi = np.maximum(c, ends).max(0) + r.max() + 1
    shape = np.ceil(hi - lo).astype(int)[::-1]  # rows = y, cols = x
    grid = np.zeros(shape, np.uint8)
    starts = np.round(c - lo).astype(int).tolist()
    stops = np.round(ends - lo).astype(int).tolist()
    widths = (2 * r).astype(int) + 1
    for p0, p1, width in zip(starts, stops, widths.tolist()):
        cv2.line(grid, p0, p1, 1, width)
    lo32 = lo.astype(np.float32)
    return shading.in_grid(points, grid, lo32[0], lo32[1])


def _sky(dz: np.ndarray, weather: CameraWeather) -> np.ndarray:
    """(N,) z of view directions -> (N, 3) float32 sky colour (horizon below 0, zenith at 1)."""
    a = np.clip(dz, 0, 1).astype(np.float32) ** 0.6
    zen = np.asarray(weather.sky_zenith_rgb, np.float32) / 255
    hor = np.asarray(weather.sky_horizon_rgb, np.float32) / 255
    return hor + (zen - hor) * a[:, None]


def _rain_streaks(img: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Short light slanted streaks blended over the image (drawn from rng)."""
    h, w = img.shape[:2]
    x0 = rng.uniform(-20, w, n)
    y0 = rng.uniform(-20, h, n)
    length = rng.uniform(8, 26, n)
    angle = rng.normal(math.radians(75), math.radians(4), n)  # mostly falling, a little wind
    x1 = x0 + length * np.cos(angle)
    y1 = y0 + length * np.sin(angle)
    lines = np.stack([np.stack([x0, y0], 1), np.stack([x1, y1], 1)], 1).round().astype(np.int32)
    overlay = img.copy()
    cv2.polylines(overlay, list(lines), False, (205, 208, 215), 1, cv2.LINE_AA)
    return cv2.addWeighted(overlay, 0.45, img, 0.55, 0)
