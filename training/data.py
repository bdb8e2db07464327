"""Streaming reader of the v1 shards: frame index, episode split, decoded samples, DataLoader.

A shard directory is discovered with `pyarrow.dataset` (files whose names start with `_` or `.`
are skipped, as pandas does). Frames are numbered in the order `pd.read_parquet(DIR)` returns
them: shard files in sorted path order, rows in file order. `train show --frame N` uses this
number.

    index = scan("data/")                                  # one row per frame, cheap columns
    is_val = split(index, val_fraction=0.1)                # whole episodes only
    stream = FrameStream(index[~is_val], output_px=64, shuffle=True)
    loader = make_loader(stream, batch_size=8, num_workers=2)

Training streams row groups: each epoch shuffles the list of row groups (the same way on every
process), deals rows to DDP ranks in turn so every rank gets the same count within one, deals
row groups to DataLoader workers, and each worker mixes frames through a shuffle buffer of
encoded rows before decoding them (OpenCV, via `schemas.codecs`) and rendering the targets.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as ds
import pyarrow.parquet as pq
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

import schemas
from schemas import codecs
from training.errors import UserError
from training.targets import render_density

COLUMNS = (
    "episode_id",
    "frame",
    "town",
    "weather",
    "ego_speed",
    "target_point",
    "waypoints",
    "traffic_light",
    "stop_sign",
    "image",
    "lidar_bev",
    "bev_semantic",
    "boxes",
)
"""The shard columns a training sample is made of."""


def scan(path: str | Path) -> pd.DataFrame:
    """Frame index of a shard directory (or of one shard file), checking every file's schema.

    Returns:
        one row per frame, in frame-number order: path (str), row_group (int), row (int, within
        the row group), episode_id, town (str), frame (int, within the episode).
    Raises:
        UserError: no such path, no shards in it, a file that is not Parquet, or a shard of
            another schema version or with missing or mistyped columns.
    """
    p = Path(path)
    if not p.exists():
        raise UserError(f"{path}: no such file or directory")
    # With the schema given, discovery lists files without opening them; we check each below.
    files = ds.dataset(p, format="parquet", schema=schemas.SCHEMA).files
    if not files:
        raise UserError(f"{path}: no shards (*.parquet files) in this directory")
    parts = []
    for f in files:
        try:
            shard = pq.ParquetFile(f)
        except (pa.ArrowException, OSError) as e:
            raise UserError(f"{f}: not a Parquet shard ({e})") from None
        try:
            schemas.validate(shard.schema_arrow.empty_table(), where=f)
        except schemas.SchemaError as e:
            raise UserError(str(e)) from None
        keys = shard.read(columns=["episode_id", "town", "frame"]).to_pandas()
        sizes = [shard.metadata.row_group(i).num_rows for i in range(shard.num_row_groups)]
        keys.insert(0, "path", f)
        keys.insert(1, "row_group", np.repeat(np.arange(len(sizes)), sizes))
        keys.insert(2, "row", np.concatenate([np.arange(n) for n in sizes] or [[]]).astype(int))
        parts.append(keys)
    index = pd.concat(parts, ignore_index=True)
    if index.empty:
        raise UserError(f"{path}: the shards hold no frames")
    return index


def split(
    index: pd.DataFrame, val_fraction: float = 0.1, val_towns: tuple[str, ...] = (), seed: int = 0
) -> np.ndarray:
    """Hold out whole episodes: a (N,) bool array, True for frames of validation episodes.

    With `val_towns`, every episode of those towns is held out; otherwise a seeded random
    `val_fraction` of the episodes (at least one, and never all, when there are two or more).
    """
    episodes = np.array(sorted(index.episode_id.unique()))
    if val_towns:
        unknown = sorted(set(val_towns) - set(index.town))
        if unknown:
            known = ", ".join(sorted(index.town.unique()))
            raise UserError(f"--val-towns: no town {', '.join(unknown)} in the shards ({known})")
        return index.town.isin(val_towns).to_numpy()
    n_val = 0
    if val_fraction > 0 and len(episodes) > 1:
        n_val = min(max(1, round(val_fraction * len(episodes))), len(episodes) - 1)
    val = np.random.default_rng(seed).permutation(episodes)[:n_val]
    return index.episode_id.isin(val).to_numpy()


def _row_arrays(table: pa.Table) -> dict:
    """Columns of a (non-empty) row group as numpy arrays or Python lists; boxes as flat arrays
    of their fields with each row's start offset."""
    table = table.combine_chunks()
    n = table.num_rows
    col = {name: table.column(name).chunk(0) for name in COLUMNS}
    out = {name: col[name].to_pylist() for name in ("episode_id", "weather", "traffic_light")}
    out.update({name: col[name].to_pylist() for name in ("image", "lidar_bev", "bev_semantic")})
    out["frame"] = col["frame"].to_numpy()
    out["ego_speed"] = col["ego_speed"].to_numpy()
    out["stop_sign"] = col["stop_sign"].to_numpy(zero_copy_only=False)
    out["target_point"] = col["target_point"].flatten().to_numpy().reshape(n, 2)
    out["waypoints"] = col["waypoints"].flatten().to_numpy().reshape(n, 4, 2)
    lengths = col["boxes"].value_lengths().to_numpy(zero_copy_only=False)
    out["box_start"] = np.concatenate([[0], np.cumsum(lengths)])
    flat = col["boxes"].flatten()
    out["boxes"] = {
        f: pc.struct_field(flat, f).to_numpy(zero_copy_only=False)
        for f in ("t", "x", "y", "yaw", "length", "width")
    }
    return out


