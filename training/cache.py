"""Decode once: a cache of the shards' decoded, model-ready inputs, outside the dataset.

Without it every epoch decodes each frame's camera JPEG and LiDAR and BEV PNGs again (about
4 ms a frame on one core, docs/speed.md). The cache keeps what the loader's decoding returns
(`decode.decode_inputs`: the image and LiDAR the model reads and the BEV target at the model's
R) as uint8 arrays in memory-mapped .npy files, one entry per shard file:

    ROOT/<key>/image.npy    (N, 3, 256, 256) uint8 RGB            N: the shard's rows, file order
    ROOT/<key>/lidar.npy    (N, 4, 256, 256) uint8 counts ch0..ch3 (2 channels: single-frame)
    ROOT/<key>/bev.npy      (N, R, R) uint8 BEV class ids
    ROOT/<key>/entry.json   what the entry holds; its mtime is when a run last used it

`key` is the sha256 of CACHE_VERSION, the shard file's own sha256 and the input config (R, the
single-frame LiDAR ablation), so a rewritten shard or another config gets a new entry and the
old one is never read. An entry is written in a temporary directory and renamed into place:
a fill stopped at any point leaves no entry, only a temporary directory that the next fill
removes. Deleting ROOT, or any entry in it, is always safe: the loader decodes the frames of a
shard without an entry from the shard itself, as it did before the cache existed, and a cached
frame and a decoded one are the same arrays.

The cache is bounded by `limit_bytes`: entries are added in shard order while ROOT stays
within it (the least recently used entries of other shard sets are removed to make room, never
those of the set being trained on) and while the disk keeps MIN_FREE_BYTES free; the frames of
the shards past the bound are decoded every epoch, as without a cache.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import time
import uuid
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

import schemas
from schemas.bev import BEV_SIZE_PX
from training import decode

CACHE_VERSION = 1
"""Bump when `decode.decode_inputs` changes what it returns for the same shard bytes."""

ARRAYS = ("image", "lidar", "bev")
"""The entry's arrays, in `decode.decode_inputs`'s order."""
ENTRY = "entry.json"
SHARD_HASHES = "shards.json"  # memo: (path, size, mtime, inode) -> the file's sha256
TMP_PREFIX = ".tmp-"
MIN_FREE_BYTES = 5 << 30
"""A fill never leaves less than this free on the cache's disk."""
DEFAULT_LIMIT_GB = 32.0
"""The default bound: a 16,000-frame build at R = 64 takes 7.4 GB; a 146k-frame one (68 GB)
is cached in part unless the user raises it."""


def default_root() -> Path:
    """$IIDSU_CACHE/decoded, else ~/.cache/iidsu/decoded (beside the town and scene caches)."""
    base = os.environ.get("IIDSU_CACHE")
    return (Path(base) if base else Path.home() / ".cache" / "iidsu") / "decoded"


@dataclass(frozen=True)
class Inputs:
    """What the loader decodes a frame to; part of every entry's key.

    Attributes:
        output_px: R, the side of the BEV target.
        single_frame_lidar: the LiDAR input is the current sweep only (2 channels, read from
            `lidar_ground_t` and ch1), as `decode.model_inputs` builds it.
    """

    output_px: int
    single_frame_lidar: bool = False

    def shapes(self) -> dict[str, tuple[int, ...]]:
        """Per-frame shape of each of ARRAYS."""
        lidar_channels = 2 if self.single_frame_lidar else schemas.LIDAR_BEV_CHANNELS
        side = schemas.IMAGE_SIZE_PX
        return {
            "image": (3, side, side),
            "lidar": (lidar_channels, BEV_SIZE_PX, BEV_SIZE_PX),
            "bev": (self.output_px, self.output_px),
        }

    def frame_bytes(self) -> int:
        return sum(int(np.prod(s)) for s in self.shapes().values())


@dataclass(frozen=True)
class CachedShard:
    """A shard's entry: its directory and the first row of each of the shard's row groups
    (file row = row_group_starts[row_group] + row within the group)."""

    dir: str
    row_group_starts: tuple[int, ...]


def entry_key(shard_sha256: str, inputs: Inputs) -> str:
    config = {"version": CACHE_VERSION, "shard": shard_sha256, **vars(inputs)}
    return hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()


