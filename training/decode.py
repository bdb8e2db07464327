"""Decoding a shard row's encoded inputs into what the model reads (schemas.codecs): the
camera, the LiDAR (or the single-frame ablation's) and the BEV target at the model's R. Used by
the loader (training/data.py), the decoded-frame cache (training/cache.py) and drive's policy."""

from __future__ import annotations

import cv2
import numpy as np
import pyarrow as pa

import schemas
from schemas import codecs

GROUND_T = "lidar_ground_t"
"""Schema 1.1's column of the current sweep's at-ground hits (256x256 uint8 1-channel PNG, the
same BEV grid as `lidar_bev`): what the single-frame ablation needs instead of ch0, which sums
three sweeps. Read only for that ablation."""
BLOBS = ("image", "lidar_bev", "bev_semantic")
"""The encoded columns a sample decodes (`decode_inputs`); what the cache (training/cache.py)
holds decoded, so a cached shard is read without them."""
DRIVABLE, LANE = schemas.BEV_CLASSES.index("drivable"), schemas.BEV_CLASSES.index("lane_marking")


def downsample_bev(classes: np.ndarray, output_px: int) -> np.ndarray:
    """A (256, 256) uint8 BEV class map -> (R, R), R dividing 256, keeping thin classes.

    Each output pixel covers a k x k block (k = 256 / R). It is lane_marking if any pixel of the
    block is (markings are 1-2 px wide at 8 px/m: nearest-neighbour sampling at R = 64 keeps one
    pixel in 16 and loses most of them), else drivable if at least half the block is road
    surface (drivable or marking), else other.
    """
    k = classes.shape[0] // output_px
    if k == 1:
        return classes
    if k * output_px != classes.shape[0]:
        raise ValueError(f"R = {output_px} does not divide the {classes.shape[0]} px BEV map")
    # OpenCV's area resampling at an integer factor is the block mean: ~0.05 ms on uint8 0/255
    # masks, where one marking pixel of a block still averages to >= 1 while k * k <= 255.
    size = (output_px, output_px)
    if k * k <= 255:
        lane = cv2.resize(
            cv2.compare(classes, LANE, cv2.CMP_EQ), size, interpolation=cv2.INTER_AREA
        )
        road = cv2.resize(
            cv2.compare(classes, DRIVABLE, cv2.CMP_GE), size, interpolation=cv2.INTER_AREA
        )
        lane, road = lane > 0, road >= 128
    else:
        masks = np.stack([classes == LANE, classes >= DRIVABLE], axis=2).astype(np.float32)
        lane, road = cv2.resize(masks, size, interpolation=cv2.INTER_AREA).transpose(2, 0, 1)
        lane, road = lane > 0, road >= 0.5
    out = road.astype(np.uint8)  # DRIVABLE is 1
    out[lane] = LANE
    return out


def model_inputs(
    image: bytes, lidar_bev: bytes, lidar_ground_t: bytes | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The camera and LiDAR the model reads, from their shard encodings (schemas.codecs):
    image (3, 256, 256) uint8 RGB and lidar (4, 256, 256) uint8 counts ch0..ch3, or, given
    `lidar_ground_t` (the single-frame ablation), (2, 256, 256): the current sweep's at-ground
    and above-ground hits. Closed-loop driving (drive/) feeds the model through this too, so it
    sees what it was trained on."""
    lidar = codecs.decode_lidar_bev(lidar_bev).transpose(2, 0, 1)
    if lidar_ground_t is not None:
        lidar = np.stack([codecs.decode_lidar_ground(lidar_ground_t), lidar[1]])
    return (
        np.ascontiguousarray(codecs.decode_image(image).transpose(2, 0, 1)),
        np.ascontiguousarray(lidar),
    )


def blob_columns(single_frame_lidar: bool = False) -> list[str]:
    """The encoded columns `decode_inputs` reads."""
    return [*BLOBS, GROUND_T] if single_frame_lidar else list(BLOBS)


def blob_arrays(table: pa.Table | pa.RecordBatch) -> dict[str, list[bytes]]:
    """The encoded columns of `table` (those of BLOBS and GROUND_T it has) as lists of bytes."""
    names = set(table.schema.names)
    return {n: table.column(n).to_pylist() for n in (*BLOBS, GROUND_T) if n in names}


def decode_inputs(rows: dict, i: int, output_px: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row `i` of `blob_arrays` output decoded: the image and LiDAR the model reads
    (`model_inputs`; the single-frame ablation's LiDAR when the rows carry `lidar_ground_t`)
    and the BEV target (R, R) uint8 class ids (`downsample_bev`). What the cache stores."""
    ground_t = rows[GROUND_T][i] if GROUND_T in rows else None
    image, lidar = model_inputs(rows["image"][i], rows["lidar_bev"][i], ground_t)
    bev = downsample_bev(codecs.decode_bev_semantic(rows["bev_semantic"][i]), output_px)
    return image, lidar, bev