def model_inputs(image: bytes, lidar_bev: bytes) -> tuple[np.ndarray, np.ndarray]:
    """The camera and LiDAR the model reads, from their shard encodings (schemas.codecs):
    image (3, 256, 256) uint8 RGB and lidar (4, 256, 256) uint8 counts ch0..ch3. Closed-loop
    driving (drive/) feeds the model through this too, so it sees what it was trained on."""
    return (
        np.ascontiguousarray(codecs.decode_image(image).transpose(2, 0, 1)),
        np.ascontiguousarray(codecs.decode_lidar_bev(lidar_bev).transpose(2, 0, 1)),
    )


def sensor_config(index: pd.DataFrame) -> dict | None:
    """The sensor configuration the frames of `index` were recorded with (the shards'
    iidsu.config_json), None if they carry none; UserError if the shards disagree."""
    configs = {
        (pq.read_schema(f).metadata or {}).get(schemas.META_CONFIG_JSON.encode())
        for f in index.path.unique()
    }
    if len(configs) > 1:
        raise UserError("the shards were recorded with different sensor configurations")
    (config,) = configs
    return json.loads(config) if config else None


def _sample(rows: dict, i: int, output_px: int) -> dict:
    """Decode row `i` of `_row_arrays` output into one training sample (numpy arrays).

    Inputs: image (3, 256, 256) uint8 RGB; lidar (4, 256, 256) uint8 counts ch0..ch3; speed ()
    float32 m/s; target_point (2,) float32 m ego. Targets: waypoints (4, 2) float32 m ego;
    heatmap, centre_* (training/targets.py); bev (R, R) uint8 class ids; traffic (2,) float32
    (red light, stop sign); weather () int64 index into schemas.WEATHERS. Keys: episode_id, frame.
    """
    import cv2

    a, b = rows["box_start"][i], rows["box_start"][i + 1]
    density = render_density({k: v[a:b] for k, v in rows["boxes"].items()}, output_px)
    bev = codecs.decode_bev_semantic(rows["bev_semantic"][i])
    if bev.shape[0] != output_px:  # nearest: class ids must not blend (thins lane markings)
        bev = cv2.resize(bev, (output_px, output_px), interpolation=cv2.INTER_NEAREST)
    image, lidar = model_inputs(rows["image"][i], rows["lidar_bev"][i])
    return {
        "image": image,
        "lidar": lidar,
        "speed": np.float32(rows["ego_speed"][i]),
        "target_point": rows["target_point"][i].astype(np.float32),
        "waypoints": rows["waypoints"][i].astype(np.float32),
        **density,
        "bev": bev,
        "traffic": np.array(
            [rows["traffic_light"][i] == "red", bool(rows["stop_sign"][i])], np.float32
        ),
        "weather": np.int64(schemas.WEATHERS.index(rows["weather"][i])),
        "episode_id": rows["episode_id"][i],
        "frame": int(rows["frame"][i]),
    }


