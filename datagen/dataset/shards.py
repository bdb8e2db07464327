"""Crash-safe Parquet shards: one file per episode, visible only once complete.

A shard is written under a temporary name that starts with `_` in the same directory (readers
skip `_` files, see data/README.md), flushed and fsync'ed, renamed onto its final name (atomic on
POSIX within one filesystem), and the directory is fsync'ed so the rename itself survives a power
cut. A build killed at any instant therefore leaves complete shards and `_*.tmp` debris, never a
truncated `.parquet`; `remove_temporaries` sweeps the debris on resume. The same protocol writes
`_manifest.json`.

Layout: `<out>/<town>/<episode_id>.parquet` (`shard_path`).
"""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

import schemas
from datagen.errors import UserError

COMPRESSION = "zstd"
ROW_GROUP_TARGET_BYTES = 32 * 1024 * 1024
"""Uncompressed bytes per row group: tens of MB, so a streaming reader holds one group of a few
dozen frames (~60 KB each) at a time while Parquet's per-group overhead stays negligible."""

# Small categorical strings: Parquet dictionary-encodes them on disk (schemas.CATEGORIES).
DICTIONARY_COLUMNS = ("episode_id", "town", *schemas.CATEGORIES)
# Column statistics (min/max) help filters on scalars; on JPEG/PNG bytes they are only footer bloat.
STATISTICS_COLUMNS = tuple(
    f.name for f in schemas.FIELDS if not pa.types.is_binary(f.type) and f.name != "boxes"
)
TEMP_PREFIX = "_"
TEMP_SUFFIX = ".tmp"
_HOST = os.uname().nodename.replace("/", "_")
_DISK_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
_NOT_WRITABLE = (errno.EACCES, errno.EPERM, errno.EROFS)


def shard_path(out_dir: Path, town: str, episode_id: str) -> Path:
    return Path(out_dir) / town / f"{episode_id}.parquet"


def rows_per_group(table: pa.Table, target_bytes: int = ROW_GROUP_TARGET_BYTES) -> int:
    """Rows per row group so that a group holds about `target_bytes` of uncompressed data."""
    if table.num_rows == 0:
        return 1
    per_row = max(1, table.nbytes // table.num_rows)
    return max(1, min(table.num_rows, target_bytes // per_row))


def write_shard(table: pa.Table, path: Path, *, validate: bool = True) -> int:
    """Atomically write `table` (a v1 table, file metadata included) to `path`; return its size
    in bytes. Raises schemas.SchemaError for an invalid table and UserError for a full disk or
    an unwritable directory."""
    path = Path(path)
    if validate:
        schemas.validate(table, where=str(path))

    def write(tmp: Path) -> None:
        pq.write_table(
            table,
            tmp,
            row_group_size=rows_per_group(table),
            compression=COMPRESSION,
            use_dictionary=[c for c in DICTIONARY_COLUMNS if c in table.schema.names],
            write_statistics=[c for c in STATISTICS_COLUMNS if c in table.schema.names],
        )

    _atomic_write(path, write)
    return path.stat().st_size


def write_json(obj: object, path: Path) -> None:
    """Atomically write `obj` as indented JSON (e.g. `_manifest.json`)."""
    data = (json.dumps(obj, indent=1, sort_keys=False) + "\n").encode()

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            f.write(data)

    _atomic_write(Path(path), write)


def read_json(path: Path) -> object:
    with open(path, encoding="utf-8") as f:
        return json.load(f)


def remove_temporaries(out_dir: Path) -> int:
    """Delete `_*.tmp` files a killed writer left in `out_dir` and its town directories; return
    how many. Only files this module names are touched."""
    out_dir = Path(out_dir)
    n = 0
    for d in [out_dir, *(p for p in out_dir.iterdir() if p.is_dir())] if out_dir.is_dir() else []:
        for p in d.glob(f"{TEMP_PREFIX}*{TEMP_SUFFIX}"):
            p.unlink(missing_ok=True)
            n += 1
    return n


def check_writable(out_dir: Path) -> None:
    """Create `out_dir` and prove a file can be written and renamed there (UserError if not)."""
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise _user_error(e, out_dir) from None
    write_json({}, out_dir / f"{TEMP_PREFIX}probe.json")
    (out_dir / f"{TEMP_PREFIX}probe.json").unlink()


def _atomic_write(path: Path, write) -> None:
    # host and pid: writers on different machines of a cluster never share a temporary
    tmp = path.parent / f"{TEMP_PREFIX}{path.name}.{_HOST}.{os.getpid()}{TEMP_SUFFIX}"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write(tmp)
        _fsync_file(tmp)
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except BaseException as e:  # KeyboardInterrupt included: never leave a half-written shard
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        if isinstance(e, OSError | pa.ArrowException):
            raise _user_error(e, path) from None
        raise


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _user_error(e: BaseException, path: Path) -> BaseException:
    """A full disk or an unwritable directory becomes a one-line UserError; anything else is a
    bug and keeps its type (pyarrow reports OS errors as ArrowException with the errno text)."""
    code = getattr(e, "errno", None)
    text = str(e)
    if code in _DISK_FULL or "No space left" in text or "Disk quota" in text:
        return UserError(f"disk full while writing {path}; free space and run again to resume")
    if code in _NOT_WRITABLE or "Permission denied" in text or "Read-only file system" in text:
        return UserError(f"cannot write to {path.parent}: {os.strerror(code or errno.EACCES)}")
    if isinstance(e, OSError):
        return UserError(f"cannot write {path}: {e.strerror or e}")
    return e
