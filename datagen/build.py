"""`datagen build`: the dataset, as parallel, resumable, crash-safe Parquet shards.

    datagen build --towns 8 --frames 146000            # paper scale (Sec. IV: 146k frames, 8 towns)
    datagen build --town grid_small --town spider --frames 2000 --workers 2 --out data/
    datagen build --net my_city.net.xml --frames 5000 --weather-mix sunny=3,foggy=1
    datagen build ... --executor ray [--ray-address ray://head:10001]

Plan. The frame budget is split evenly across the towns, each town's share across the weathers
(by `--weather-mix`, default uniform), and each (town, weather) share into episodes of at most
`--episode-seconds` of driving. Episode ids, seeds and behaviour profiles come from `--seed`
alone, so the plan does not depend on worker count, executor or timing. An episode that ends
early (route end, teleport, blocked ego) delivers fewer rows than asked; once every episode of a
town's round is finished, the missing frames of each weather are planned as a further round of
episodes, numbered after the last. Because each episode's content is a function of its spec and
each round a function of the previous rounds' row counts, the dataset is the same however the
work was scheduled or interrupted.

Crash safety and resume. A shard is written under a `_` temporary name and renamed when complete
(datagen/shards.py), then recorded in `_manifest.json`, itself rewritten atomically. Running the
same command again keeps every finished episode (its shard present with the manifest's row
count), adopts shards that were renamed but not yet recorded, and redoes the rest.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata
import json
import math
import multiprocessing as mp
import os
import queue
import resource
import signal
import sys
import time
import traceback
import zlib
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import schemas
from datagen import shards
from datagen.errors import UserError

HELP = "generate the dataset: driving episodes across towns and weathers, as Parquet shards"

PAPER_FRAMES = 146_000  # paper Sec. IV "Dataset Collection": 146k frames from 8 towns at 2 FPS
EPISODE_SECONDS = 180.0  # "a few minutes of driving" per episode: 360 frames at 2 Hz
MAX_ROUNDS = 8
"""Top-up rounds per town for episodes that ended early. A weather whose whole round delivered no
rows is given up at once (a network where the ego cannot drive); the manifest records any
shortfall."""
MAX_TASKS_PER_WORKER = 50
"""Episodes a worker process runs before it is replaced: bounds slow leaks (libsumo, Embree)
without paying a process start (imports, scene caches) for every episode."""
SUMMARY_COUNTS = (
    "collisions",  # the ego's (world.py counts SUMO's collision checks, junctions included)
    "other_collisions",
    "red_light_violations",
    "teleports",
    "hard_brakes",
    "reroutes",
)
MANIFEST = "_manifest.json"
LOCK = "_build.lock"
MANIFEST_FORMAT = "iidsu-build-manifest/1"
META_EPISODE_JSON = "iidsu.episode_json"
"""Shard file metadata: the episode's spec, row count and end reason, so that a shard renamed just
before a crash (but not yet in the manifest) can be adopted on resume."""


# --------------------------------------------------------------------------------------------
# Configuration and plan


@dataclass(frozen=True)
class Town:
    """A town of the build: a built-in town, or a user's network (`--net`, named by its stem)."""

    name: str
    net_path: str
    network_sha256: str
    builtin: bool


@dataclass(frozen=True)
class BuildConfig:
    """What determines the dataset. Workers, executor and output directory do not.

    Attributes:
        towns: the towns, in order.
        frames: total rows in the dataset, split evenly across towns.
        seed: the one seed every episode seed derives from.
        episode_seconds: driving time per planned episode (frames = seconds x 2 Hz).
        weather_mix: ((weather, weight), ...) normalised to sum 1; None = uniform.
        sensors: a datagen.episode.SensorConfig, or None for its defaults.
    """

    towns: tuple[Town, ...]
    frames: int = PAPER_FRAMES
    seed: int = 0
    episode_seconds: float = EPISODE_SECONDS
    weather_mix: tuple[tuple[str, float], ...] | None = None
    sensors: object | None = None

    @property
    def episode_frames(self) -> int:
        return max(1, round(self.episode_seconds * schemas.FRAME_RATE_HZ))

    def weights(self) -> dict[str, float]:
        mix = dict(self.weather_mix) if self.weather_mix else dict.fromkeys(schemas.WEATHERS, 1.0)
        total = sum(mix.values())
        return {w: mix.get(w, 0.0) / total for w in schemas.WEATHERS}

    def sensors_dict(self) -> dict:
        sensors = self.sensors
        if sensors is None:
            from datagen.episode import SensorConfig

            sensors = SensorConfig()
        return _jsonable(sensors.to_dict() if hasattr(sensors, "to_dict") else sensors)

    def identity(self) -> dict:
        """The manifest's record of the arguments; a different identity is a different dataset."""
        return {
            "schema_version": schemas.SCHEMA_VERSION,
            "generator_version": generator_version(),
            "towns": [{"name": t.name, "network_sha256": t.network_sha256} for t in self.towns],
            "frames": self.frames,
            "seed": self.seed,
            "episode_frames": self.episode_frames,
            "weather_mix": self.weights(),
            "sensors": self.sensors_dict(),
        }


