"""Streaming reader of the v1 shards: frame index, episode split, decoded samples, DataLoader.

A shard directory is discovered with `schemas.dataset.shard_files` (`*.parquet` at any depth,
skipping names that start with `_` or `.`, as pandas does, and non-Parquet files such as
`data/README.md`). Frames are numbered in the order `pd.read_parquet(DIR)` returns them for a
directory of shards: shard files in sorted path order, rows in file order. `train show --frame N`
uses this number.

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
import pyarrow.parquet as pq
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

import schemas
from schemas.dataset import DatasetError, shard_files
from training.augment import zoom_out, zoom_scale
from training.cache import ARRAYS as CACHED_ARRAYS
from training.cache import CachedShard, open_entry
from training.decode import (  # the decoding a sample and the cache share
    BLOBS,
    GROUND_T,
    blob_arrays,
    decode_inputs,
)
from training.errors import UserError
from training.targets import MIN_LIDAR_POINTS, render_density, visible_boxes

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
    `path` may name several, comma-separated ("data,runs/dagger1": a build and `drive
    collect`'s on-policy frames read as one dataset; their episode ids must differ).

    Returns:
        one row per frame, in frame-number order: path (str), row_group (int), row (int, within
        the row group), episode_id, town (str), frame (int, within the episode).
    Raises:
        UserError: no such path, no shards in it, a file that is not Parquet, or a shard of
            another schema version or with missing or mistyped columns.
    """
    several = "," in str(path) and not Path(path).exists()
    files = []
    for one in str(path).split(",") if several else [path]:
        try:
            found = [str(f) for f in shard_files(one)]
        except DatasetError as e:
            raise UserError(str(e)) from None
        if not found:
            raise UserError(f"{one}: no shards (*.parquet files) in this directory")
        files += found
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
    twice = index.duplicated(["episode_id", "frame"])
    if twice.any():
        raise UserError(
            f"{path}: episode {index.episode_id[twice].iloc[0]} is in two shards (the same "
            "dataset twice, or datasets built with the same seed?)"
        )
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
        if set(index.town) <= set(val_towns):
            raise UserError(
                f"--val-towns {','.join(val_towns)} holds out every town of the shards: none "
                "left to train on"
            )
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
    col = {name: table.column(name).chunk(0) for name in table.column_names}
    out = {name: col[name].to_pylist() for name in ("episode_id", "weather", "traffic_light")}
    out.update(blob_arrays(table))
    out["frame"] = col["frame"].to_numpy()
    out["ego_speed"] = col["ego_speed"].to_numpy()
    out["stop_sign"] = col["stop_sign"].to_numpy(zero_copy_only=False)
    out["target_point"] = col["target_point"].flatten().to_numpy().reshape(n, 2)
    out["waypoints"] = col["waypoints"].flatten().to_numpy().reshape(n, 4, 2)
    lengths = col["boxes"].value_lengths().to_numpy(zero_copy_only=False)
    out["box_start"] = np.concatenate([[0], np.cumsum(lengths)])
    flat = col["boxes"].flatten()
    fields = ("track_id", "t", "x", "y", "yaw", "length", "width", "lidar_points")
    out["boxes"] = {f: pc.struct_field(flat, f).to_numpy(zero_copy_only=False) for f in fields}
    return out


def sensor_config(index: pd.DataFrame) -> dict | None:
    """The sensor configuration the frames of `index` were recorded with (the shards'
    iidsu.config_json without what shapes only the labels, schemas.sensor_part), None if they
    carry none; UserError if the shards disagree."""
    raw = {
        (pq.read_schema(f).metadata or {}).get(schemas.META_CONFIG_JSON.encode())
        for f in index.path.unique()
    }
    configs = {
        None if c is None else json.dumps(schemas.sensor_part(json.loads(c)), sort_keys=True)
        for c in raw
    }
    if len(configs) > 1:
        raise UserError("the shards were recorded with different sensor configurations")
    (config,) = configs
    return json.loads(config) if config else None


