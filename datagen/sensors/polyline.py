"""Polylines on the ground plane and the triangles built along them: what the static scene
(datagen/sensors/scene.py) and its furniture (datagen/sensors/furniture.py) are made from.

Points are (n, 2) float64 world (x, y), metres; all functions are vectorised over points and
add z last; triangles are (k, 3, 3).
"""

from __future__ import annotations

import mapbox_earcut
import numpy as np


def resample(p: np.ndarray, max_seg_m: float) -> np.ndarray:
    """(n, 2) polyline -> the same polyline with points inserted so that no segment is longer
    than `max_seg_m`."""
    d = np.linalg.norm(np.diff(p, axis=0), axis=1)
    k = np.maximum(1, np.ceil(d / max_seg_m).astype(int))
    if (k == 1).all():
        return p
    out = [p[i] + (p[i + 1] - p[i]) * (np.arange(k[i])[:, None] / k[i]) for i in range(len(d))]
    return np.concatenate([*out, p[-1:]])


def dedupe(p: np.ndarray) -> np.ndarray:
    keep = np.ones(len(p), bool)
    keep[1:] = np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-3
    return p[keep]


def vertex_normals(p: np.ndarray) -> np.ndarray:
    """(n, 2) polyline -> (n, 2) left normals at the vertices, mitred (scaled so that offset
    lines stay parallel to the segments), mitre capped at 2x."""
    seg = np.diff(p, axis=0)
    seg /= np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-9)
    nseg = np.stack([-seg[:, 1], seg[:, 0]], axis=1)
    n = np.empty_like(p)
    n[0], n[-1] = nseg[0], nseg[-1]
    if len(p) > 2:
        m = nseg[:-1] + nseg[1:]
        m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-9)
        cos = np.clip((m * nseg[1:]).sum(1, keepdims=True), 0.5, 1.0)
        n[1:-1] = m / cos
    return n


def offset(p: np.ndarray, d_m: float) -> np.ndarray:
    """Polyline offset `d_m` to its left (negative: right)."""
    return p + vertex_normals(p) * d_m


def substring(p: np.ndarray, s0: float, s1: float) -> np.ndarray | None:
    """The part of polyline `p` between arc lengths s0 and s1, or None if empty."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    s0, s1 = max(s0, 0.0), min(s1, s[-1])
    if s1 - s0 < 1e-3:
        return None
    inner = (s > s0) & (s < s1)
    a = np.array([np.interp(s0, s, p[:, 0]), np.interp(s0, s, p[:, 1])])
    b = np.array([np.interp(s1, s, p[:, 0]), np.interp(s1, s, p[:, 1])])
    return np.concatenate([a[None], p[inner], b[None]])


def length(p: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def strip(p: np.ndarray, half_w_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Left and right boundary (each (n, 2)) of a strip of half width `half_w_m` along p."""
    n = vertex_normals(p) * half_w_m
    return p + n, p - n


def strip_triangles(left: np.ndarray, right: np.ndarray, z_m: float) -> np.ndarray:
    """Quad strip between two (n, 2) boundaries -> (2(n-1), 3, 3) triangles at height z_m."""
    L = np.concatenate([left, np.full((len(left), 1), z_m)], axis=1)
    R = np.concatenate([right, np.full((len(right), 1), z_m)], axis=1)
    t1 = np.stack([R[:-1], R[1:], L[1:]], axis=1)
    t2 = np.stack([R[:-1], L[1:], L[:-1]], axis=1)
    return np.concatenate([t1, t2])


def walls(ring: np.ndarray, z0_m: float, z1_m: float, closed: bool = True) -> np.ndarray:
    """Vertical quads along a (n, 2) polyline (closed: back to its start) from z0 to z1."""
    a = ring
    b = np.roll(ring, -1, axis=0) if closed else ring[1:]
    a = a if closed else ring[:-1]
    lo0 = np.concatenate([a, np.full((len(a), 1), z0_m)], 1)
    lo1 = np.concatenate([b, np.full((len(b), 1), z0_m)], 1)
    hi0 = np.concatenate([a, np.full((len(a), 1), z1_m)], 1)
    hi1 = np.concatenate([b, np.full((len(b), 1), z1_m)], 1)
    return np.concatenate([np.stack([lo0, lo1, hi1], 1), np.stack([lo0, hi1, hi0], 1)])


def polygon_triangles(ring: np.ndarray, z_m: float) -> np.ndarray:
    """Simple polygon (n, 2) -> (k, 3, 3) triangles at height z_m (earcut)."""
    ring = dedupe(np.asarray(ring, np.float64))
    if len(ring) > 3 and np.linalg.norm(ring[0] - ring[-1]) < 1e-3:
        ring = ring[:-1]
    if len(ring) < 3:
        return np.zeros((0, 3, 3))
    idx = mapbox_earcut.triangulate_float64(ring, np.array([len(ring)], np.uint32))
    v = np.concatenate([ring, np.full((len(ring), 1), z_m)], 1)
    return v[np.asarray(idx, np.int64).reshape(-1, 3)]
