"""The front camera: one ray per pixel of the stored 256x256 centre crop of a 400x300,
100-degree image (paper Sec. III-A), shaded per material with a sun, a sky and the weather.

Mounted as TransFuser's CARLA camera: 1.3 m ahead of the ego's box centre, 2.3 m above the
ground, looking straight ahead (no pitch). Only the crop is cast (65,536 rays); its horizontal
and vertical field of view is 2 * atan(128 / f) = 74.6 degrees with f = 200 / tan(50 deg).

Shading (per pixel, numpy): base colour of the triangle hit x (ambient + sun * max(0, n.s) *
shadow), with shadow rays towards the sun in sunny weather; building walls get a procedural
window grid; traffic-light lamps glow in the colour of the signal that governs the ego (the
heads facing it ahead, see `lit_slots`); rays that hit nothing within `range_m` see the sky.
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

from datagen.scene import FrameScene, Material, StaticScene
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

    @property
    def crop_half_fov_rad(self) -> float:
        """Half the horizontal field of view of the crop (along its diagonal, a bit more)."""
        half = self.crop_px / 2
        return math.atan(math.hypot(half, half) / self.focal_px)


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
        sky_zenith_rgb=(70, 125, 215), sky_horizon_rgb=(175, 205, 235), ambient=0.45, sun=0.85,
        saturation=1.1, brightness=1.0, visibility_m=3000.0, fog_rgb=(175, 205, 235),
    ),
    "cloudy": CameraWeather(
        sky_zenith_rgb=(150, 153, 160), sky_horizon_rgb=(200, 202, 206), ambient=0.85, sun=0.12,
        saturation=0.7, brightness=0.95, visibility_m=1500.0, fog_rgb=(195, 197, 201),
    ),
    "rainy": CameraWeather(
        sky_zenith_rgb=(72, 76, 84), sky_horizon_rgb=(118, 122, 130), ambient=0.62, sun=0.05,
        saturation=0.6, brightness=0.72, visibility_m=350.0, fog_rgb=(112, 116, 124), wet=1.0,
        streaks=260,
    ),
    "foggy": CameraWeather(
        sky_zenith_rgb=(178, 180, 184), sky_horizon_rgb=(178, 180, 184), ambient=0.8, sun=0.1,
        saturation=0.8, brightness=1.0, visibility_m=90.0, fog_rgb=(178, 180, 184),
    ),
}

LAMP_RGB = np.array([(255, 45, 30), (255, 190, 20), (40, 255, 110)], np.float32) / 255
_LIGHT_SLOT = {"red": 0, "yellow": 1, "green": 2}
GLASS_RGB = np.array([0.17, 0.21, 0.26], np.float32)
WINDOW_FLOOR_M, WINDOW_BAY_M = 3.2, 3.6  # window grid: one per floor and bay


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


def lit_slots(static: StaticScene, frame: FrameState) -> np.ndarray:
    """(H,) int8 lamp lit per signal head: 0 red, 1 yellow, 2 green, -1 dark.

    FrameState carries only the signal governing the ego, so the heads that show it are those
    facing the ego (within ~35 degrees) ahead of it up to its stop line + 25 m and within 15 m
    to the side; every other head is drawn dark."""
    n = len(static.head_xy_m)
    out = np.full(n, -1, np.int8)
    slot = _LIGHT_SLOT.get(frame.traffic_light)
    if slot is None or not n:
        return out
    pose = frame.ego.pose
    ego = pose.ego_from_world(static.head_xy_m)
    facing = np.cos(static.head_yaw_rad - pose.yaw_rad) < -0.82
    reach = (frame.light_distance_m or 0.0) + 25.0
    near = (ego[:, 0] > 0) & (ego[:, 0] < reach) & (np.abs(ego[:, 1]) < 15.0)
    out[facing & near] = slot
    return out


class Camera:
    """Renders the crop from fixed ray directions (computed once)."""

    def __init__(self, config: CameraConfig = CameraConfig()):
        self.config = config
        self.directions_ego = ray_directions(config)

    @property
    def n_rays(self) -> int:
        return len(self.directions_ego)

    def rays(self, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """World-frame (origins, directions), each (n_rays, 3) float32."""
        c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        d = self.directions_ego
        dirs = np.empty((len(d), 3), np.float32)
        dirs[:, 0] = c * d[:, 0] - s * d[:, 1]
        dirs[:, 1] = s * d[:, 0] + c * d[:, 1]
        dirs[:, 2] = d[:, 2]
        ox, oy = pose.world_from_ego(np.array([[self.config.mount_x_m, 0.0]]))[0]
        origin = np.array([ox, oy, self.config.mount_z_m], np.float32)
        return np.broadcast_to(origin, dirs.shape).copy(), dirs

    def render(
        self,
        scene: FrameScene,
        pose: Pose,
        weather: CameraWeather,
        rng: np.random.Generator,
        sun_dir: np.ndarray = np.array([0.5, 0.3, 0.81]),
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
        dist, prim = scene.cast(origins, dirs, cfg.range_m)
        hit = prim >= 0
        sky = _sky(dirs[:, 2], weather)  # (N, 3) float32 0..1
        rgb = sky.copy()
        hi = np.flatnonzero(hit)
        p = prim[hi]
        d = dirs[hi]
        t = dist[hi]
        n = scene.normals[p]
        facing = (n * d).sum(1)
        n = np.where((facing > 0)[:, None], -n, n)
        cos_view = np.abs(facing)
        albedo = scene.colour_rgb[p].astype(np.float32) * (1 / 255)
        mat = scene.material[p]
        pts = origins[hi] + d * t[:, None]

        # Procedural windows on building walls.
        wall = (mat == Material.BUILDING) & (np.abs(n[:, 2]) < 0.3)
        if wall.any():
            w = np.flatnonzero(wall)
            u = pts[w, 0] * -n[w, 1] + pts[w, 1] * n[w, 0]
            z = pts[w, 2]
            win = ((z % WINDOW_FLOOR_M) > 1.0) & ((z % WINDOW_FLOOR_M) < 2.4) & (z > 0.9)
            win &= ((u % WINDOW_BAY_M) > 0.8) & ((u % WINDOW_BAY_M) < 2.8)
            albedo[w[win]] = GLASS_RGB + 0.25 * np.asarray(weather.sky_horizon_rgb, np.float32) / 255

        # Light: ambient + sun (with shadows when sunny).
        sun = np.asarray(sun_dir, np.float32)
        lambert = np.maximum(n @ sun, 0)
        if cfg.shadows and weather.sun > 0.5:
            lit = np.flatnonzero(lambert > 0)
            o = pts[lit] + n[lit] * 0.03
            shadowed = scene.occluded(o.astype(np.float32), np.broadcast_to(sun, o.shape).copy(), 200.0)
            lambert[lit[shadowed]] = 0
        light = weather.ambient + weather.sun * lambert
        # Up-facing surfaces see the whole sky, walls half of it.
        light = light * (0.75 + 0.25 * np.abs(n[:, 2]))
        colour = albedo * light[:, None]

        # Wet surfaces: darker, and mirror the sky at grazing angles (Schlick, F0 = 0.04).
        if weather.wet > 0:
            flat = np.isin(mat, (Material.ROAD, Material.MARKING, Material.SIDEWALK)) & (n[:, 2] > 0.9)
            f = (0.04 + 0.96 * (1 - cos_view) ** 5) * weather.wet * flat
            colour *= (1 - 0.35 * weather.wet * flat)[:, None]
            refl = _sky(-d[:, 2], weather)
            colour = colour * (1 - f[:, None]) + refl * f[:, None]

        # Lamps glow (unshaded) in their signal's colour.
        is_lamp = mat == Material.LAMP
        if is_lamp.any():
            k = np.flatnonzero(is_lamp)
            tag = scene.tag[p[k]]
            head, slot = tag // 3, tag % 3
            on = np.zeros(len(k), bool) if lamps is None else lamps[head] == slot
            colour[k] = np.where(on[:, None], LAMP_RGB[slot], LAMP_RGB[slot] * 0.18)

        # Distance fades to the weather's fog/haze colour.
        fade = np.exp(-3.912 * t / weather.visibility_m)[:, None]
        fog = np.asarray(weather.fog_rgb, np.float32) / 255
        rgb[hi] = colour * fade + fog * (1 - fade)

        # Saturation and brightness.
        grey = rgb.mean(1, keepdims=True)
        rgb = (grey + (rgb - grey) * weather.saturation) * weather.brightness
        img = (np.clip(rgb, 0, 1) * 255).astype(np.uint8).reshape(cfg.crop_px, cfg.crop_px, 3)
        if weather.streaks:
            img = _rain_streaks(img, weather.streaks, rng)
        return img


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
