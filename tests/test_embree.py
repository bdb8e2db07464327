"""datagen/sensors/embree.py against embreex, the binding it replaced: same scene, same rays, same
answers bit for bit (primitive ids, hit distances, occlusion)."""

import numpy as np
import pytest
from embreex import rtcore, rtcore_scene
from embreex.mesh_construction import TriangleMesh

from datagen.sensors import embree
from datagen.sensors.raycast import repeat_rows


def _town_like(rng: np.random.Generator) -> np.ndarray:
    """(N, 3, 3) float32: a ground of two big triangles, random boxes' faces and random small
    triangles above it, some coplanar with the ground (ties at the same distance)."""
    ground = np.array(
        [[[-50, -50, 0], [50, -50, 0], [50, 50, 0]], [[-50, -50, 0], [50, 50, 0], [-50, 50, 0]]]
    )
    centres = rng.uniform(-40, 40, (300, 1, 3)) * [1, 1, 0] + [0, 0, 0.0]
    small = (
        centres
        + rng.normal(0, 1.5, (300, 3, 3)) * [1, 1, 0]
        + rng.uniform(0, 4, (300, 1, 1)) * [0, 0, 1]
    )
    flat = centres[:40] + rng.normal(0, 2, (40, 3, 3)) * [1, 1, 0]  # lying on the ground
    return np.concatenate([ground, small, flat]).astype(np.float32)


def _embreex(tri: np.ndarray):
    scene = rtcore_scene.EmbreeScene(rtcore.EmbreeDevice())
    TriangleMesh(scene, tri)
    return scene


def _rays(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    d = rng.normal(size=(n, 3)).astype(np.float32)
    d[:, 2] = -np.abs(d[:, 2]) * 0.5
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return repeat_rows(np.array([1.0, -2.0, 1.7], np.float32), n), d


@pytest.mark.parametrize("n", [1, 15, 16, 17, 5003])
def test_queries_equal_embreex(n):
    rng = np.random.default_rng(n)
    tri = _town_like(rng)
    ours, theirs = embree.Scene(tri), _embreex(tri)
    origins, directions = _rays(rng, n)
    bound = rng.uniform(5, 80, n).astype(np.float32)

    expected = theirs.run(origins, directions, dists=bound.copy(), output=1)
    tfar = bound.copy()
    prim = embree.intersect(ours, origins, directions, tfar)
    assert (prim >= 0).any() and (prim < 0).any() or n < 20
    np.testing.assert_array_equal(prim, expected["primID"])
    np.testing.assert_array_equal(tfar, expected["tfar"])

    tfar = bound.copy()
    embree.distance(ours, origins, directions, tfar)
    np.testing.assert_array_equal(
        tfar, theirs.run(origins, directions, dists=bound.copy(), query="DISTANCE")
    )

    # Shadow rays: one shared direction (the sun), origins spread over the ground.
    points = np.concatenate([rng.uniform(-40, 40, (n, 2)), np.full((n, 1), 0.03)], 1).astype(
        np.float32
    )
    sun = np.array([[0.3, 0.2, 0.93]], np.float32)
    expected = theirs.run(points, sun, dists=np.full(n, 100, np.float32), query="OCCLUDED") >= 0
    got = embree.occluded(ours, points, sun, np.full(n, 100, np.float32))
    assert got.dtype == np.bool_
    np.testing.assert_array_equal(got, expected)


def test_an_empty_scene_hits_nothing_and_bad_rays_are_refused():
    scene = embree.Scene(np.zeros((0, 3, 3), np.float32))
    tfar = np.full(3, 10, np.float32)
    prim = embree.intersect(scene, np.zeros((1, 3), np.float32), np.eye(3, dtype=np.float32), tfar)
    assert (prim == -1).all() and (tfar == 10).all()
    with pytest.raises(ValueError, match="directions"):
        embree.intersect(scene, np.zeros((1, 3), np.float32), np.eye(3), tfar)  # float64
    with pytest.raises(ValueError, match="origins"):
        embree.occluded(scene, np.zeros((2, 3), np.float32), np.eye(3, dtype=np.float32), tfar)
