"""Small synthetic shards that satisfy the contract, for tests (and bench/train.py) that need no
simulator: `synthetic_table` (one episode's rows), `write_shards` (a dataset laid out on disk as
`datagen build` writes it)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import schemas
from schemas import WEATHERS, codecs


def synthetic_table(
    n_frames: int = 4,
    episode_id: str = "synth-0-0",
    town: str = "synth",
    weather: str = "sunny",
    seed: int = 0,
    noise: bool = True,
) -> pa.Table:
    """`n_frames` consecutive frames of one episode with random but valid content; `noise=False`
    makes the images flat (a few ms a frame instead of ~70: for tests of hundreds of episodes)."""
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n_frames):
        if noise:
            image = rng.integers(0, 255, (256, 256, 3), dtype=np.uint8)
            bev = rng.integers(0, 4, (256, 256, 4), dtype=np.uint8)
            sem = rng.integers(0, 3, (256, 256), dtype=np.uint8)
        else:
            image = np.full((256, 256, 3), (seed + i) % 256, dtype=np.uint8)
            bev = np.full((256, 256, 4), (seed + i) % 4, dtype=np.uint8)
            sem = np.full((256, 256), (seed + i) % 3, dtype=np.uint8)
        boxes = [
            {
                "track_id": f"veh{j}",
                "cls": "vehicle",
                "t": t,
                "x": float(5 + 3 * j + t),
                "y": float(j - 1),
                "yaw": 0.1 * j,
                "length": 4.5,
                "width": 1.8,
                "speed": 5.0,
                "lidar_points": 40 if t == 0 else 0,
            }
            for j in range(2)
            for t in range(3)
        ]
        rows.append(
            {
                "episode_id": episode_id,
                "frame": i,
                "time_s": 10.0 + 0.5 * i,
                "town": town,
                "weather": weather,
                "behaviour": "cautious" if weather in ("rainy", "foggy") else "normal",
                "ego_x": 100.0 + i,
                "ego_y": 50.0,
                "ego_yaw": 0.0,
                "ego_speed": 2.0,
                "rig_shift_m": 0.0,
                "rig_yaw_rad": 0.0,
                "command": "follow",
                "target_point": [20.0, 0.0],
                "waypoints": [1.0, 0.0, 2.0, 0.0, 3.0, 0.0, 4.0, 0.0],
                "traffic_light": "red" if i % 2 else "none",
                "light_distance_m": 12.0 if i % 2 else None,
                "stop_sign": False,
                "stop_distance_m": None,
                "expert_reason": "none",
                "image": codecs.encode_image(image),
                "lidar_bev": codecs.encode_lidar_bev(bev),
                "lidar_ground_t": codecs.encode_lidar_ground(bev[..., 0]),
                "bev_semantic": codecs.encode_bev_semantic(sem),
                "boxes": boxes,
            }
        )
    meta = schemas.file_metadata(
        generator_version="test", config={}, network_sha256="0" * 64, seed=seed
    )
    return pa.Table.from_pylist(rows, schema=schemas.schema(meta))


def write_shards(
    root: Path, towns=("alpha", "beta"), episodes: int = 2, frames: int = 4, row_group: int = 3
) -> Path:
    """Shards as `datagen build` lays them out: <root>/<town>/<episode_id>.parquet, with small
    row groups so that streaming crosses row-group boundaries."""
    k = 0
    for town in towns:
        (root / town).mkdir(parents=True, exist_ok=True)
        for e in range(episodes):
            episode = f"{town}-{k}-{e}"
            table = synthetic_table(frames, episode, town, WEATHERS[k % 4], seed=k)
            pq.write_table(table, root / town / f"{episode}.parquet", row_group_size=row_group)
            k += 1
    (root / "_manifest.json").write_text("{}")  # not data: skipped
    return root