def _file_sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 22):
            h.update(chunk)
    return h.hexdigest()


def _write_json(path: Path, value) -> None:
    """Write atomically (a temporary file renamed over the old one)."""
    tmp = path.with_name(f"{TMP_PREFIX}{uuid.uuid4().hex}.json")
    tmp.write_text(json.dumps(value))
    os.replace(tmp, path)


def shard_hashes(paths: list[str], root: Path) -> dict[str, str]:
    """The sha256 of every shard file's bytes, recomputed only for files whose size, mtime or
    inode changed since the memo in ROOT/shards.json recorded them (hashing reads ~1 GB/s)."""
    memo_path = root / SHARD_HASHES
    try:
        memo = json.loads(memo_path.read_text())
    except (OSError, ValueError):
        memo = {}
    out, changed = {}, False
    for p in paths:
        real = os.path.realpath(p)
        st = os.stat(real)
        stamp = [st.st_size, st.st_mtime_ns, st.st_ino]
        known = memo.get(real)
        if known is None or known[:3] != stamp:
            memo[real] = [*stamp, _file_sha256(real)]
            changed = True
        out[p] = memo[real][3]
    if changed:
        with contextlib.suppress(OSError):
            _write_json(memo_path, memo)
    return out


_OPEN: dict[str, dict[str, np.ndarray] | None] = {}  # per process: entry dir -> memory maps


def open_entry(entry: str) -> dict[str, np.ndarray] | None:
    """The memory-mapped arrays of an entry (opened once per process), or None if it is gone
    (deleted or evicted since the run started: the loader then decodes the shard)."""
    if entry not in _OPEN:
        try:
            _OPEN[entry] = {n: np.load(Path(entry) / f"{n}.npy", mmap_mode="r") for n in ARRAYS}
        except (OSError, ValueError):
            _OPEN[entry] = None
    return _OPEN[entry]


def _entries(root: Path) -> dict[str, tuple[int, float]]:
    """Every complete entry in ROOT: key -> (bytes, last use as a POSIX time)."""
    out = {}
    for d in root.iterdir() if root.is_dir() else ():
        meta = d / ENTRY
        if d.name.startswith(TMP_PREFIX) or not meta.is_file():
            continue
        with contextlib.suppress(OSError):
            size = sum(f.stat().st_size for f in d.iterdir())
            out[d.name] = (size, meta.stat().st_mtime)
    return out


def _remove_stale_tmp(root: Path) -> None:
    """Remove temporary directories of fills whose process has ended (an interrupted fill)."""
    for d in root.glob(f"{TMP_PREFIX}*"):
        pid = d.name[len(TMP_PREFIX) :].split("-")[0]
        alive = True
        try:
            os.kill(int(pid), 0)
        except (ValueError, ProcessLookupError):
            alive = False
        except PermissionError:
            pass
        if not alive:
            if d.is_dir():
                shutil.rmtree(d, ignore_errors=True)
            else:
                d.unlink(missing_ok=True)


def fill_entry(shard: str, inputs: Inputs, root: str, key: str) -> bool:
    """Decode every row of `shard` into the entry ROOT/key (written in a temporary directory,
    then renamed). Returns False if another process put the entry there first."""
    root_path = Path(root)
    tmp = root_path / f"{TMP_PREFIX}{os.getpid()}-{uuid.uuid4().hex}"
    tmp.mkdir(parents=True)
    try:
        f = pq.ParquetFile(shard)
        n = f.metadata.num_rows
        shapes = inputs.shapes()
        arrays = {
            name: np.lib.format.open_memmap(
                tmp / f"{name}.npy", mode="w+", dtype=np.uint8, shape=(n, *shapes[name])
            )
            for name in ARRAYS
        }
        columns = decode.blob_columns(inputs.single_frame_lidar)
        row = 0
        for batch in f.iter_batches(32, columns=columns, use_threads=False):
            rows = decode.blob_arrays(batch)
            for i in range(batch.num_rows):
                for name, value in zip(ARRAYS, decode.decode_inputs(rows, i, inputs.output_px)):
                    arrays[name][row] = value
                row += 1
        for a in arrays.values():
            a.flush()
        del arrays
        meta = {"shard": os.path.realpath(shard), "rows": n, **vars(inputs)}
        (tmp / ENTRY).write_text(json.dumps(meta, indent=1) + "\n")
        try:
            os.rename(tmp, root_path / key)
        except OSError:  # another run filled it meanwhile: theirs is the same
            return False
        return True
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _fill_one(args: tuple) -> tuple[str, bool, str]:
    shard, inputs, root, key = args
    try:
        return shard, fill_entry(shard, inputs, root, key), ""
    except OSError as e:  # e.g. the disk filled up: this shard stays uncached
        return shard, False, str(e)


