"""Embree 4 called directly: triangle scenes and the three ray queries the sensors make.

embreex (trimesh's binding) ships the Embree 4 library but wraps only its single-ray queries,
one Python call per batch, and it copies vertices into Embree through Python-level indexing
(~1.1 us a triangle: 16 ms for a 14k-triangle cell scene, 0.5 ms for a frame's agents). This
module loads the same library (the one in the embreex wheel), fills a geometry's buffers with
one numpy copy (2.3 ms and 0.1 ms for those scenes), and runs the ray loops as numba-compiled
code that calls Embree's C functions (`rtcIntersect1`, `rtcOccluded16`) directly.

Same answers as embreex, bit for bit: the scene is built the same way (one unshared vertex
triple per triangle, primitive id = row, the ROBUST scene flag) and rays start at tnear 0
with time 0, so Embree builds the same BVH and returns the same hits (tests/test_embree.py
checks that against embreex). Hits use single rays; shadow rays (`occluded`) use 16-ray packets:
they share the sun's direction, so the packets stay coherent and were ~3x faster than single
rays on the same scene, with the same answers. Embree's packets were not faster for the
sensors' primary rays here (0.92-0.99x: a robust scene and a CPU whose single-ray traversal is
already 8 or 16 wide), and packet hits may pick another of two triangles at the same distance,
so those stay single rays.

Units: metres; every array is float32 world coordinates (datagen/sensors/raycast.py).
"""

from __future__ import annotations

import ctypes
import glob
import os

import llvmlite.binding as llvm
import numba
import numpy as np
from numba import types

_RTC_GEOMETRY_TYPE_TRIANGLE = 0
_RTC_BUFFER_TYPE_INDEX, _RTC_BUFFER_TYPE_VERTEX = 0, 1
_RTC_FORMAT_UINT3, _RTC_FORMAT_FLOAT3 = 0x5003, 0x9003
_RTC_SCENE_FLAG_ROBUST = 1 << 2  # embreex's default (EmbreeScene(robust=True))
_INVALID = 0xFFFFFFFF  # RTC_INVALID_GEOMETRY_ID
_ALIGN = 64  # RTCRayHit16 and its valid mask are 64-byte aligned

# Fields of Embree 4's RTCRayHit (RTCRay then RTCHit), one float or uint each; in the 16-ray
# RTCRayHit16 each field is 16 consecutive lanes (structure of arrays).
_OX, _OY, _OZ, _TNEAR, _DX, _DY, _DZ, _TIME, _TFAR, _MASK, _ID, _FLAGS = range(12)
_PRIM, _GEOM, _INST = 17, 18, 19  # after Ng x, y, z (12-14), u (15), v (16)
_FIELDS = 24  # RTCRayHit is 80 bytes (20 fields); room for a build's extra instance fields
_PACKET = 16
NAME = "embree"  # datagen/sensors/raycast.py RAYCASTERS


def _library_path() -> str:
    import embreex

    libs = os.path.join(os.path.dirname(os.path.dirname(embreex.__file__)), "embreex.libs")
    found = sorted(glob.glob(os.path.join(libs, "libembree4*.so*")))
    if not found:  # a build of embreex linked against a system Embree 4
        found = ["libembree4.so.4"]
    return found[0]


def _load() -> ctypes.CDLL:
    path = _library_path()
    lib = ctypes.CDLL(path)
    llvm.load_library_permanently(path)  # lets the compiled loops resolve rtc* by name
    p = ctypes.c_void_p
    sigs = {
        "rtcNewDevice": (p, [ctypes.c_char_p]),
        "rtcNewScene": (p, [p]),
        "rtcSetSceneFlags": (None, [p, ctypes.c_int]),
        "rtcNewGeometry": (p, [p, ctypes.c_int]),
        "rtcSetNewGeometryBuffer": (
            p,
            [p, ctypes.c_int, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t, ctypes.c_size_t],
        ),
        "rtcCommitGeometry": (None, [p]),
        "rtcAttachGeometry": (ctypes.c_uint, [p, p]),
        "rtcReleaseGeometry": (None, [p]),
        "rtcCommitScene": (None, [p]),
        "rtcReleaseScene": (None, [p]),
        "rtcGetDeviceError": (ctypes.c_int, [p]),
    }
    for name, (res, args) in sigs.items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = res, args
    return lib


