"""Executors: run episodes in parallel, in local worker processes or as Ray tasks."""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import queue
import resource
import signal
import sys
import time
import traceback
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import pyarrow as pa

from datagen import shards
from datagen.errors import UserError
from datagen.manifest import META_EPISODE_JSON
from datagen.plan import Episode, Town, jsonable

MAX_TASKS_PER_WORKER = 50
"""Episodes a worker process runs before it is replaced: bounds slow leaks (libsumo, Embree)
without paying a process start (imports, scene caches) for every episode."""


def available_cores() -> int:
    """Cores this process may run on (taskset / cgroup CPU sets respected)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


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
