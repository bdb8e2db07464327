"""The build's manifest (`_manifest.json`), its lock, resume and statistics.

A shard is written under a `_` temporary name and renamed when complete (datagen/dataset/shards.py), then
recorded in `_manifest.json`, itself rewritten atomically. Running the same command again keeps
every finished episode (its shard present with the manifest's row count), adopts shards that were
renamed but not yet recorded, and redoes the rest (`prepare_output`).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections import Counter, defaultdict
from collections.abc import Iterable
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

import schemas
from datagen.dataset import shards
from datagen.dataset.plan import BuildConfig, TownPlan, is_done
from datagen.errors import UserError
from schemas.dataset import shard_files

MANIFEST = "_manifest.json"
LOCK = "_build.lock"
MANIFEST_FORMAT = "iidsu-build-manifest/1"
META_EPISODE_JSON = "iidsu.episode_json"
"""Shard file metadata: the episode's spec, row count and end reason, so that a shard renamed just
before a crash (but not yet in the manifest) can be adopted on resume."""


# --------------------------------------------------------------------------------------------
# Manifest and resume


def load_manifest(out_dir: Path) -> dict | None:
    path = Path(out_dir) / MANIFEST
    if not path.exists():
        return None
    try:
        manifest = shards.read_json(path)
    except (OSError, ValueError) as e:
        raise UserError(f"{path} is unreadable ({e}); use --force to start over") from None
    if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
        raise UserError(f"{path} is not an iidsu build manifest; use --force to start over")
    return manifest


def _iidsu_shards(out_dir: Path) -> Iterable[tuple[Path, dict | None]]:
    """(path, file metadata, {} if unreadable, None if not an iidsu shard) for every file a
    reader of `out_dir` takes as a shard (`schemas.dataset.shard_files`: the one rule)."""
    for path in shard_files(out_dir):
        try:
            meta = pq.read_schema(path).metadata or {}
        except (OSError, pa.ArrowException):
            yield path, {}
            continue
        meta = {k.decode(): v.decode() for k, v in meta.items()}
        yield path, meta if schemas.META_SCHEMA_VERSION in meta else None


def _ours(path: Path, out_dir: Path, cfg: BuildConfig) -> bool:
    """Whether `path` is where this build writes one of its episodes."""
    town = path.parent.name
    return (
        path.parent.parent == out_dir
        and town in {t.name for t in cfg.towns}
        and path.stem.startswith(f"{town}-{cfg.seed}-")
    )


def _differences(old: dict, new: dict) -> list[str]:
    out = []
    for k in new:
        if old.get(k) != new[k]:
            a, b = json.dumps(old.get(k)), json.dumps(new[k])
            out.append(f"{k}: {a} != {b}" if len(a) + len(b) < 80 else k)
    return out


class BuildLock:
    """`<out>/_build.lock`, held (flock) for the whole build so that two builds never write
    one directory; the kernel releases it when the process dies, even by SIGKILL."""

    def __init__(self, out_dir: Path):
        self.path = Path(out_dir) / LOCK
        self.fd: int | None = None

    def __enter__(self) -> BuildLock:
        import fcntl

        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self.fd)
            self.fd = None
            raise UserError(
                f"another datagen build is writing {self.path.parent}; wait for it or stop it"
            ) from None
        return self

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            self.path.unlink(missing_ok=True)
            os.close(self.fd)  # closing releases the lock
            self.fd = None


def prepare_output(out_dir: Path, cfg: BuildConfig, force: bool) -> dict:
    """Check or clear `out_dir` for this build; return the finished episodes to keep."""
    shards.remove_temporaries(out_dir)
    manifest = None if force else load_manifest(out_dir)
    found = list(_iidsu_shards(out_dir))
    # Unreadable files named like this build's shards are damaged ones of ours (redone below).
    foreign = [
        p for p, meta in found if meta is None or (meta == {} and not _ours(p, out_dir, cfg))
    ]
    if foreign:
        raise UserError(
            f"{out_dir} holds Parquet files that are not iidsu shards (e.g. {foreign[0]}); "
            "choose another --out"
        )
    if manifest is None and (found or (out_dir / MANIFEST).exists()):
        if not force:
            raise UserError(
                f"{out_dir} holds shards but no build manifest; use --force to replace them"
            )
    if manifest is not None and manifest.get("build") != cfg.identity():
        diff = ", ".join(_differences(manifest.get("build") or {}, cfg.identity()))
        raise UserError(
            f"{out_dir} was built with different arguments ({diff}); "
            "use --force to replace it, or choose another --out"
        )
    if force:
        for path, _ in found:
            path.unlink()
        for d in out_dir.iterdir():
            if d.is_dir() and not d.name.startswith((".", "_")) and not any(d.iterdir()):
                d.rmdir()
        (out_dir / MANIFEST).unlink(missing_ok=True)
        return {}

    # Resume: keep recorded episodes whose shard is intact, adopt recorded-in-shard ones.
    done = {}
    for record in (manifest or {}).get("episodes", []):
        if record.get("status") != "done":
            continue
        if record["rows"] == 0:
            done[record["episode_id"]] = record
            continue
        path = out_dir / record["file"]
        try:
            if pq.ParquetFile(path).metadata.num_rows == record["rows"]:
                done[record["episode_id"]] = record
        except (OSError, pa.ArrowException):
            pass
    for path, meta in found:
        eid = path.stem
        if eid in done:
            continue
        try:
            record = json.loads(meta[META_EPISODE_JSON])
            ok = (
                record["episode_id"] == eid
                and pq.ParquetFile(path).metadata.num_rows == record["rows"]
            )
        except (KeyError, ValueError, OSError, pa.ArrowException):
            ok = False
        if ok:
            rel = str(path.relative_to(out_dir))
            done[eid] = {**record, "file": rel, "bytes": path.stat().st_size, "status": "done"}
        else:
            path.unlink()  # a damaged shard of ours: it will be written again
    return done


def make_manifest(cfg: BuildConfig, plans: dict[str, TownPlan], done: dict, run: dict) -> dict:
    """The manifest: build identity, per-episode records in plan order, statistics. Everything
    but `run` (timings, workers) is a function of the config and the episode results."""
    episodes = []
    for town in cfg.towns:
        for e in plans[town.name].episodes:
            record = done.get(e.episode_id) if is_done(e, done) else None
            if record is None:
                episodes.append({**e.key(), "round": e.round, "status": "pending"})
            else:
                record = {k: v for k, v in record.items() if not k.startswith("_")}
                episodes.append({**record, "status": "done"})
    complete = all(p.complete for p in plans.values()) and all(
        r["status"] == "done" for r in episodes
    )
    return {
        "format": MANIFEST_FORMAT,
        "status": "complete" if complete else "building",
        "build": cfg.identity(),
        "towns": [dataclasses.asdict(t) for t in cfg.towns],
        "episodes": episodes,
        "statistics": statistics(episodes, plans),
        "run": run,
    }


def statistics(episodes: list[dict], plans: dict[str, TownPlan]) -> dict:
    finished = [r for r in episodes if r["status"] == "done"]
    by = defaultdict(Counter)
    totals: Counter = Counter()
    ended: Counter = Counter()
    for r in finished:
        by["town"][r["town"]] += r["rows"]
        by["weather"][r["weather"]] += r["rows"]
        by["behaviour"][r["behaviour"]] += r["rows"]
        by["town_weather"][f"{r['town']}/{r['weather']}"] += r["rows"]
        if r["rows"] < r["n_frames"]:
            ended[r.get("end_reason") or "unknown"] += 1
        for k, v in (r.get("stats") or {}).items():
            if isinstance(v, int) and not isinstance(v, bool) and not k.startswith("n_"):
                totals[k] += v  # counts (collisions, teleports, ...); means do not add up
    return {
        "frames": sum(r["rows"] for r in finished),
        "episodes": len(finished),
        "bytes": sum(r.get("bytes", 0) for r in finished),
        "frames_by_town": dict(by["town"]),
        "frames_by_weather": dict(by["weather"]),
        "frames_by_behaviour": dict(by["behaviour"]),
        "frames_by_town_weather": dict(by["town_weather"]),
        "episodes_ended_early": dict(ended),
        "stats_totals": dict(totals),
        "shortfall": {t: p.shortfall for t, p in plans.items() if p.shortfall},
    }