_lib = _load()
_device = _lib.rtcNewDevice(None)

# Pointers travel as int64 (the x86-64 and AArch64 ABIs pass both in the same registers).
_i64 = types.int64
_intersect1 = types.ExternalFunction("rtcIntersect1", types.void(_i64, _i64, _i64))
_occluded16 = types.ExternalFunction("rtcOccluded16", types.void(_i64, _i64, _i64, _i64))


class Scene:
    """A committed Embree scene of (N, 3, 3) float32 triangles; primitive id = row.

    `ptr` is the RTCScene handle the ray functions take; the scene is released when the
    object is collected."""

    def __init__(self, triangles_m: np.ndarray):
        tri = np.ascontiguousarray(triangles_m, np.float32).reshape(-1, 3, 3)
        n = len(tri)
        lib = _lib
        self.ptr = lib.rtcNewScene(_device)
        lib.rtcSetSceneFlags(self.ptr, _RTC_SCENE_FLAG_ROBUST)
        geom = lib.rtcNewGeometry(_device, _RTC_GEOMETRY_TYPE_TRIANGLE)
        if n:
            vb = lib.rtcSetNewGeometryBuffer(
                geom, _RTC_BUFFER_TYPE_VERTEX, 0, _RTC_FORMAT_FLOAT3, 16, 3 * n
            )
            ib = lib.rtcSetNewGeometryBuffer(
                geom, _RTC_BUFFER_TYPE_INDEX, 0, _RTC_FORMAT_UINT3, 12, n
            )
            if not vb or not ib:
                raise MemoryError(f"Embree could not allocate buffers for {n} triangles")
            vertices = np.ctypeslib.as_array((ctypes.c_float * (12 * n)).from_address(vb))
            vertices.reshape(3 * n, 4)[:, :3] = tri.reshape(3 * n, 3)  # x, y, z, padding
            index = np.ctypeslib.as_array((ctypes.c_uint32 * (3 * n)).from_address(ib))
            index[:] = np.arange(3 * n, dtype=np.uint32)
            lib.rtcCommitGeometry(geom)
            lib.rtcAttachGeometry(self.ptr, geom)
        lib.rtcReleaseGeometry(geom)
        lib.rtcCommitScene(self.ptr)
        error = lib.rtcGetDeviceError(_device)
        if error:
            raise RuntimeError(f"Embree error {error} building a scene of {n} triangles")

    def __del__(self):
        if getattr(self, "ptr", None) and _lib is not None:  # (None at interpreter exit)
            _lib.rtcReleaseScene(self.ptr)
            self.ptr = None


