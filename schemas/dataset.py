"""What every reader of an iidsu dataset needs: which files are shards, their rows, box corners.

    files = shard_files("data/")                   # every shard under data/, in read order
    row = read_row("data/", frame=10)              # one frame as a dict of Python values
    table = read_episode("data/", "grid_small-0-0003")   # one episode's frames, in order

**Which files are shards** (one rule for `datagen build`, `inspect`, `validate` and `train`):
every file named `*.parquet` under the directory, at any depth, except those in which a file or
directory name on the way starts with `_` or `.` (pyarrow's and pandas's rule for data files:
`_manifest.json`, `_frame.png`, temporary `_*.parquet` while a build writes), in the order of
their path strings (pyarrow's order, so `pd.read_parquet(DIR)` numbers frames the same way when
DIR holds nothing else). Files of any other name (`README.md`, a PNG) are not shards, so a
reader of `data/` skips `data/README.md`, where pandas would fail on it. A path that is a file
is taken as the one shard.

**Box geometry**: `box_corners` turns the `boxes` column's centre, yaw and extents into corner
points, in the same frame as the centre (the ego frame at t for the shards' boxes; the world
frame in `drive`'s infraction judge, which uses the same function).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

import schemas

SHARD_SUFFIX = ".parquet"
NOT_DATA_PREFIXES = ("_", ".")  # pyarrow's default `ignore_prefixes`


class DatasetError(ValueError):
    """A path that is no dataset, or a frame or episode it does not hold; one-line message."""


def shard_files(path: str | Path) -> list[Path]:
    """The shards of the dataset at `path` (see the module docstring for the rule).

    Returns [] for a directory without shards; raises DatasetError if `path` does not exist.
    """
    path = Path(path)
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise DatasetError(f"{path}: no such file or directory")
    files = []
    for dirpath, dirnames, filenames in os.walk(path):
        dirnames[:] = [d for d in dirnames if not d.startswith(NOT_DATA_PREFIXES)]
        files += [
            Path(dirpath) / f
            for f in filenames
            if f.endswith(SHARD_SUFFIX) and not f.startswith(NOT_DATA_PREFIXES)
        ]
    return sorted(files, key=lambda p: p.as_posix())


def _shards(path: str | Path) -> list[Path]:
    files = shard_files(path)
    if not files:
        raise DatasetError(f"{path}: no shards (*.parquet files) in this directory")
    return files


def open_shard(path: str | Path) -> pq.ParquetFile:
    """The shard at `path`, opened, with its schema version checked.

    Raises DatasetError for a file that is not Parquet, schemas.SchemaError for another major
    schema version or a file without one."""
    try:
        pf = pq.ParquetFile(path)
    except (OSError, pa.ArrowException) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise DatasetError(f"{path}: not a readable Parquet file ({first})") from None
    schemas.check_version(pf.schema_arrow.metadata, str(path))
    return pf


def read_row(path: str | Path, frame: int, episode: str | None = None) -> dict:
    """One frame of the dataset at `path` as a dict of Python values (column -> value).

    Without `episode`, `frame` counts rows across the shards in read order; with it, `frame`
    is that episode's `frame` number."""
    if frame < 0:
        raise DatasetError(f"frame must be >= 0, got {frame}")
    if episode is not None:
        table = read_episode(path, episode)
        hit = np.flatnonzero(table.column("frame").to_numpy() == frame)
        if not len(hit):
            raise DatasetError(f"{path}: episode {episode!r} has no frame {frame}")
        return table.slice(int(hit[0]), 1).to_pylist()[0]
    seen = 0
    for f in _shards(path):
        pf = open_shard(f)
        n = pf.metadata.num_rows
        if frame < seen + n:
            return pf.read().slice(frame - seen, 1).to_pylist()[0]
        seen += n
    raise DatasetError(f"{path}: frame {frame} out of range ({seen} rows)")


def episode_ids(path: str | Path) -> list[str]:
    """The episode ids in the dataset at `path`, in read order, each once."""
    ids: dict[str, None] = {}
    for f in _shards(path):
        column = open_shard(f).read(columns=["episode_id"]).column("episode_id")
        ids.update(dict.fromkeys(column.unique().to_pylist()))
    return list(ids)


def read_episode(path: str | Path, episode: str, columns: list[str] | None = None) -> pa.Table:
    """Every frame of `episode` in the dataset at `path`, sorted by `frame`.

    Raises DatasetError, naming some of the episodes there, if it holds no such episode."""
    parts, seen = [], {}
    for f in _shards(path):
        pf = open_shard(f)
        ids = pf.read(columns=["episode_id"]).column("episode_id")
        mask = pc.equal(ids, episode)
        if pc.any(mask).as_py():
            parts.append(pf.read(columns=columns).filter(mask))
        elif len(seen) < 4:
            seen.update(dict.fromkeys(ids.unique().to_pylist()))
    if not parts:
        some = ", ".join(list(seen)[:4])
        raise DatasetError(f"{path}: no episode {episode!r} (episodes there include {some})")
    table = pa.concat_tables(parts)
    return table.take(pc.sort_indices(table, [("frame", "ascending")]))


def box_corners(
    x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray
) -> np.ndarray:
    """Corners of boxes on the ground plane, in the frame of their centres.

    Args: centres x, y (m), heading yaw (rad, counter-clockwise from +x), extents along
    (length, m) and across (width, m) the heading; scalars or arrays of one shape (...).
    Returns: (..., 4, 2) float64 (x, y), front-right first, then counter-clockwise
    (front-left, rear-left, rear-right), Waymax's `bbox_corners` order.
    """
    x, y, yaw, length, width = np.broadcast_arrays(
        *(np.asarray(v, np.float64) for v in (x, y, yaw, length, width))
    )
    sign = np.array([(1, -1), (1, 1), (-1, 1), (-1, -1)], np.float64)  # (4, 2) front, left
    along = sign[:, 0] * (length[..., None] / 2)  # (..., 4)
    across = sign[:, 1] * (width[..., None] / 2)
    c, s = np.cos(yaw)[..., None], np.sin(yaw)[..., None]
    return np.stack(
        [x[..., None] + c * along - s * across, y[..., None] + s * along + c * across], -1
    )
