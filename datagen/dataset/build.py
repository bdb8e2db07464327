"""`datagen build`: the dataset, as parallel, resumable, crash-safe Parquet shards.

    datagen build --towns 8 --frames 146000            # paper scale (Sec. IV: 146k frames, 8 towns)
    datagen build --town grid_small --town spider --frames 2000 --workers 2 --out data/
    datagen build --net my_city.net.xml --frames 5000 --weather-mix sunny=3,foggy=1
    datagen build ... --executor ray [--ray-address ray://head:10001]

The plan (which episodes, from the arguments alone) is datagen/dataset/plan.py; the executors (local
processes or Ray) datagen/dataset/executors.py; the manifest, lock and resume datagen/dataset/manifest.py. This
module runs the loop: plan, submit what is not done, record each finished episode, re-plan.
Because each episode's content is a function of its spec and each top-up round a function of the
previous rounds' row counts, the dataset is the same however the work was scheduled or
interrupted; running the same command again resumes.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pyarrow as pa

import schemas
from datagen.dataset import executors, shards
from datagen.dataset.manifest import (
    MANIFEST,
    META_EPISODE_JSON,
    BuildLock,
    make_manifest,
    prepare_output,
)
from datagen.dataset.plan import (
    EPISODE_SECONDS,
    PAPER_FRAMES,
    BuildConfig,
    Episode,
    Town,
    is_done,
    jsonable,
    plan,
)
from datagen.errors import UserError
from datagen.sensors.overrides import parse_sensors
from schemas import outputs
from schemas.errors import Stopped

HELP = "generate the dataset: driving episodes across towns and weathers, as Parquet shards"
SUMMARY_COUNTS = (
    "collisions",  # the ego's (simulation.py counts SUMO's collision checks, junctions included)
    "other_collisions",
    "red_light_violations",
    "teleports",
    "hard_brakes",
    "reroutes",
)
RESUME = "run the same command again to resume"
MANIFEST_EVERY_S = 2.0
"""The manifest is rewritten at most this often while building (and always at the end and on a
stop): every shard carries its own record, so a build killed in between loses nothing (resume
adopts the shards), and a build of many short episodes does not spend its time writing JSON."""

Runner = Callable[..., object]
"""run_episode(spec, sensors, progress) -> EpisodeResult; tests substitute a synthetic one."""


# --------------------------------------------------------------------------------------------
# One episode, as an executor task (in a worker process or a Ray task)


def episode_task(
    job: tuple[Episode, Town],
    progress: Callable[[int], None],
    *,
    out_dir: str,
    sensors: object | None,
    runner: Runner | None = None,
) -> dict:
    """Run one episode and write its shard; return its record for the manifest. `runner`
    replaces datagen.episode.run_episode (tests: synthetic tables) and then gets the Episode."""
    episode, town = job
    spec = episode
    if runner is None:
        from datagen import episode as episode_module
        from datagen.sensors.config import SensorConfig

        net_path = town.net_path
        if town.builtin and not Path(net_path).exists():  # another machine of a Ray cluster
            from datagen.world.towns import town_net_path

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
        sensors = sensors if sensors is not None else SensorConfig()
        runner = episode_module.run_episode
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
        "stats": _deterministic(jsonable(result.stats or {})),
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
    return {**record, "_timing": timing}


def _deterministic(stats: dict) -> dict:
    """Stats without wall-clock timings (`wall_s`, `timing...`), so that the manifest of a
    resumed build equals that of an uninterrupted one."""
    return {
        k: v
        for k, v in stats.items()
        if not (k.startswith(("wall", "tim")) or k.endswith("wall_s"))
    }


# --------------------------------------------------------------------------------------------
# The build


@dataclass
class BuildReport:
    """What `build` returns: the manifest and figures of this run (for the summary and bench).

    Attributes:
        peak_rss_mb: {"host:pid": peak resident MB} of every worker process that ran an episode.
        episode_log: (seconds since start, episode id, rows, worker, its peak RSS in MB) of each
            episode this run finished, in finishing order (bench/soak.py).
    """

    manifest: dict
    new_frames: int = 0
    elapsed_s: float = 0.0
    stage_s: dict = field(default_factory=dict)
    peak_rss_mb: dict = field(default_factory=dict)
    episode_log: list = field(default_factory=list)


@dataclass(frozen=True)
class RunOptions:
    """How a build runs; none of it changes the dataset.

    Attributes:
        workers: episodes at once (default: all cores).
        executor: "process" (local worker processes) or "ray".
        ray_address: an existing Ray cluster; None starts a local instance.
        retries: further attempts of an episode whose worker died.
        stall_s: watchdog, seconds without progress; None = adaptive (datagen/dataset/executors.py).
        max_episodes_per_worker: episodes before a worker process is replaced; None = never.
    """

    workers: int | None = None
    executor: str = "process"
    ray_address: str | None = None
    retries: int = executors.RETRIES
    stall_s: float | None = None
    max_episodes_per_worker: int | None = executors.MAX_TASKS_PER_WORKER


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
    options: RunOptions | None = None,
) -> BuildReport:
    """Build (or resume) the dataset of `cfg` in `out_dir`; see the module docstring.
    `workers`, `executor` and `ray_address` are shorthands for the fields of `options`."""
    options = options or RunOptions(workers=workers, executor=executor, ray_address=ray_address)
    options = dataclasses.replace(options, workers=options.workers or executors.available_cores())
    out_dir = Path(out_dir)
    shards.check_writable(out_dir)
    with BuildLock(out_dir), executors.stop_on_sigterm():
        return _build(cfg, out_dir, options, force, runner, progress_bar)


def _build(cfg, out_dir, options: RunOptions, force, runner, progress_bar) -> BuildReport:
    from tqdm import tqdm

    done = prepare_output(out_dir, cfg, force)
    towns = {t.name: t for t in cfg.towns}
    run = {"executor": options.executor, "workers": options.workers, "started_unix": time.time()}
    plans = plan(cfg, done)
    shards.write_json(make_manifest(cfg, plans, done, run), out_dir / MANIFEST)

    start = time.perf_counter()
    report = BuildReport(manifest={})
    stage: Counter = Counter()
    credited: dict[str, int] = {}  # frames shown on the bar per running episode
    asked: dict[str, int] = {}
    task = functools.partial(episode_task, out_dir=str(out_dir), sensors=cfg.sensors, runner=runner)
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
    written = time.monotonic()  # when the manifest was last written
    try:
        pool = executors.make(
            options.executor,
            task,
            workers=options.workers,
            ray_address=options.ray_address,
            retries=options.retries,
            stall_s=options.stall_s,
            max_tasks_per_worker=options.max_episodes_per_worker,
            noun="episode",
        )
        with pool:
            while True:
                for town_name, town_plan in plans.items():
                    for e in town_plan.episodes:
                        if e.episode_id not in submitted and not is_done(e, done):
                            pool.submit(e.episode_id, (e, towns[town_name]))
                            submitted.add(e.episode_id)
                            credited[e.episode_id] = 0
                            asked[e.episode_id] = e.n_frames
                if not pool.pending():
                    break
                for ev in pool.events(timeout_s=0.5):
                    eid = ev.key
                    if isinstance(ev, executors.Progress):
                        # recorded states, capped at the rows asked (the last few states only
                        # give the future of earlier frames); corrected to the real rows when
                        # done. A retried episode counts again from 0: the cap still holds.
                        add = max(0, min(ev.amount, asked[eid] - credited[eid]))
                        credited[eid] += add
                        bar.update(add)
                        continue
                    record = dict(ev.result)
                    bar.update(record["rows"] - credited.pop(eid, 0))
                    for k, v in record.pop("_timing").items():
                        stage[k] += v
                    report.peak_rss_mb[ev.worker] = max(
                        report.peak_rss_mb.get(ev.worker, 0.0), ev.peak_rss_mb
                    )
                    report.new_frames += record["rows"]
                    report.episode_log.append(
                        (
                            time.perf_counter() - start,
                            eid,
                            record["rows"],
                            ev.worker,
                            ev.peak_rss_mb,
                        )
                    )
                    done[eid] = {**record, "status": "done"}
                    plans = plan(cfg, done)
                    if time.monotonic() - written >= MANIFEST_EVERY_S:
                        run["elapsed_s"] = time.perf_counter() - start
                        shards.write_json(make_manifest(cfg, plans, done, run), out_dir / MANIFEST)
                        written = time.monotonic()
    except (KeyboardInterrupt, executors.ExecutorError) as e:
        bar.close()
        run["elapsed_s"] = time.perf_counter() - start
        shards.write_json(make_manifest(cfg, plans, done, run), out_dir / MANIFEST)
        shards.remove_temporaries(out_dir)  # the stopped workers' unfinished shards
        n_done = sum(r["rows"] for r in done.values())
        sigterm = isinstance(e, executors.Terminated) or executors.sigterm_received()
        what = "stopped (SIGTERM)" if sigterm else "stopped"
        if isinstance(e, executors.ExecutorError):
            raise type(e)(
                f"{e}; stopped with {n_done} of {cfg.frames} frames done; {RESUME}", e.keys
            ) from None
        # the runner (schemas/cli.py) prints it as `datagen build: ...`, exit 143 or 130
        raise Stopped(
            f"{what} with {n_done} of {cfg.frames} frames done; {RESUME}", sigterm
        ) from None
    finally:
        bar.close()
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
    p.add_argument("--out", type=Path, default=Path("data/shards"), help="dataset directory")
    p.add_argument(
        "--workers", type=int, default=None, help="parallel episodes (default: all cores)"
    )
    p.add_argument(
        "--episode-seconds",
        type=float,
        default=EPISODE_SECONDS,
        help="simulated driving time per episode, s (default: %(default)s)",
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
        help="override a SensorConfig field (datagen/sensors/config.py; nested: camera.crop_px=128 "
        'or camera={"crop_px": 128}), e.g. --sensor jpeg_quality=80, or --sensor '
        "raycaster=trimesh to cast rays with trimesh.ray (portable, slower) (repeatable; "
        "default: the paper's sensors)",
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
    p.add_argument(
        "--retries",
        type=int,
        default=executors.RETRIES,
        help="further attempts of an episode whose worker died (default: %(default)s)",
    )
    p.add_argument(
        "--stall-timeout",
        type=float,
        default=None,
        metavar="SECONDS",
        help="stop when an episode reports no progress for this long (default: 10x the slowest "
        f"episode so far, at least {executors.STALL_FLOOR_S:.0f} s)",
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


def resolve_towns(args) -> tuple[Town, ...]:
    from datagen.world import towns as towns_module

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
        if name in towns_module.HELD_OUT_TOWNS:
            raise UserError(
                f"town {name!r} is the held-out town (`drive eval` on drive/routes/heldout_*.json"
                f" drives it); it is never built into a dataset. Built-in towns: "
                f"{', '.join(towns_module.TOWN_NAMES)}"
            )
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
        held = towns_module.held_out_town_of(path)
        if held is not None:  # its sha256 is the held-out town's: never train on it
            raise UserError(f"--net {net}: this is the network of the held-out town {held!r}")
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


def options_from_args(args) -> RunOptions:
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be at least 1, got {args.workers}")
    if args.retries < 0:
        raise UserError(f"--retries must be at least 0, got {args.retries}")
    stall = args.stall_timeout
    if stall is not None and not (math.isfinite(stall) and stall > 0):
        raise UserError(f"--stall-timeout must be a positive number of seconds, got {stall}")
    return RunOptions(
        workers=args.workers,
        executor=args.executor,
        ray_address=args.ray_address,
        retries=args.retries,
        stall_s=stall,
    )


def run(args) -> int:
    cfg = config_from_args(args)
    options = options_from_args(args)
    outputs.check_dir(args.out)
    report = build(
        cfg, args.out, force=args.force, progress_bar=not args.no_progress, options=options
    )
    print(summary(report))
    if report.manifest["status"] != "complete":
        print("datagen build: the dataset is incomplete (see above)", file=sys.stderr)
        return 1
    return 0