def read_frames(index: pd.DataFrame, output_px: int) -> list[dict]:
    """Decoded samples for every frame of `index` (a slice of `scan`'s result), in its order."""
    samples = {}
    for (path, rg), group in index.groupby(["path", "row_group"], sort=False):
        table = pq.ParquetFile(path).read_row_group(rg, columns=list(COLUMNS))
        rows = _row_arrays(table.take(group.row.to_numpy()))
        for k, position in enumerate(group.index):
            samples[position] = _sample(rows, k, output_px)
    return [samples[position] for position in index.index]


@dataclass(frozen=True)
class _Unit:
    """One row group and the rows of it that belong to the stream's frames."""

    path: str
    row_group: int
    rows: np.ndarray  # (n,) int, positions within the row group


class FrameStream(IterableDataset):
    """Decoded samples of the frames in `index`, streamed row group by row group.

    Args:
        index: the frames to stream (a slice of `scan`'s result).
        output_px: R, the side of the dense targets.
        shuffle: shuffle row groups per epoch and frames through a buffer (training); without
            it, frames come in index order per worker (evaluation).
        seed: with the epoch (`set_epoch`), fixes every random choice, so a resumed run sees
            the same data order as an uninterrupted one.
        buffer_size: encoded frames a worker holds for shuffling.
        rank, world: this process's share under DDP.
    """

    def __init__(
        self,
        index: pd.DataFrame,
        output_px: int,
        shuffle: bool = False,
        seed: int = 0,
        buffer_size: int = 256,
        rank: int = 0,
        world: int = 1,
    ):
        super().__init__()
        self.output_px, self.shuffle, self.seed = output_px, shuffle, seed
        self.buffer_size, self.rank, self.world = buffer_size, rank, world
        self.epoch = 0
        self.n_frames = len(index)
        self.units = [
            _Unit(path, int(rg), group.row.to_numpy())
            for (path, rg), group in index.groupby(["path", "row_group"], sort=False)
        ]

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def frames_per_rank(self) -> int:
        """Frames every rank gets at least (ranks differ by at most one)."""
        return self.n_frames // self.world

    def _my_units(self) -> list[_Unit]:
        """This rank's and this worker's rows for the current epoch."""
        order = np.arange(len(self.units))
        if self.shuffle:
            order = np.random.default_rng([self.seed, self.epoch]).permutation(order)
        mine, offset = [], 0
        for u in order:  # deal rows to ranks in turn over the epoch's order
            rows = self.units[u].rows
            keep = (offset + np.arange(len(rows))) % self.world == self.rank
            offset += len(rows)
            mine.append(_Unit(self.units[u].path, self.units[u].row_group, rows[keep]))
        info = get_worker_info()
        worker, n_workers = (info.id, info.num_workers) if info else (0, 1)
        return mine[worker::n_workers]

    def __iter__(self):
        info = get_worker_info()
        worker = info.id if info else 0
        rng = np.random.default_rng([self.seed, self.epoch, self.rank, worker, 1])
        buffer: list[tuple[dict, int]] = []  # (row arrays of a row group, row)
        for unit in self._my_units():
            if not len(unit.rows):
                continue
            table = pq.ParquetFile(unit.path).read_row_group(unit.row_group, columns=list(COLUMNS))
            rows = _row_arrays(table.take(unit.rows))
            for i in range(len(unit.rows)):
                if not self.shuffle:
                    yield _sample(rows, i, self.output_px)
                    continue
                buffer.append((rows, i))
                if len(buffer) >= self.buffer_size:
                    j = rng.integers(len(buffer))
                    buffer[j], buffer[-1] = buffer[-1], buffer[j]
                    yield _sample(*buffer.pop(), self.output_px)
        for j in rng.permutation(len(buffer)):
            yield _sample(*buffer[j], self.output_px)


def make_loader(stream: FrameStream, batch_size: int, num_workers: int) -> DataLoader:
    """Batches of `stream`'s samples; tensors keep their dtypes (uint8 images travel as such)."""
    return DataLoader(
        stream,
        batch_size=batch_size,
        num_workers=num_workers,
        pin_memory=torch.cuda.is_available(),
        prefetch_factor=4 if num_workers else None,
    )