@dataclass(frozen=True)
class Episode:
    """One planned episode (the fields of datagen.episode.EpisodeSpec, plus its round)."""

    episode_id: str
    town: str
    seed: int
    weather: str
    behaviour: str
    n_frames: int
    round: int = 0

    def key(self) -> dict:
        """What must match for a finished episode to count as this one."""
        return {
            k: getattr(self, k)
            for k in ("episode_id", "town", "seed", "weather", "behaviour", "n_frames")
        }


def available_cores() -> int:
    """Cores this process may run on (taskset / cgroup CPU sets respected)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def generator_version() -> str:
    """The shards' `iidsu.generator_version` (package and scene version): a dataset is never
    resumed with a different generator."""
    try:
        from datagen.episode import generator_version as episode_generator_version
    except ImportError:  # pragma: no cover  (the sensors are part of the package)
        return importlib.metadata.version("iidsu")
    return episode_generator_version()


def split_evenly(total: int, parts: int) -> list[int]:
    """`total` as `parts` integers differing by at most one, larger ones first."""
    base, extra = divmod(total, parts)
    return [base + (i < extra) for i in range(parts)]


def apportion(total: int, weights: dict[str, float]) -> dict[str, int]:
    """Largest-remainder split of `total` by `weights` (ties go to the earlier key)."""
    exact = {k: total * w for k, w in weights.items()}
    counts = {k: math.floor(v) for k, v in exact.items()}
    order = sorted(weights, key=lambda k: -(exact[k] - counts[k]))  # stable: earlier key first
    for k in order[: total - sum(counts.values())]:
        counts[k] += 1
    return counts


def town_quotas(cfg: BuildConfig) -> dict[str, dict[str, int]]:
    """Frames per town and weather: {town: {weather: frames}}."""
    per_town = split_evenly(cfg.frames, len(cfg.towns))
    return {t.name: apportion(n, cfg.weights()) for t, n in zip(cfg.towns, per_town)}


def _episode(cfg: BuildConfig, town: str, index: int, weather: str, n: int, rnd: int) -> Episode:
    # A town's episodes are keyed by (seed, town name, index): the same town and index give the
    # same episode in any build with the same seed, whatever the other towns are.
    root = np.random.SeedSequence(cfg.seed, spawn_key=(zlib.crc32(town.encode()), index))
    sim_seed, draw_seed = root.spawn(2)
    from datagen.behaviour import draw_condition

    w, behaviour = draw_condition(np.random.default_rng(draw_seed), {weather: 1.0})
    assert w == weather, (w, weather)
    return Episode(
        episode_id=f"{town}-{cfg.seed}-{index:04d}",
        town=town,
        seed=int(sim_seed.generate_state(1)[0] & 0x7FFFFFFF),  # SUMO takes a signed 32-bit seed
        weather=weather,
        behaviour=behaviour,
        n_frames=n,
        round=rnd,
    )


def _round_episodes(
    cfg: BuildConfig, town: str, need: dict[str, int], first_index: int, rnd: int
) -> list[Episode]:
    """Episodes of at most cfg.episode_frames covering `need` frames per weather, weathers
    interleaved so that a partial build already holds every weather."""
    sizes = {
        w: split_evenly(n, math.ceil(n / cfg.episode_frames)) for w, n in need.items() if n > 0
    }
    out: list[Episode] = []
    for k in range(max((len(s) for s in sizes.values()), default=0)):
        for w in schemas.WEATHERS:
            if w in sizes and k < len(sizes[w]):
                out.append(_episode(cfg, town, first_index + len(out), w, sizes[w][k], rnd))
    return out


@dataclass
class TownPlan:
    """A town's episodes so far, whether its frames are all planned and done, and any frames it
    had to give up on (weathers where a whole round delivered nothing, or MAX_ROUNDS reached)."""

    episodes: list[Episode]
    complete: bool
    shortfall: dict[str, int]


def plan_town(cfg: BuildConfig, town: str, quota: dict[str, int], done: dict) -> TownPlan:
    """The pure planning function: rounds of `town` given the finished episodes `done`
    ({episode_id: record with "rows" and the Episode key}). Deterministic in its arguments."""
    episodes = _round_episodes(cfg, town, quota, 0, 0)
    current = episodes
    given_up: dict[str, int] = {}
    for rnd in range(1, MAX_ROUNDS + 1):
        if not all(_is_done(e, done) for e in current):
            return TownPlan(episodes, False, given_up)
        got: Counter = Counter()
        for e in episodes:
            got[e.weather] += done[e.episode_id]["rows"]
        round_got: Counter = Counter()
        for e in current:
            round_got[e.weather] += done[e.episode_id]["rows"]
        need = {}
        for w, q in quota.items():
            missing = q - got[w]
            if missing <= 0 or w in given_up:
                continue
            if round_got[w] == 0 and any(e.weather == w for e in current):
                given_up[w] = missing  # a whole round of this weather delivered no rows
            else:
                need[w] = missing
        if not need or rnd == MAX_ROUNDS:
            given_up.update(need)
            return TownPlan(episodes, True, given_up)
        current = _round_episodes(cfg, town, need, len(episodes), rnd)
        episodes = episodes + current
    raise AssertionError("unreachable")


def _is_done(e: Episode, done: dict) -> bool:
    record = done.get(e.episode_id)
    return record is not None and all(record.get(k) == v for k, v in e.key().items())


def plan(cfg: BuildConfig, done: dict) -> dict[str, TownPlan]:
    quotas = town_quotas(cfg)
    return {t.name: plan_town(cfg, t.name, quotas[t.name], done) for t in cfg.towns}


# --------------------------------------------------------------------------------------------
# Running one episode (in a worker process or a Ray task)

Runner = Callable[..., object]
"""run_episode(spec, sensors, progress) -> EpisodeResult; tests substitute a synthetic one."""

_events = None  # this worker's queue to the main process (progress messages)


def _init_worker(events) -> None:
    global _events
    _events = events
    # Ctrl-C reaches the whole process group; the main process alone decides what stops.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def run_task(
    episode: Episode,
    town: Town,
    out_dir: str,
    sensors: object | None,
    runner: Runner | None = None,
    report: Callable[[str, int], None] | None = None,
) -> dict:
    """Run one episode and write its shard; return its record for the manifest. `runner`
    replaces datagen.episode.run_episode (tests: synthetic tables) and then gets `episode`."""
    if report is None and _events is not None:
        report = lambda eid, k: _events.put(("progress", eid, k))  # noqa: E731
    spec = episode
    if runner is None:
        from datagen import episode as episode_module

        net_path = town.net_path
        if town.builtin and not Path(net_path).exists():  # another machine of a Ray cluster
            from datagen.towns import town_net_path

            net_path = str(town_net_path(town.name))
        spec = episode_module.EpisodeSpec(
            episode_id=episode.episode_id,
            town=episode.town,
            net_path=str(net_path),
            seed=episode.seed,
            weather=episode.weather,
            behaviour=episode.behaviour,
            n_frames=episode.n_frames,
        )
        sensors = sensors if sensors is not None else episode_module.SensorConfig()
        runner = episode_module.run_episode
    progress = (lambda k: report(episode.episode_id, k)) if report else None
    t0, cpu0 = time.perf_counter(), time.process_time()
    result = runner(spec, sensors, progress)
    t1, cpu1 = time.perf_counter(), time.process_time()
    table: pa.Table = result.table
    rows = table.num_rows
    if rows > episode.n_frames:
        raise RuntimeError(f"{episode.episode_id}: {rows} rows for {episode.n_frames} asked")
    record = {
        **episode.key(),
        "round": episode.round,
        "rows": rows,
        "end_reason": result.end_reason if rows < episode.n_frames else None,
        "stats": _deterministic(_jsonable(result.stats or {})),
    }
    path = shards.shard_path(Path(out_dir), episode.town, episode.episode_id)
    record.update(file=None, bytes=0)
    if rows:
        meta = dict(table.schema.metadata or {})
        embedded = {k: v for k, v in record.items() if k not in ("file", "bytes")}
        meta[META_EPISODE_JSON.encode()] = json.dumps(embedded, sort_keys=True).encode()
        record["bytes"] = shards.write_shard(table.replace_schema_metadata(meta), path)
        record["file"] = str(path.relative_to(out_dir))
    t2 = time.perf_counter()
    # cpu_s: this process's CPU time (all threads) in run_episode; below episode_s when the
    # machine is shared, so the two tell contention from cost.
    timing = {"episode_s": t1 - t0, "write_s": t2 - t1, "cpu_s": cpu1 - cpu0}
    for k, v in (result.stats or {}).items():  # per-stage seconds, if the episode reports them
        if isinstance(v, dict) and k.startswith("tim"):
            timing.update({f"{s}_s" if not s.endswith("_s") else s: float(x) for s, x in v.items()})
    run = {
        "pid": os.getpid(),
        "host": os.uname().nodename,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "timing": timing,
    }
    return {**record, "_run": run}


def _deterministic(stats: dict) -> dict:
    """Stats without wall-clock timings (`wall_s`, `timing...`), so that the manifest of a
    resumed build equals that of an uninterrupted one."""
    return {
        k: v
        for k, v in stats.items()
        if not (k.startswith(("wall", "tim")) or k.endswith("wall_s"))
    }


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return _jsonable(dataclasses.asdict(obj))
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    return obj


# --------------------------------------------------------------------------------------------
# Executors: the same three calls for a local process pool and for Ray


class ProcessExecutor:
    """`workers` spawned processes, one libsumo simulation each (libsumo holds one simulation
    per process, so threads would not do)."""

    def __init__(self, workers: int, out_dir: Path, sensors, runner: Runner | None = None):
        # spawn: a fresh interpreter per worker, no inherited libsumo/Embree/thread state.
        ctx = mp.get_context("spawn")
        self.events = ctx.Queue()
        self.pool = ProcessPoolExecutor(
            workers,
            mp_context=ctx,
            initializer=_init_worker,
            initargs=(self.events,),
            max_tasks_per_child=MAX_TASKS_PER_WORKER,
        )
        self.args = (str(out_dir), sensors, runner)
        self.futures: dict = {}

    def submit(self, episode: Episode, town: Town) -> None:
        fut = self.pool.submit(run_task, episode, town, *self.args)
        self.futures[fut] = episode

    def busy(self) -> bool:
        return bool(self.futures)

    def poll(self, timeout: float) -> list[tuple]:
        events = _drain(self.events, timeout)
        for fut in [f for f in self.futures if f.done()]:
            episode = self.futures.pop(fut)
            try:
                events.append(("done", episode.episode_id, fut.result()))
            except BrokenProcessPool:
                raise UserError(
                    f"a worker process died while running episode {episode.episode_id} "
                    "(killed, or out of memory); run the same command again to resume"
                ) from None
            except UserError:
                raise
            except Exception as e:
                _raise_task_error(episode, e)
        return events

    def close(self, cancel: bool = False) -> None:
        if cancel:
            # Stop the running episodes now: their shards are unfinished temporaries, which
            # the next run sweeps away. (shutdown() forgets the processes, so kill them first.)
            terminate = getattr(self.pool, "terminate_workers", None)  # Python >= 3.14
            if terminate:
                terminate()
            else:
                for p in list((self.pool._processes or {}).values()):
                    p.terminate()
        self.pool.shutdown(wait=True, cancel_futures=cancel)
        self.events.close()


def _drain(q, timeout: float) -> list[tuple]:
    events = []
    try:
        events.append(q.get(timeout=timeout))
        while True:
            events.append(q.get_nowait())
    except queue.Empty:
        pass
    return events


def _raise_task_error(episode: Episode, e: BaseException):
    """A failed episode is a bug (not the user's): its traceback for the report, then one line.
    Finished episodes stay; the same command resumes once the bug is fixed."""
    print("".join(traceback.format_exception(e)).rstrip(), file=sys.stderr)
    first = str(e).strip().splitlines()[0] if str(e).strip() else ""
    raise UserError(
        f"episode {episode.episode_id} failed ({type(e).__name__}: {first}; traceback above); "
        "finished episodes are kept"
    ) from None


class RayExecutor:
    """Episodes as Ray tasks (one CPU each) on a local Ray instance or an existing cluster
    (`address`). Every node must have this package installed and see `out_dir` at the same path
    (a shared filesystem); progress comes back through a small actor."""

    def __init__(self, address: str | None, workers: int, out_dir: Path, sensors, runner=None):
        try:
            import ray
        except ImportError:
            raise UserError(
                "--executor ray needs Ray: pip install 'iidsu[ray]' (or pip install 'ray>=2.9')"
            ) from None
        self.ray = ray
        self.started = not ray.is_initialized()
        if self.started:
            kwargs = {"include_dashboard": False, "logging_level": "WARNING"}
            if address:
                kwargs["address"] = address
            else:
                kwargs["num_cpus"] = workers
            try:
                ray.init(**kwargs)
            except (ConnectionError, RuntimeError, ValueError) as e:
                where = address or "a local instance"
                raise UserError(f"cannot start Ray on {where}: {str(e).splitlines()[0]}") from None

        @ray.remote
        class Progress:
            def __init__(self):
                self.events = []

            def add(self, eid, k):
                self.events.append(("progress", eid, k))

            def drain(self):
                events, self.events = self.events, []
                return events

        self.progress = Progress.remote()
        self.task = ray.remote(num_cpus=1, max_calls=MAX_TASKS_PER_WORKER)(_ray_task)
        self.args = (str(out_dir), sensors, runner)
        self.refs: dict = {}

    def submit(self, episode: Episode, town: Town) -> None:
        ref = self.task.remote(episode, town, *self.args, self.progress)
        self.refs[ref] = episode

    def busy(self) -> bool:
        return bool(self.refs)

    def poll(self, timeout: float) -> list[tuple]:
        ray = self.ray
        ready, _ = ray.wait(list(self.refs), num_returns=len(self.refs), timeout=timeout)
        events = ray.get(self.progress.drain.remote())
        for ref in ready:
            episode = self.refs.pop(ref)
            try:
                events.append(("done", episode.episode_id, ray.get(ref)))
            except ray.exceptions.RayTaskError as e:
                cause = e.as_instanceof_cause()
                if isinstance(cause, UserError):
                    raise UserError(str(cause).splitlines()[-1]) from None
                _raise_task_error(episode, cause)
            except ray.exceptions.RayError as e:
                raise UserError(
                    f"Ray lost episode {episode.episode_id}: {str(e).splitlines()[0]}; "
                    "run the same command again to resume"
                ) from None
        return events

    def close(self, cancel: bool = False) -> None:
        if cancel:
            for ref in self.refs:
                self.ray.cancel(ref, force=True)
        if self.started:
            self.ray.shutdown()


def _ray_task(episode, town, out_dir, sensors, runner, progress_actor):
    def report(eid, k):
        progress_actor.add.remote(eid, k)

    return run_task(episode, town, out_dir, sensors, runner, report)


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
    """(path, file metadata, {} if unreadable, None if not an iidsu shard) for every *.parquet
    directly in `out_dir` or one of its subdirectories (the layout datagen writes)."""
    for path in sorted([*out_dir.glob("*.parquet"), *out_dir.glob("*/*.parquet")]):
        if path.name.startswith(("_", ".")) or path.parent.name.startswith(("_", ".")):
            continue
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
            record = done.get(e.episode_id) if _is_done(e, done) else None
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


# --------------------------------------------------------------------------------------------
# The build


@dataclass
class BuildReport:
    """What `build` returns: the manifest and figures of this run (for the summary and bench)."""

    manifest: dict
    new_frames: int = 0
    elapsed_s: float = 0.0
    stage_s: dict = field(default_factory=dict)
    peak_rss_mb: dict = field(default_factory=dict)


def build(
    cfg: BuildConfig,
    out_dir: Path,
    *,
    workers: int | None = None,
    force: bool = False,
    executor: str = "process",
    ray_address: str | None = None,
    runner: Runner | None = None,
    progress_bar: bool = True,
) -> BuildReport:
    """Build (or resume) the dataset of `cfg` in `out_dir`; see the module docstring."""
    out_dir = Path(out_dir)
    shards.check_writable(out_dir)
    with BuildLock(out_dir):
        return _build(
            cfg,
            out_dir,
            workers or available_cores(),
            force,
            executor,
            ray_address,
            runner,
            progress_bar,
        )


def _build(cfg, out_dir, workers, force, executor, ray_address, runner, progress_bar):
    from tqdm import tqdm

    done = prepare_output(out_dir, cfg, force)
    towns = {t.name: t for t in cfg.towns}
    run = {"executor": executor, "workers": workers, "started_unix": time.time()}
    plans = plan(cfg, done)
    shards.write_json(make_manifest(cfg, plans, done, run), out_dir / MANIFEST)

    start = time.perf_counter()
    report = BuildReport(manifest={})
    stage: Counter = Counter()
    credited: dict[str, int] = {}  # frames shown on the bar per running episode
    asked: dict[str, int] = {}
    if executor == "ray":
        pool = RayExecutor(ray_address, workers, out_dir, cfg.sensors, runner)
    else:
        pool = ProcessExecutor(workers, out_dir, cfg.sensors, runner)
    bar = tqdm(
        total=cfg.frames,
        initial=sum(r["rows"] for r in done.values()),
        unit="frame",
        desc="build",
        dynamic_ncols=True,
        mininterval=0.5 if sys.stderr.isatty() else 5.0,
        smoothing=0.05,
        disable=not progress_bar,
    )
    submitted: set[str] = set()
    interrupted = False
    try:
        while True:
            for town_name, town_plan in plans.items():
                for e in town_plan.episodes:
                    if e.episode_id not in submitted and not _is_done(e, done):
                        pool.submit(e, towns[town_name])
                        submitted.add(e.episode_id)
                        credited[e.episode_id] = 0
                        asked[e.episode_id] = e.n_frames
            if not pool.busy():
                break
            for kind, eid, payload in pool.poll(timeout=0.2):
                if kind == "progress" and eid in credited:
                    # recorded states, capped at the rows asked (the last few states only give
                    # the future of earlier frames); corrected to the real rows when done.
                    add = max(0, min(payload, asked[eid] - credited[eid]))
                    credited[eid] += add
                    bar.update(add)
                elif kind == "done":
                    record = payload
                    bar.update(record["rows"] - credited.pop(eid, 0))
                    run_info = record.pop("_run")
                    for k, v in run_info["timing"].items():
                        stage[k] += v
                    key = f"{run_info['host']}:{run_info['pid']}"
                    report.peak_rss_mb[key] = max(
                        report.peak_rss_mb.get(key, 0.0), run_info["peak_rss_mb"]
                    )
                    report.new_frames += record["rows"]
                    done[eid] = {**record, "status": "done"}
                    plans = plan(cfg, done)
                    run["elapsed_s"] = time.perf_counter() - start
                    shards.write_json(make_manifest(cfg, plans, done, run), out_dir / MANIFEST)
    except KeyboardInterrupt:
        interrupted = True
        raise
    finally:
        bar.close()
        pool.close(cancel=interrupted or pool.busy())
        if interrupted:
            n_done = sum(r["rows"] for r in done.values())
            print(
                f"datagen build: stopped with {n_done} of {cfg.frames} frames done; "
                "run the same command again to resume",
                file=sys.stderr,
            )
    report.elapsed_s = time.perf_counter() - start
    run.update(
        elapsed_s=report.elapsed_s,
        new_frames=report.new_frames,
        frames_per_s=report.new_frames / report.elapsed_s if report.elapsed_s else 0.0,
        stage_s=dict(stage),
        peak_rss_mb=report.peak_rss_mb,
    )
    report.manifest = make_manifest(cfg, plans, done, run)
    shards.write_json(report.manifest, out_dir / MANIFEST)
    report.stage_s = dict(stage)
    return report


# --------------------------------------------------------------------------------------------
# Summary


def summary(report: BuildReport) -> str:
    m = report.manifest
    s = m["statistics"]
    towns = [t["name"] for t in m["towns"]]
    weathers = [w for w in schemas.WEATHERS if s["frames_by_weather"].get(w)]
    width = max([len(t) for t in towns] + [8])
    lines = [
        f"{'town':<{width}} " + " ".join(f"{w:>8}" for w in weathers) + f" {'total':>8}",
    ]
    for t in towns:
        cells = [s["frames_by_town_weather"].get(f"{t}/{w}", 0) for w in weathers]
        lines.append(f"{t:<{width}} " + " ".join(f"{c:>8}" for c in cells) + f" {sum(cells):>8}")
    lines.append(
        f"{'total':<{width}} "
        + " ".join(f"{s['frames_by_weather'].get(w, 0):>8}" for w in weathers)
        + f" {s['frames']:>8}"
    )
    behaviours = ", ".join(f"{b} {n}" for b, n in sorted(s["frames_by_behaviour"].items()))
    lines.append(f"frames by behaviour: {behaviours or '-'}")
    totals = s["stats_totals"]
    shown = [k for k in SUMMARY_COUNTS if k in totals] or ["collisions"]
    lines.append(
        f"episodes: {s['episodes']}; "
        + "; ".join(f"{k.replace('_', ' ')}: {totals.get(k, 0)}" for k in shown)
    )
    ended = ", ".join(f"{r} {n}" for r, n in sorted(s["episodes_ended_early"].items()))
    lines.append(f"episodes ended early: {ended or 'none'}")
    if s["shortfall"]:
        lines.append(f"frames given up (episodes could not deliver them): {s['shortfall']}")
    per_frame = s["bytes"] / s["frames"] if s["frames"] else 0
    lines.append(
        f"{s['bytes'] / 1e9:.2f} GB, {per_frame / 1e3:.1f} KB/frame; this run: "
        f"{report.new_frames} new frames in {report.elapsed_s:.0f} s "
        f"({report.new_frames / max(report.elapsed_s, 1e-9):.1f} frames/s)"
    )
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Command line


def add_arguments(p: argparse.ArgumentParser) -> None:
    where = p.add_argument_group("towns (default: all built-in towns)")
    where.add_argument("--towns", type=int, metavar="N", help="the first N built-in towns")
    where.add_argument(
        "--town", action="append", default=[], metavar="NAME", help="a built-in town (repeatable)"
    )
    where.add_argument(
        "--net",
        action="append",
        default=[],
        metavar="FILE",
        help="a SUMO network .net.xml[.gz], named by its stem (repeatable)",
    )
    p.add_argument(
        "--frames", type=int, default=PAPER_FRAMES, help="frames in total (default: %(default)s)"
    )
    p.add_argument("--seed", type=int, default=0, help="the build's seed (default: 0)")
    p.add_argument("--out", type=Path, default=Path("data/shards"), help="output dir (%(default)s)")
    p.add_argument(
        "--workers", type=int, default=None, help="parallel episodes (default: all cores)"
    )
    p.add_argument(
        "--episode-seconds",
        type=float,
        default=EPISODE_SECONDS,
        help="driving time per episode (default: %(default)s)",
    )
    p.add_argument(
        "--weather-mix",
        default=None,
        metavar="W=X,...",
        help="relative weather frequencies, e.g. sunny=2,foggy=1 (default: uniform)",
    )
    p.add_argument(
        "--sensor",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override a SensorConfig field, e.g. --sensor jpeg_quality=80 (repeatable)",
    )
    p.add_argument(
        "--force", action="store_true", help="replace an existing dataset in --out (any args)"
    )
    p.add_argument(
        "--executor",
        choices=("process", "ray"),
        default="process",
        help="run episodes in local processes (default) or as Ray tasks",
    )
    p.add_argument(
        "--ray-address", default=None, help="an existing Ray cluster (default: start a local one)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def parse_weather_mix(text: str | None) -> tuple[tuple[str, float], ...] | None:
    if not text:
        return None
    mix = {}
    for part in text.split(","):
        name, sep, value = part.strip().partition("=")
        if name not in schemas.WEATHERS:
            raise UserError(f"--weather-mix: unknown weather {name!r} (one of {schemas.WEATHERS})")
        try:
            mix[name] = float(value) if sep else 1.0
        except ValueError:
            raise UserError(f"--weather-mix: {part!r} is not WEATHER=NUMBER") from None
        if not math.isfinite(mix[name]) or mix[name] < 0:
            raise UserError(f"--weather-mix: weight of {name} must be >= 0")
    if sum(mix.values()) <= 0:
        raise UserError("--weather-mix: at least one weight must be positive")
    return tuple((w, mix[w]) for w in schemas.WEATHERS if w in mix)


def parse_sensors(overrides: list[str]):
    """SensorConfig with `FIELD=VALUE` overrides (dotted FIELD for nested configs)."""
    from datagen.episode import SensorConfig

    sensors = SensorConfig()
    for item in overrides:
        name, sep, value = item.partition("=")
        if not sep:
            raise UserError(f"--sensor {item!r}: expected FIELD=VALUE")
        sensors = _replace_path(sensors, name.split("."), value, item)
    return sensors


def _replace_path(obj, path: list[str], value: str, item: str):
    fields = {f.name: f for f in dataclasses.fields(obj)} if dataclasses.is_dataclass(obj) else {}
    if path[0] not in fields:
        raise UserError(f"--sensor {item!r}: no field {path[0]!r} (fields: {', '.join(fields)})")
    current = getattr(obj, path[0])
    if len(path) > 1:
        return dataclasses.replace(obj, **{path[0]: _replace_path(current, path[1:], value, item)})
    try:
        if isinstance(current, bool):
            new = {"true": True, "false": False, "1": True, "0": False}[value.lower()]
        elif isinstance(current, int | float):
            new = type(current)(value)
        elif isinstance(current, str) or current is None:
            new = value
        else:
            new = type(current)(json.loads(value))
    except (KeyError, ValueError, TypeError):
        raise UserError(f"--sensor {item!r}: cannot read {value!r} for {path[0]}") from None
    return dataclasses.replace(obj, **{path[0]: new})


def resolve_towns(args) -> tuple[Town, ...]:
    from datagen import towns as towns_module

    if args.towns is not None and (args.town or args.net):
        raise UserError("--towns N cannot be combined with --town or --net")
    names: list[str] = list(args.town)
    if args.towns is not None:
        if not 1 <= args.towns <= len(towns_module.TOWN_NAMES):
            raise UserError(
                f"--towns must be between 1 and {len(towns_module.TOWN_NAMES)}, got {args.towns}"
            )
        names = list(towns_module.TOWN_NAMES[: args.towns])
    elif not args.town and not args.net:
        names = list(towns_module.TOWN_NAMES)
    result: list[Town] = []
    for name in names:
        if name not in towns_module.TOWN_NAMES:
            raise UserError(
                f"unknown town {name!r}; built-in towns: {', '.join(towns_module.TOWN_NAMES)}"
            )
        path = towns_module.town_net_path(name)
        result.append(Town(name, str(path), towns_module.network_sha256(path), True))
    for net in args.net:
        path = Path(net)
        if not path.is_file():
            raise UserError(f"--net {net}: no such file")
        path = towns_module.check_network(path).resolve()
        stem = path.name
        for suffix in (".gz", ".xml", ".net"):
            stem = stem.removesuffix(suffix)
        result.append(Town(stem, str(path), towns_module.network_sha256(path), False))
    seen: set[str] = set()
    for t in result:
        if t.name in seen:
            raise UserError(f"town {t.name!r} is given twice (a --net file's stem names its town)")
        if t.name.startswith(("_", ".")) or "/" in t.name:
            raise UserError(f"--net {t.net_path}: its name must not start with '_' or '.'")
        seen.add(t.name)
    return tuple(result)


def config_from_args(args) -> BuildConfig:
    if args.frames < 1:
        raise UserError(f"--frames must be at least 1, got {args.frames}")
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be at least 1, got {args.workers}")
    if not (math.isfinite(args.episode_seconds) and args.episode_seconds >= 0.5):
        raise UserError(f"--episode-seconds must be at least 0.5, got {args.episode_seconds}")
    mix = parse_weather_mix(args.weather_mix)
    sensors = parse_sensors(args.sensor)
    return BuildConfig(
        towns=resolve_towns(args),
        frames=args.frames,
        seed=args.seed,
        episode_seconds=args.episode_seconds,
        weather_mix=mix,
        sensors=sensors,
    )


def run(args) -> int:
    cfg = config_from_args(args)
    report = build(
        cfg,
        args.out,
        workers=args.workers,
        force=args.force,
        executor=args.executor,
        ray_address=args.ray_address,
        progress_bar=not args.no_progress,
    )
    print(summary(report))
    if report.manifest["status"] != "complete":
        print("datagen build: the dataset is incomplete (see above)", file=sys.stderr)
        return 1
    return 0
