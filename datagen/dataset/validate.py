"""`datagen validate DIR`: check a dataset shard by shard, and against its manifest.

    datagen validate data/shards      # every shard under it, and data/shards/_manifest.json
    datagen validate data/shards/grid_small/grid_small-0-0000.parquet   # one shard

Per shard: a readable Parquet file of the v1 schema version (schemas.check_version), every row
group passing schemas.validate, one episode per file named by its file and directory, frames
0..n-1 in order, and every image, LiDAR BEV and semantic BEV decoding to its documented shape.
Against `_manifest.json`: every finished episode's shard present with the recorded row count, no
shard the manifest does not list, no episode twice, and the per-town and per-weather frame counts
equal to the manifest's statistics. Problems are printed one line each (`path: problem`) and make
the exit status non-zero.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import schemas
from datagen.dataset import executors
from datagen.errors import UserError
from schemas import codecs
from schemas.dataset import shard_files

HELP = "check every shard of a dataset (schema, manifest row counts, decodable images)"
MANIFEST = "_manifest.json"

# column -> (decoder, expected array shape)
DECODERS = {
    "image": (codecs.decode_image, (schemas.IMAGE_SIZE_PX, schemas.IMAGE_SIZE_PX, 3)),
    "lidar_bev": (
        codecs.decode_lidar_bev,
        (schemas.BEV_SIZE_PX, schemas.BEV_SIZE_PX, schemas.LIDAR_BEV_CHANNELS),
    ),
    "bev_semantic": (codecs.decode_bev_semantic, (schemas.BEV_SIZE_PX, schemas.BEV_SIZE_PX)),
}


@dataclass
class ShardReport:
    """What one shard holds and what is wrong with it."""

    path: str  # relative to the dataset directory
    rows: int = 0
    episode_ids: list[str] = field(default_factory=list)
    town_weather: dict[str, int] = field(default_factory=dict)  # "town/weather" -> rows
    network_sha256: str | None = None
    problems: list[str] = field(default_factory=list)


def check_shard(path: Path, root: Path | None = None) -> ShardReport:
    """Check one shard file; never raises for a bad file, it reports."""
    path = Path(path)
    rel = str(path.relative_to(root)) if root else str(path)
    report = ShardReport(rel)
    problem = report.problems.append
    try:
        pf = pq.ParquetFile(path)
        meta = pf.schema_arrow.metadata
        schemas.check_version(meta, rel)
    except schemas.SchemaError as e:
        problem(str(e).removeprefix(f"{rel}: "))
        return report
    except (OSError, pa.ArrowException) as e:
        problem(f"not a readable Parquet file ({_first_line(e)})")
        return report
    meta = {k.decode(): v.decode() for k, v in (meta or {}).items()}
    report.network_sha256 = meta.get(schemas.META_NETWORK_HASH)
    for key in (schemas.META_GENERATOR_VERSION, schemas.META_NETWORK_HASH, schemas.META_SEED):
        if key not in meta:
            problem(f"file metadata lacks {key!r}")
    try:
        json.loads(meta.get(schemas.META_CONFIG_JSON, ""))
    except ValueError:
        problem(f"file metadata {schemas.META_CONFIG_JSON!r} is missing or not JSON")

    ids: Counter = Counter()
    expected_frame = 0
    bad_frames = False
    decode_errors: Counter = Counter()
    for g in range(pf.metadata.num_row_groups):
        where = f"row group {g}"
        try:
            table = pf.read_row_group(g)
            schemas.validate(table, where)
        except schemas.SchemaError as e:
            problem(str(e))
            return report
        except (OSError, pa.ArrowException) as e:
            problem(f"{where}: unreadable ({_first_line(e)})")
            return report
        report.rows += table.num_rows
        ids.update(table.column("episode_id").to_pylist())
        frames = table.column("frame").to_numpy()
        want = np.arange(expected_frame, expected_frame + len(frames))
        bad_frames |= not np.array_equal(frames, want)
        expected_frame += len(frames)
        cells = Counter(
            f"{t}/{w}"
            for t, w in zip(table.column("town").to_pylist(), table.column("weather").to_pylist())
        )
        for k, n in cells.items():
            report.town_weather[k] = report.town_weather.get(k, 0) + n
        for column, (decode, shape) in DECODERS.items():
            for i, data in enumerate(table.column(column).to_pylist()):
                try:
                    array = decode(data)
                    if array.shape != shape:
                        raise ValueError(f"shape {array.shape}, expected {shape}")
                    if column == "bev_semantic" and array.max() >= len(schemas.BEV_CLASSES):
                        raise ValueError(f"class id {array.max()} out of range")
                except Exception as e:  # ValueError, cv2.error: whatever the codec says
                    if not decode_errors[column]:
                        problem(f"frame {frames[i]}: {column} does not decode ({_first_line(e)})")
                    decode_errors[column] += 1
    for column, n in decode_errors.items():
        if n > 1:
            problem(f"{column}: {n} frames in all do not decode")
    report.episode_ids = sorted(ids)
    if report.rows == 0:
        problem("no rows")
    if len(ids) > 1:
        problem(f"holds {len(ids)} episodes ({', '.join(sorted(ids)[:3])}...); expected one")
    elif ids and path.stem not in ids:
        problem(f"holds episode {next(iter(ids))!r} but is named {path.name!r}")
    if bad_frames:
        problem("frames are not 0..n-1 in order")
    towns = {k.split("/")[0] for k in report.town_weather}
    if root is not None and path.parent != root and towns != {path.parent.name}:
        problem(f"town {sorted(towns)} does not match its directory {path.parent.name!r}")
    return report


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def _check_task(path: Path, progress, root: Path) -> ShardReport:
    """check_shard as an executor task (datagen/dataset/executors.py)."""
    return check_shard(path, root)


def validate_dir(root: Path, workers: int = 1) -> tuple[list[ShardReport], list[str], int]:
    """(shard reports, dataset-level problems, total rows) for the dataset in `root`."""
    root = Path(root)
    paths = shard_files(root)
    if workers > 1 and len(paths) > 1:
        task = functools.partial(_check_task, root=root)
        by_key: dict[str, ShardReport] = {}
        with executors.stop_on_sigterm():
            pool = executors.make("process", task, workers=min(workers, len(paths)), noun="shard")
            with pool:
                for done in pool.map((str(p), p) for p in paths):
                    by_key[done.key] = done.result
        reports = [by_key[str(p)] for p in paths]
    else:
        reports = [check_shard(p, root) for p in paths]

    problems: list[str] = []
    if not paths:
        problems.append(f"{root}: no shards (*.parquet)")
    owners: dict[str, str] = {}
    for r in reports:
        for eid in r.episode_ids:
            if eid in owners:
                problems.append(f"{r.path}: episode {eid!r} is also in {owners[eid]}")
            owners.setdefault(eid, r.path)
    problems += check_manifest(root, reports)
    return reports, problems, sum(r.rows for r in reports)


def check_manifest(root: Path, reports: list[ShardReport]) -> list[str]:
    path = root / MANIFEST
    if not path.exists():
        inner = sorted(p.parent for p in root.glob(f"*/{MANIFEST}"))
        hint = f"; datagen build wrote {inner[0]}: validate that" if len(inner) == 1 else ""
        return [f"{MANIFEST}: missing (not a directory written by datagen build?){hint}"]
    try:
        manifest = json.loads(path.read_text())
        episodes = manifest["episodes"]
        stats = manifest["statistics"]
        towns = {t["name"]: t for t in manifest["towns"]}
    except (OSError, ValueError, KeyError, TypeError) as e:
        return [f"{MANIFEST}: unreadable ({_first_line(e)})"]
    problems = []
    by_path = {r.path: r for r in reports}
    listed = set()
    for e in episodes:
        if e.get("status") != "done":
            continue
        if not e.get("rows"):
            continue
        file = e.get("file")
        listed.add(file)
        r = by_path.get(file)
        if r is None:
            problems.append(f"{file}: listed in {MANIFEST} ({e['rows']} rows) but missing")
        elif r.rows != e["rows"] and not r.problems:
            problems.append(f"{file}: {r.rows} rows, {MANIFEST} says {e['rows']}")
    for r in reports:
        if r.path not in listed:
            problems.append(f"{r.path}: not listed in {MANIFEST}")
        town = r.path.split("/")[0]
        sha = towns.get(town, {}).get("network_sha256")
        if sha and r.network_sha256 and r.network_sha256 != sha:
            problems.append(f"{r.path}: network_sha256 differs from the manifest's for {town}")
    seen: Counter = Counter()
    for r in reports:
        seen.update(r.town_weather)
    want = Counter(stats.get("frames_by_town_weather", {}))
    for k in sorted(set(seen) | set(want)):
        if seen[k] != want[k] and not any(r.problems for r in reports):
            problems.append(f"{MANIFEST}: {want[k]} frames of {k}, the shards hold {seen[k]}")
    if manifest.get("status") != "complete":
        problems.append(
            f"{MANIFEST}: the build is not complete ({stats.get('frames', 0)} frames so far); "
            "run the same `datagen build` command again to finish it"
        )
    return problems


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", type=Path, help="dataset directory (or one shard)")
    p.add_argument(
        "--workers", type=int, default=None, help="processes, 1 or more (default: all cores)"
    )


def run(args) -> int:
    path: Path = args.path
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be at least 1, got {args.workers}")
    if not path.exists():
        raise UserError(f"{path}: no such file or directory")
    if path.is_file():
        reports, problems, rows = [check_shard(path)], [], 0
        rows = reports[0].rows
    else:
        reports, problems, rows = validate_dir(path, args.workers or executors.available_cores())
    lines = [f"{r.path}: {p}" for r in reports for p in r.problems] + problems
    for line in lines:
        print(line, file=sys.stderr)
    bad = sum(1 for r in reports if r.problems)
    if lines:
        print(f"{len(lines)} problem(s); {bad} of {len(reports)} shard(s) bad")
        return 1
    print(f"ok: {len(reports)} shard(s), {rows} frames")
    return 0
