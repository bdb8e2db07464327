"""The camera's per-pixel shading passes, compiled with numba (datagen/sensors/camera.py `render` calls
them; read that docstring for what the shading is).

Why compiled: in numpy the shading was a chain of ~30 whole-array passes with a gather and a
scatter per attribute, ~8 ms a frame on top of the ~12 ms of Embree rays (bench/frame.py, issue
12). One loop per pass does the same arithmetic in one sweep over the pixels.

Same values as the numpy chain they replace, bit for bit (tests/test_identical.py pins it):
every operation is float32 in numpy's order, with no fused multiply-add (numba does not contract
without fastmath), and every constant is a float32, as numpy 2 casts a Python float next to a
float32 array (NEP 50). The two transcendental steps that numpy computes with its own SIMD
routines, the fog's exp and the wet road's power, stay in numpy (camera.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from datagen.sensors.mesh import Material

F32 = np.float32
_BUILDING = int(Material.BUILDING)
_LAMP = int(Material.LAMP)
_WALL_MAX_NZ = F32(0.3)  # a wall: |normal z| below this
_FLOOR_M, _BAY_M = F32(3.2), F32(3.6)  # procedural window grid: one per floor and bay
_WIN_Z0, _WIN_Z1, _WIN_MIN_Z = F32(1.0), F32(2.4), F32(0.9)  # window rows within a floor, m
_WIN_U0, _WIN_U1 = F32(0.8), F32(2.8)  # window columns within a bay, m
_OFFSET_M = F32(0.03)  # shadow rays start this far off the surface


@numba.njit(cache=True, nogil=True)
def surface(
    hit, prim, dist, dirs, origin, n_static, s_normal, s_colour, s_material, s_tag, a_normal,
    a_colour, a_material, glass, sun,
):  # fmt: skip
    """Surface of each hit pixel (hit: (M,) pixel indices, ascending) as the camera sees it.

    Args:
        prim, dist: (N,) int32 primitive and float32 distance of every pixel's ray (m).
        dirs: (N, 3) float32 world-frame ray directions; origin: (3,) float32 camera, world.
        n_static: primitives below it are static (s_*), the rest actors (a_*, id - n_static).
        s_normal, s_colour, s_material, s_tag / a_*: per-primitive normal (3,) float32, RGB
            uint8, material uint8, lamp tag int32 (actors have none: -1).
        glass: (3,) float32 window colour 0..255; sun: (3,) float32 unit vector to the sun.
    Returns:
        normal (M, 3) float32 (turned towards the camera), albedo (M, 3) float32 0..255
        (windows painted), material (M,) uint8, tag (M,) int32, facing (M,) float32 (normal
        before turning . ray), point (M, 3) float32 world m, lambert (M,) float32 max(n . sun, 0).
    """
    m = len(hit)
    normal = np.empty((m, 3), np.float32)
    albedo = np.empty((m, 3), np.float32)
    material = np.empty(m, np.uint8)
    tag = np.empty(m, np.int32)
    facing = np.empty(m, np.float32)
    point = np.empty((m, 3), np.float32)
    lambert = np.empty(m, np.float32)
    for k in range(m):
        i = hit[k]
        p = prim[i]
        if p < n_static:
            nx, ny, nz = s_normal[p, 0], s_normal[p, 1], s_normal[p, 2]
            r, g, b = s_colour[p, 0], s_colour[p, 1], s_colour[p, 2]
            mat, tg = s_material[p], s_tag[p]
        else:
            q = p - n_static
            nx, ny, nz = a_normal[q, 0], a_normal[q, 1], a_normal[q, 2]
            r, g, b = a_colour[q, 0], a_colour[q, 1], a_colour[q, 2]
            mat, tg = a_material[q], -1
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        f = nx * dx + ny * dy + nz * dz
        sign = F32(-1.0) if f > 0 else F32(1.0)
        nx, ny, nz = nx * sign, ny * sign, nz * sign
        t = dist[i]
        px, py, pz = origin[0] + dx * t, origin[1] + dy * t, origin[2] + dz * t
        ar, ag, ab = F32(r), F32(g), F32(b)
        if mat == _BUILDING and abs(nz) < _WALL_MAX_NZ:
            u = px * -ny + py * nx
            zf, uf = pz % _FLOOR_M, u % _BAY_M
            if zf > _WIN_Z0 and zf < _WIN_Z1 and pz > _WIN_MIN_Z and uf > _WIN_U0 and uf < _WIN_U1:
                ar, ag, ab = glass[0], glass[1], glass[2]
        normal[k, 0], normal[k, 1], normal[k, 2] = nx, ny, nz
        albedo[k, 0], albedo[k, 1], albedo[k, 2] = ar, ag, ab
        material[k], tag[k], facing[k] = mat, tg, f
        point[k, 0], point[k, 1], point[k, 2] = px, py, pz
        lambert[k] = max(nx * sun[0] + ny * sun[1] + nz * sun[2], F32(0.0))
    return normal, albedo, material, tag, facing, point, lambert


@numba.njit(cache=True, nogil=True)
def shadow_origins(point, normal, lit):
    """(L, 3) float32 start points of the shadow rays of pixels `lit`: each surface point
    moved _OFFSET_M along its (camera-facing) normal."""
    out = np.empty((len(lit), 3), np.float32)
    for k in range(len(lit)):
        j = lit[k]
        for c in range(3):
            out[k, c] = point[j, c] + normal[j, c] * _OFFSET_M
    return out


@numba.njit(cache=True, nogil=True)
def light(albedo, normal, lambert, ambient, sun, gain):
    """(M, 3) float32 lit colour 0..1: albedo x (ambient + sun x lambert) x (0.75 + 0.25 |n_z|)
    x gain (brightness / 255); walls see half the sky. ambient, sun, gain: float32."""
    m = len(albedo)
    colour = np.empty((m, 3), np.float32)
    for k in range(m):
        lt = (ambient + sun * lambert[k]) * (F32(0.75) + F32(0.25) * abs(normal[k, 2]))
        lt = lt * gain
        for c in range(3):
            colour[k, c] = albedo[k, c] * lt
    return colour


@numba.njit(cache=True, nogil=True)
def wet(colour, flat, hit, fresnel, dry, reflected_sky):
    """Wet ground, in place on colour (M, 3) float32: for each of the pixels `flat` (indices
    into the hit pixels), colour x dry x (1 - fresnel) + the mirrored sky x fresnel, where
    fresnel (len(flat),) float32 is Schlick's reflectance x wetness, dry (float32) the darkening,
    and reflected_sky (N, 3) float32 is per pixel (hit[k] is hit pixel k's pixel)."""
    for j in range(len(flat)):
        k = flat[j]
        f = fresnel[j]
        for c in range(3):
            colour[k, c] = colour[k, c] * dry * (F32(1.0) - f) + reflected_sky[hit[k], c] * f


@numba.njit(cache=True, nogil=True)
def compose(sky, hit, colour, material, tag, lamps, lamp_rgb, fade, fog):
    """The (N, 3) float32 image 0..1: the sky where nothing is hit; elsewhere lamps glow in
    their colour (full when lit: lamps[head] == slot, else 0.18), then every colour fades to
    `fog` by `fade` (M,), fog + (colour - fog) * fade.

    Args:
        lamps: (H,) int8 lit slot per signal head (camera.lit_slots), -1 dark; heads beyond
            H are dark.
        lamp_rgb: (3, 3) float32 lamp colours 0..1 (red, yellow, green).
    """
    rgb = sky.copy()
    dim = F32(0.18)
    for k in range(len(hit)):
        i = hit[k]
        if material[k] == _LAMP:
            head, slot = tag[k] // 3, tag[k] % 3
            on = head < len(lamps) and lamps[head] == slot
            for c in range(3):
                colour[k, c] = lamp_rgb[slot, c] * (F32(1.0) if on else dim)
        for c in range(3):
            rgb[i, c] = (colour[k, c] - fog[c]) * fade[k] + fog[c]
    return rgb


@numba.njit(cache=True, nogil=True)
def in_grid(points, grid, lo_x, lo_y):
    """Indices of the points (N, 3+) whose cell floor(p_xy - lo) on the uint8 `grid` (rows y,
    cols x, 1 m cells) is set; lo_x, lo_y float32 m."""
    out = np.empty(len(points), np.int64)
    n = 0
    h, w = grid.shape
    for k in range(len(points)):
        i = math.floor(points[k, 0] - lo_x)
        j = math.floor(points[k, 1] - lo_y)
        if 0 <= i < w and 0 <= j < h and grid[j, i] > 0:
            out[n] = k
            n += 1
    return out[:n]