def _sample(
    rows: dict, i: int, output_px: int, min_lidar_points: int = MIN_LIDAR_POINTS, zoom: float = 1.0
) -> dict:
    """Decode row `i` of `_row_arrays` output into one training sample (numpy arrays), the
    camera image zoomed out by `zoom` (training/augment.py; 1: as recorded).

    Inputs: image (3, 256, 256) uint8 RGB; lidar (4, 256, 256) uint8 counts ch0..ch3, or, when
    the rows carry `lidar_ground_t` (the single-frame ablation), (2, 256, 256): the current
    sweep's at-ground and above-ground hits; speed () float32 m/s; target_point (2,) float32 m
    ego. Targets: waypoints (4, 2) float32 m ego; heatmap, centre_* (training/targets.py) of the
    agents with >= `min_lidar_points` LiDAR returns at t; bev (R, R) uint8 class ids
    (`downsample_bev`); traffic (2,) float32 (red light, stop sign); weather () int64 index
    into schemas.WEATHERS. Keys: episode_id, frame.

    Rows of a cached shard (`rows["cached"]`: the entry's arrays, `rows["file_row"]`: each
    row's position in them) take image, lidar and bev from the cache instead of decoding.
    """
    a, b = rows["box_start"][i], rows["box_start"][i + 1]
    boxes = visible_boxes({k: v[a:b] for k, v in rows["boxes"].items()}, min_lidar_points)
    density = render_density(boxes, output_px)
    if "cached" in rows:  # copies: the memory maps are read-only
        r = rows["file_row"][i]
        image, lidar, bev = (np.array(rows["cached"][name][r]) for name in CACHED_ARRAYS)
    else:
        image, lidar, bev = decode_inputs(rows, i, output_px)
    return {
        "image": zoom_out(image, zoom),
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


def read_frames(
    index: pd.DataFrame,
    output_px: int,
    single_frame_lidar: bool = False,
    min_lidar_points: int = MIN_LIDAR_POINTS,
) -> list[dict]:
    """Decoded samples for every frame of `index` (a slice of `scan`'s result), in its order.
    `single_frame_lidar` and `min_lidar_points` as for `FrameStream`."""
    columns = input_columns(index, single_frame_lidar)
    samples = {}
    for (path, rg), group in index.groupby(["path", "row_group"], sort=False):
        table = pq.ParquetFile(path).read_row_group(rg, columns=columns)
        rows = _row_arrays(table.take(group.row.to_numpy()))
        for k, position in enumerate(group.index):
            samples[position] = _sample(rows, k, output_px, min_lidar_points)
    return [samples[position] for position in index.index]


def input_columns(index: pd.DataFrame, single_frame_lidar: bool = False) -> list[str]:
    """The columns to read for samples of `index`'s frames; with `single_frame_lidar`, also
    `lidar_ground_t`, and a UserError if a shard of `index` lacks it (datasets written before
    schema 1.1 store ground hits summed over three sweeps only)."""
    if not single_frame_lidar:
        return list(COLUMNS)
    for path in index.path.unique():
        if GROUND_T not in pq.read_schema(path).names:
            raise UserError(
                f"{path}: no '{GROUND_T}' column (the current sweep's ground hits), which "
                "--single-frame-lidar needs; this dataset predates schema 1.1: rebuild it with "
                "`datagen build`, or train without --single-frame-lidar"
            )
    return [*COLUMNS, GROUND_T]


@dataclass(frozen=True)
class _Unit:
    """One row group and the rows of it that belong to the stream's frames."""

    path: str
    row_group: int
    rows: np.ndarray  # (n,) int, ascending positions within the row group


READ_ROWS = 8
"""Rows a worker reads from one row group at a time when shuffling: small, so that consecutive
reads come from many episodes, large enough that a read's fixed cost (a pyarrow call and
`_row_arrays`, ~1 ms) stays small beside decoding the frames (~8 ms each). Measured on the index
of a 146k-frame build (bench/train.py): 4 rows give 24.1 distinct episodes per 32-frame batch,
8 rows 23.1."""


def _interleave(units: list[_Unit], open_units: int, rng: np.random.Generator):
    """The shuffled reading schedule of one worker: (unit number, start, stop) steps.

    Up to `open_units` row groups are open at once; each step picks one of them at random and
    reads its next READ_ROWS positions [start, stop) (in file order, up to the group's last
    wanted row); a finished group is replaced by the next unit of `units`. k indexes `units`.
    """
    pending = iter(range(len(units)))
    active: list[list[int]] = []  # [unit number, next position]
    while True:
        while len(active) < open_units:
            k = next(pending, None)
            if k is None:
                break
            if len(units[k].rows):
                active.append([k, 0])
        if not active:
            return
        j = int(rng.integers(len(active)))
        k, start = active[j]
        stop = min(start + READ_ROWS, int(units[k].rows[-1]) + 1)
        yield k, start, stop
        if stop > units[k].rows[-1]:
            active[j] = active[-1]
            active.pop()
        else:
            active[j][1] = stop


class _Readers:
    """A worker's open row groups, each read front to back in slices of rows. pyarrow's
    buffered stream reads a column chunk page by page, so an open group holds a few pages
    (about a megabyte), not the whole group (tens of MB)."""

    def __init__(self):
        self.open: dict[tuple[str, int], list] = {}  # unit -> [batches, table, first row of it]

    def read(self, unit: _Unit, start: int, stop: int, columns: list[str]) -> pa.Table:
        """Rows [start, stop) of `unit`'s row group; each call continues where the last ended
        (with the `columns` of the first call)."""
        key = (unit.path, unit.row_group)
        if key not in self.open:
            shard = pq.ParquetFile(unit.path, buffer_size=1 << 20)
            batches = shard.iter_batches(  # one thread: DataLoader workers are the parallelism
                READ_ROWS, row_groups=[unit.row_group], columns=columns, use_threads=False
            )
            self.open[key] = [batches, [], 0]  # batch iterator, batches read ahead, their first row
        state = self.open[key]
        batches, ahead, first = state
        while first + sum(b.num_rows for b in ahead) < stop:
            ahead.append(next(batches))
        table = pa.Table.from_batches(ahead).slice(start - first, stop - start)
        while ahead and first + ahead[0].num_rows <= stop:  # drop what is fully read
            first += ahead.pop(0).num_rows
        state[2] = first
        if stop > unit.rows[-1]:
            del self.open[key]  # done: let pyarrow free its buffers
        return table


class FrameStream(IterableDataset):
    """Decoded samples of the frames in `index`, streamed from the shards.

    Training (`shuffle`): each epoch shuffles the list of row groups (the same way on every
    process), deals rows to DDP ranks in turn so every rank gets the same count within one,
    and deals row groups to DataLoader workers. A worker keeps `open_units` row groups open and
    reads READ_ROWS rows at a time from a randomly chosen one (`_interleave`), so its shuffle
    buffer holds frames of dozens of episodes (towns, weathers, behaviours) rather than the one
    or two a whole-row-group reader held; frames leave the buffer in random order. A batch
    (one worker's consecutive samples) therefore mixes the dataset: measured in bench/train.py.

    Evaluation (no `shuffle`): frames in index order per worker, whole row groups at a time.

    Args:
        index: the frames to stream (a slice of `scan`'s result).
        output_px: R, the side of the dense targets.
        shuffle: training order (above); without it, index order.
        seed: with the epoch (`set_epoch`), fixes every random choice, so a resumed run sees
            the same data order as an uninterrupted one.
        buffer_size: encoded frames a worker holds for shuffling.
        open_units: row groups a worker reads from at once when shuffling.
        rank, world: this process's share under DDP.
        single_frame_lidar: the LiDAR input is the current sweep only (see `_sample`); needs
            the `lidar_ground_t` column.
        min_lidar_points: detection targets keep agents with at least this many LiDAR returns
            at t (training/targets.py).
        zoom_out: (smallest factor, probability) of the camera zoom-out augmentation
            (training/augment.py), drawn per frame from seed, epoch and frame; None: none.
        cache: shard path -> its entry in the decoded-frame cache (`cache.prepare`); the
            frames of those shards are read decoded from it (the same samples), the others
            decoded from the shards.
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
        open_units: int = 64,
        single_frame_lidar: bool = False,
        min_lidar_points: int = MIN_LIDAR_POINTS,
        zoom_out: tuple[float, float] | None = None,
        cache: dict[str, CachedShard] | None = None,
    ):
        super().__init__()
        self.zoom_out = zoom_out
        self.cache = cache or {}
        self.output_px, self.shuffle, self.seed = output_px, shuffle, seed
        self.buffer_size, self.rank, self.world = buffer_size, rank, world
        self.open_units = open_units
        self.single_frame_lidar, self.min_lidar_points = single_frame_lidar, min_lidar_points
        self.columns = input_columns(index, single_frame_lidar)
        self.light_columns = [c for c in self.columns if c not in (*BLOBS, GROUND_T)]
        self.epoch = 0
        self.n_frames = len(index)
        self.units = [
            _Unit(path, int(rg), group.row.to_numpy())
            for (path, rg), group in index.groupby(["path", "row_group"], sort=False)
        ]
        self._keys = {
            (path, int(rg)): dict(zip(group.row.tolist(), zip(group.episode_id, group.frame)))
            for (path, rg), group in index.groupby(["path", "row_group"], sort=False)
        }

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def frames_per_rank(self) -> int:
        """Frames every rank gets at least (ranks differ by at most one)."""
        return self.n_frames // self.world

    def _my_units(self, worker: int = 0, n_workers: int = 1) -> list[_Unit]:
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
        return mine[worker::n_workers]

    def _order(self, read, worker: int, n_workers: int):
        """Items in the order this worker yields them. `read(unit, rows, start, stop)` turns a
        reading step (rows of `unit` within positions [start, stop)) into a list of items:
        decodable rows for `__iter__`, keys for `keys`."""
        units = self._my_units(worker, n_workers)
        if not self.shuffle:
            for unit in units:
                if len(unit.rows):
                    yield from read(unit, unit.rows, 0, int(unit.rows[-1]) + 1)
            return
        schedule = np.random.default_rng([self.seed, self.epoch, self.rank, worker, 2])
        rng = np.random.default_rng([self.seed, self.epoch, self.rank, worker, 1])
        buffer: list = []
        for k, start, stop in _interleave(units, self.open_units, schedule):
            rows = units[k].rows
            rows = rows[(rows >= start) & (rows < stop)]
            for item in read(units[k], rows, start, stop):
                buffer.append(item)
                if len(buffer) >= self.buffer_size:
                    j = rng.integers(len(buffer))
                    buffer[j], buffer[-1] = buffer[-1], buffer[j]
                    yield buffer.pop()
        for j in rng.permutation(len(buffer)):
            yield buffer[j]

    def keys(self, worker: int = 0, n_workers: int = 1):
        """(episode_id, frame) of the frames worker `worker` of `n_workers` yields, in that
        order, without reading the shards: the same schedule as iterating (bench/train.py
        measures batch composition with it)."""

        def read(unit: _Unit, rows: np.ndarray, start: int, stop: int) -> list:
            key = self._keys[(unit.path, unit.row_group)]
            return [key[int(r)] for r in rows]

        yield from self._order(read, worker, n_workers)

    def __iter__(self):
        info = get_worker_info()
        worker, n_workers = (info.id, info.num_workers) if info else (0, 1)
        readers = _Readers()

        def read(unit: _Unit, rows: np.ndarray, start: int, stop: int) -> list:
            entry = self.cache.get(unit.path)
            cached = open_entry(entry.dir) if entry is not None else None
            columns = self.columns if cached is None else self.light_columns
            if self.shuffle:
                table = readers.read(unit, start, stop, columns)
                if len(rows) < stop - start:  # another rank's rows in between (take: ~3 ms)
                    table = table.take(rows - start)
            else:  # whole row groups, in order
                shard = pq.ParquetFile(unit.path)
                table = shard.read_row_group(unit.row_group, columns=columns).take(rows)
            if not table.num_rows:
                return []
            arrays = _row_arrays(table)
            if cached is not None:
                arrays["cached"] = cached
                arrays["file_row"] = entry.row_group_starts[unit.row_group] + rows
            return [(arrays, i) for i in range(table.num_rows)]

        for arrays, i in self._order(read, worker, n_workers):
            zoom = 1.0
            if self.zoom_out is not None:
                key = (str(arrays["episode_id"][i]), int(arrays["frame"][i]))
                zoom = zoom_scale(self.seed, self.epoch, *key, *self.zoom_out)
            yield _sample(arrays, i, self.output_px, self.min_lidar_points, zoom)


def make_loader(stream: FrameStream, batch_size: int, num_workers: int) -> DataLoader:
    """Batches of `stream`'s samples; tensors keep their dtypes (uint8 images travel as such)."""
    return DataLoader(
        stream,
        batch_size=batch_size,
        num_workers=num_workers,
        pin_memory=torch.cuda.is_available(),
        prefetch_factor=4 if num_workers else None,
    )