def prepare(
    shards: list[str],
    inputs: Inputs,
    root: str | Path,
    limit_bytes: int,
    processes: int = 1,
    rank: int = 0,
    world: int = 1,
    barrier: Callable[[], None] | None = None,
    log: Callable[[str], None] = print,
) -> dict[str, CachedShard]:
    """Fill the missing entries of `shards` within the bound; return those that exist.

    Entries are planned in `shards` order: each missing one is filled if ROOT, with it, stays
    within `limit_bytes` (after removing least recently used entries of other shard sets) and
    the disk keeps MIN_FREE_BYTES free. Under DDP (`world` > 1) every rank plans the same
    entries and fills every world-th of them, then waits at `barrier`. `processes` decode in
    parallel. Returns shard path -> CachedShard for the shards that have an entry now.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    if rank == 0:
        _remove_stale_tmp(root)
    hashes = shard_hashes(shards, root)
    keys = {s: entry_key(hashes[s], inputs) for s in shards}
    rows = {s: pq.ParquetFile(s).metadata.num_rows for s in shards}
    existing = _entries(root)
    # This set's entries, in shard order, up to the bound: those it has and those to fill.
    free = shutil.disk_usage(root).free
    keep, plan, total = set(), [], 0
    for s in shards:
        k = keys[s]
        if k in keep:  # two shards with the same bytes share an entry
            continue
        size = existing[k][0] if k in existing else rows[s] * inputs.frame_bytes()
        if total + size > limit_bytes:
            break  # this shard and the rest stay uncached
        if k not in existing:
            if free - size < MIN_FREE_BYTES:
                break
            free -= size
            plan.append(s)
        keep.add(k)
        total += size
    # Make room: other sets' entries, least recently used first; this set's past the bound.
    others = sorted((t, k) for k, (_, t) in existing.items() if k not in keep)  # oldest first
    evict = [k for k in existing if k not in keep and k in keys.values()]
    used = sum(size for k, (size, _) in existing.items() if k not in evict) + sum(
        rows[s] * inputs.frame_bytes() for s in plan
    )
    for _, k in others:
        if used <= limit_bytes:
            break
        if k not in evict:
            evict.append(k)
            used -= existing[k][0]
    if rank == 0:
        for k in evict:
            shutil.rmtree(root / k, ignore_errors=True)
    todo = plan[rank::world]
    if todo:
        frames = sum(rows[s] for s in plan)
        log(
            f"decoding {frames} frames of {len(plan)} shards into the cache {root} "
            f"({frames * inputs.frame_bytes() / 1e9:.1f} GB, once; --cache-gb 0 turns it off)"
        )
        t0 = time.perf_counter()
        jobs = [(s, inputs, str(root), keys[s]) for s in todo]
        if processes > 1 and len(jobs) > 1:
            ctx = get_context("spawn")  # no fork of a process that has run torch's thread pool
            with ProcessPoolExecutor(min(processes, len(jobs)), mp_context=ctx) as pool:
                results = list(pool.map(_fill_one, jobs))
        else:
            results = [_fill_one(j) for j in jobs]
        errors = {e for _, _, e in results if e}
        log(
            f"cache filled in {time.perf_counter() - t0:.0f} s"
            + (f"; not cached: {'; '.join(sorted(errors))}" if errors else "")
        )
    if barrier is not None and world > 1:
        barrier()
    out = {}
    for s in shards:
        d = root / keys[s]
        if (d / ENTRY).is_file():
            with contextlib.suppress(OSError):
                os.utime(d / ENTRY)  # last use, for the bound's eviction order
            meta = pq.ParquetFile(s).metadata
            starts = np.cumsum(
                [0] + [meta.row_group(i).num_rows for i in range(meta.num_row_groups)]
            )
            out[s] = CachedShard(str(d), tuple(int(x) for x in starts[:-1]))
    return out