def _aligned_f32(n: int) -> np.ndarray:
    """(n,) float32 zeros starting on a 64-byte boundary."""
    raw = np.zeros(n + _ALIGN // 4, np.float32)
    start = (-raw.ctypes.data % _ALIGN) // 4
    return raw[start : start + n]


@numba.njit(cache=True, nogil=True, inline="always")
def _load_ray(ray, u, lane, lanes, origin, direction, tfar):
    """Write one ray into lane `lane` of an Embree ray structure of `lanes` lanes (1: RTCRay,
    16: RTCRay16; `u` is the same memory as uint32): origin, direction, tnear = time = 0,
    tfar, every mask bit, id and flags 0."""
    ray[_OX * lanes + lane] = origin[0]
    ray[_OY * lanes + lane] = origin[1]
    ray[_OZ * lanes + lane] = origin[2]
    ray[_TNEAR * lanes + lane] = 0.0
    ray[_DX * lanes + lane] = direction[0]
    ray[_DY * lanes + lane] = direction[1]
    ray[_DZ * lanes + lane] = direction[2]
    ray[_TIME * lanes + lane] = 0.0
    ray[_TFAR * lanes + lane] = tfar
    u[_MASK * lanes + lane] = _INVALID
    u[_ID * lanes + lane] = 0
    u[_FLAGS * lanes + lane] = 0


@numba.njit(cache=True, nogil=True)
def _first_hits(scene, origins, directions, tfar, prim, want_prim, rayhit):
    """rtcIntersect1 for each ray i (origins, directions: (N, 3) or (1, 3) shared); tfar (N,)
    is the ray's far bound in, its hit distance out (unchanged on a miss); prim[i] the hit
    primitive, -1 none (only written when want_prim)."""
    u = rayhit.view(np.uint32)
    address = rayhit.ctypes.data
    o_step = 1 if origins.shape[0] > 1 else 0
    d_step = 1 if directions.shape[0] > 1 else 0
    for i in range(tfar.shape[0]):
        _load_ray(rayhit, u, 0, 1, origins[i * o_step], directions[i * d_step], tfar[i])
        u[_PRIM] = _INVALID
        u[_GEOM] = _INVALID
        u[_INST] = _INVALID
        _intersect1(scene, address, 0)
        tfar[i] = rayhit[_TFAR]
        if want_prim:
            p = u[_PRIM]
            prim[i] = -1 if p == _INVALID else np.int32(p)


@numba.njit(cache=True, nogil=True)
def _any_hits(scene, origins, directions, tfar, hit, ray, valid):
    """rtcOccluded16 over packets of 16 consecutive rays: hit[i] = something lies on ray i
    within tfar[i]. origins, directions: (N, 3) or (1, 3) shared."""
    u = ray.view(np.uint32)
    address, valid_address = ray.ctypes.data, valid.ctypes.data
    o_step = 1 if origins.shape[0] > 1 else 0
    d_step = 1 if directions.shape[0] > 1 else 0
    n = tfar.shape[0]
    for start in range(0, n, _PACKET):
        k = min(_PACKET, n - start)
        for j in range(_PACKET):
            if j >= k:
                valid[j] = 0
                continue
            i = start + j
            _load_ray(ray, u, j, _PACKET, origins[i * o_step], directions[i * d_step], tfar[i])
            valid[j] = -1
        _occluded16(valid_address, scene, address, 0)
        for j in range(k):
            hit[start + j] = ray[_TFAR * _PACKET + j] < 0  # Embree sets tfar to -inf on a hit


def _inputs(origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray) -> tuple:
    if tfar.dtype != np.float32 or tfar.ndim != 1 or not tfar.flags.c_contiguous:
        raise ValueError(f"tfar must be contiguous float32 (N,), got {tfar.dtype} {tfar.shape}")
    n = len(tfar)
    return _rows("origins", origins, n), _rows("directions", directions, n)


def _rows(name: str, a: np.ndarray, n: int) -> np.ndarray:
    """`a` as the compiled loops take it: C-contiguous (N, 3), or (1, 3) for one row shared by
    all rays (also what a zero-stride view of one repeated row becomes; datagen/sensors/raycast.py)."""
    if a.dtype != np.float32 or a.ndim != 2 or a.shape[1] != 3 or a.shape[0] not in (1, n):
        raise ValueError(f"{name} must be float32 (N, 3) or (1, 3), got {a.dtype} {a.shape}")
    return a[:1] if a.strides[0] == 0 else np.ascontiguousarray(a)


def intersect(
    scene: Scene, origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray
) -> np.ndarray:
    """First hits: (N,) int32 primitive ids (-1: no hit within tfar). tfar (N,) float32 holds
    each ray's far bound and is overwritten with the hit distance where there is a hit."""
    origins, directions = _inputs(origins, directions, tfar)
    prim = np.empty(len(tfar), np.int32)
    _first_hits(scene.ptr, origins, directions, tfar, prim, True, _aligned_f32(_FIELDS))
    return prim


def distance(scene: Scene, origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray) -> None:
    """First-hit distances only: tfar (N,) float32, each ray's far bound, is overwritten with
    the hit distance where there is a hit (unchanged on a miss)."""
    origins, directions = _inputs(origins, directions, tfar)
    nothing = np.empty(0, np.int32)
    _first_hits(scene.ptr, origins, directions, tfar, nothing, False, _aligned_f32(_FIELDS))


def occluded(
    scene: Scene, origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray
) -> np.ndarray:
    """(N,) bool: does the scene hold anything along each ray within tfar (N,) float32 (m)."""
    origins, directions = _inputs(origins, directions, tfar)
    hit = np.empty(len(tfar), np.bool_)
    ray = _aligned_f32(_FIELDS * _PACKET)
    valid = _aligned_f32(_PACKET).view(np.int32)
    _any_hits(scene.ptr, origins, directions, tfar, hit, ray, valid)
    return hit
