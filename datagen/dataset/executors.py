"""Executors: map a picklable task function over keyed tasks, on local processes or on Ray.

Every command that runs work in parallel (`datagen build`, `datagen validate`, `drive eval`) uses
these, so each behaves the same way:

- results come back as tasks finish (`Done`), with `Progress` heartbeats from running tasks;
- a worker that dies (segfault, OOM kill, `kill -9`) is detected and its task run again, at most
  `retries` more times; then the run stops with `TaskLost` naming the task;
- a task that reports no progress for `stall_s` seconds stops the run with `Stalled` naming it
  (default: 10x the slowest task so far, at least STALL_FLOOR_S);
- a task that raises stops the run with `TaskFailed` (its traceback is printed first); a
  `UserError` raised by a task reaches the caller as that UserError;
- processes are recycled after `max_tasks_per_worker` tasks (bounding slow leaks of libsumo and
  Embree) by the supervisor itself, which starts the replacement: recycling cannot deadlock;
- `stop_on_sigterm()` turns SIGTERM (batch schedulers, `timeout`) into KeyboardInterrupt, and
  leaving the executor by an exception stops every worker at once.

A task function takes its payload and a progress callback (`progress(n)`: n units of work done;
`progress(0)` is a bare heartbeat) and returns a picklable result. It must be importable by name
(a module-level function, or a functools.partial of one), since workers are fresh interpreters:

    from datagen.dataset import executors

    def score_route(route, progress):          # a module-level function
        ...; progress(1); ...
        return {"route": route.name, "score": 0.9}

    with executors.stop_on_sigterm(), executors.make("process", score_route, workers=2) as ex:
        for done in ex.map((r.name, r) for r in routes):   # yields Done as tasks finish
            print(done.key, done.result, done.worker, done.peak_rss_mb)

`map` submits everything at once; a caller whose tasks depend on earlier results (the build's
top-up rounds) uses `submit(key, payload)` and `events(timeout_s)` directly (datagen/dataset/build.py).
Which task runs where and when never changes a result, so output that is a function of the
results alone (the build's shards and manifest) is the same for any executor and worker count.

Size: ~630 lines: the interface and its two implementations (local processes, Ray), whose
failure handling must agree case by case, are read together.
"""

from __future__ import annotations

import os
import resource
import signal
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

from datagen.errors import UserError
from schemas.cli import sigterm_received, stop_on_sigterm  # noqa: F401  (re-exported)
from schemas.errors import Terminated  # noqa: F401  (re-exported)

TaskFn = Callable[[object, Callable[[int], None]], object]
"""fn(payload, progress) -> result; payload and result picklable, fn importable by name."""

MAX_TASKS_PER_WORKER = 50
"""Tasks a worker process runs before the supervisor replaces it: bounds slow leaks (libsumo,
Embree) without paying a process start (imports, scene caches) for every task. Insurance more
than need: `bench/soak.py --episodes 240 --recycle 0` measured a build worker's peak RSS going
from 336 MB after its first episode to 374 MB after ~120 (about 31 MB per 100 episodes)."""
RETRIES = 2
"""Further attempts for a task whose worker died (a crash, an OOM kill); a task that raises is not
retried: the same task would raise again."""
STALL_FACTOR = 10.0
STALL_FLOOR_S = 300.0
"""Default watchdog: a running task that reports no progress for max(STALL_FLOOR_S,
STALL_FACTOR x the slowest task so far) seconds is stuck. Generous on purpose: a false alarm
costs a rerun, a missed hang costs nothing but time."""


def available_cores() -> int:
    """Cores this process may run on (taskset / cgroup CPU sets respected)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


# --------------------------------------------------------------------------------------------
# Events and errors


@dataclass(frozen=True)
class Progress:
    """A running task reported `amount` units of work done (0: a heartbeat)."""

    key: str
    amount: int


@dataclass(frozen=True)
class Done:
    """A finished task: its result, the worker that ran it ("host:pid"), that worker's peak
    resident memory so far (MB, ru_maxrss) and how many times the task was started."""

    key: str
    result: object
    worker: str
    peak_rss_mb: float
    attempts: int = 1


class ExecutorError(UserError):
    """The run stopped: a task failed, was lost or stalled. `keys` names the task(s)."""

    def __init__(self, message: str, keys: tuple[str, ...] = ()):
        super().__init__(message)
        self.keys = keys


class TaskFailed(ExecutorError):
    """The task function raised; `traceback` is the worker's, already printed to stderr."""

    def __init__(self, message: str, keys: tuple[str, ...], traceback_text: str = ""):
        super().__init__(message, keys)
        self.traceback = traceback_text


class TaskLost(ExecutorError):
    """The task's worker died on every attempt (killed, out of memory, a crash)."""


class Stalled(ExecutorError):
    """No progress from the task(s) for longer than the watchdog allows."""


def _failed(noun: str, key: str, exc_type: str, message: str, tb: str) -> TaskFailed:
    """A failed task is a bug (not the user's): its traceback for the report, then one line."""
    if tb:
        print(tb.rstrip(), file=sys.stderr)
    first = message.strip().splitlines()[0] if message.strip() else ""
    where = "; traceback above" if tb else ""
    return TaskFailed(f"{noun} {key} failed ({exc_type}: {first}{where})", (key,), tb)


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KB on Linux


# --------------------------------------------------------------------------------------------
# The common part: task bookkeeping and the watchdog


class Executor:
    """Runs `fn(payload, progress)` for each submitted (key, payload). Subclasses start the work;
    this class keeps the queue, the attempts and the watchdog.

    Args:
        fn: the task function (see the module docstring).
        workers: tasks run at once.
        retries: further attempts for a task whose worker died.
        stall_s: watchdog limit in seconds; None: adaptive (STALL_FACTOR, STALL_FLOOR_S).
        max_tasks_per_worker: tasks before a worker process is replaced; None: never.
        noun: what a task is, in messages ("episode", "shard", "route").
        on_lost: `on_lost(key, message)` is the result of a task whose worker died on every
            attempt, yielded as its Done (drive eval records such a route as failed and goes
            on, as the leaderboard records a crashed route); None: TaskLost stops the run.
    """

    def __init__(
        self,
        fn: TaskFn,
        *,
        workers: int,
        retries: int = RETRIES,
        stall_s: float | None = None,
        max_tasks_per_worker: int | None = MAX_TASKS_PER_WORKER,
        noun: str = "task",
        on_lost: Callable[[str, str], object] | None = None,
    ):
        if workers < 1:
            raise UserError(f"workers must be at least 1, got {workers}")
        self.fn = fn
        self.workers = workers
        self.retries = retries
        self.stall_s = stall_s
        self.max_tasks_per_worker = max_tasks_per_worker
        self.noun = noun
        self.on_lost = on_lost
        self._lost: list[Done] = []  # tasks given up with on_lost, to yield as done
        self._payloads: dict[str, object] = {}  # submitted and not finished
        self._attempts: dict[str, int] = {}
        self._last_seen: dict[str, float] = {}  # running task -> monotonic time of its last event
        self._started: dict[str, float] = {}
        self._slowest_s = 0.0
        self._last_event = time.monotonic()

    # The caller's interface -----------------------------------------------------------------

    def submit(self, key: str, payload: object) -> None:
        """Queue one task; `key` (unique among unfinished tasks) names it in events and errors."""
        if key in self._payloads:
            raise ValueError(f"{self.noun} {key} is already submitted")
        if not self._payloads:  # the idle clock starts with the first waiting task
            self._last_event = time.monotonic()
        self._payloads[key] = payload
        self._attempts[key] = 0
        self._enqueue(key, payload)

    def pending(self) -> int:
        """Tasks submitted and not finished."""
        return len(self._payloads)

    def events(self, timeout_s: float) -> list[Progress | Done]:
        """Wait up to `timeout_s` for events; raises ExecutorError when the run must stop."""
        if not self._payloads:
            return []
        events = self._poll(timeout_s)
        events, self._lost = events + self._lost, []
        now = time.monotonic()
        for ev in events:
            self._last_event = now
            if isinstance(ev, Done):
                self._payloads.pop(ev.key, None)
                self._last_seen.pop(ev.key, None)
                self._slowest_s = max(self._slowest_s, now - self._started.pop(ev.key, now))
            elif ev.key in self._last_seen:
                self._last_seen[ev.key] = now
        self._watchdog(now)
        return events

    def map(self, tasks: Iterable[tuple[str, object]], timeout_s: float = 0.5) -> Iterator[Done]:
        """Submit every (key, payload) and yield each Done as it comes (in finishing order)."""
        for key, payload in tasks:
            self.submit(key, payload)
        while self.pending():
            for ev in self.events(timeout_s):
                if isinstance(ev, Done):
                    yield ev

    def close(self, cancel: bool = False) -> None:
        """Stop the workers: at once (`cancel`, running tasks are lost) or when idle."""
        raise NotImplementedError

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(cancel=exc_type is not None or bool(self._payloads))

    # For the subclasses ---------------------------------------------------------------------

    def _enqueue(self, key: str, payload: object) -> None:
        raise NotImplementedError

    def _poll(self, timeout_s: float) -> list[Progress | Done]:
        raise NotImplementedError

    def _task_started(self, key: str, attempt: bool = True) -> None:
        """An attempt of `key` began running: count it (unless counted when it was handed to a
        worker) and start its watchdog clock."""
        now = time.monotonic()
        if attempt:
            self._attempts[key] += 1
        self._started[key] = self._last_seen[key] = self._last_event = now

    def _task_lost(self, key: str, why: str) -> bool:
        """The worker running `key` died: True if it may run again, else raise TaskLost."""
        self._last_seen.pop(key, None)
        self._started.pop(key, None)
        attempts = self._attempts[key]
        if attempts <= self.retries:
            print(
                f"{self.noun} {key}: its worker {why}; retrying ({attempts} of "
                f"{self.retries + 1} attempts used)",
                file=sys.stderr,
            )
            return True
        message = (
            f"{self.noun} {key}: its worker {why}, on each of {attempts} attempts "
            "(killed, out of memory, or a crash)"
        )
        if self.on_lost is None:
            raise TaskLost(message, (key,))
        print(message, file=sys.stderr)
        self._lost.append(Done(key, self.on_lost(key, message), "", 0.0, attempts))
        return False

    def stall_limit_s(self) -> float:
        """The watchdog's current limit, in seconds."""
        if self.stall_s is not None:
            return self.stall_s
        return max(STALL_FLOOR_S, STALL_FACTOR * self._slowest_s)

    def _watchdog(self, now: float) -> None:
        limit = self.stall_limit_s()
        stuck = sorted(k for k, t in self._last_seen.items() if now - t > limit)
        if stuck:
            raise Stalled(
                f"{self.noun} {', '.join(stuck)} made no progress for {limit:.0f} s "
                f"(stuck; the limit is {'set' if self.stall_s is not None else 'adaptive'})",
                tuple(stuck),
            )
        # Nothing started, progressed or finished (never under the floor: starting workers
        # and scheduling take time): no worker is alive to run the waiting tasks.
        idle_limit = max(limit, STALL_FLOOR_S)
        if self._payloads and now - self._last_event > idle_limit:
            raise Stalled(
                f"no {self.noun} started or made progress for {idle_limit:.0f} s "
                f"({len(self._payloads)} waiting): no live worker",
                tuple(sorted(self._payloads)),
            )


# --------------------------------------------------------------------------------------------
# Local processes, supervised


def _worker_main(conn, fn: TaskFn) -> None:
    """A worker process: run the tasks the supervisor sends on `conn` until told to stop (None)
    or the supervisor is gone. Each message back is a tuple on the same pipe."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the supervisor alone decides
    _die_with_parent()
    host = os.uname().nodename
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return  # the supervisor is gone
        if msg is None:
            return
        key, payload = msg
        try:
            conn.send(("start", key))
        except (EOFError, OSError):
            return

        def progress(amount: int = 1, key=key) -> None:
            conn.send(("progress", key, int(amount)))

        try:
            out = ("done", key, fn(payload, progress), f"{host}:{os.getpid()}", _peak_rss_mb())
        except UserError as e:
            out = ("user_error", key, str(e))
        except BaseException as e:
            out = ("error", key, type(e).__name__, str(e), "".join(traceback.format_exception(e)))
        try:
            conn.send(out)
        except (EOFError, OSError):
            return  # the pipe broke: the supervisor is gone
        except Exception as e:  # the result does not pickle
            tb = "".join(traceback.format_exception(e))
            conn.send(("error", key, type(e).__name__, f"its result cannot be sent: {e}", tb))


def _die_with_parent() -> None:
    """Linux: SIGKILL this worker when the supervisor dies (even by SIGKILL), so that no orphan
    goes on writing into a directory a rerun owns."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() == 1:  # the parent died before prctl took effect
        os._exit(1)


@dataclass
class _Worker:
    process: object  # multiprocessing.Process
    conn: object  # our end of its pipe
    key: str | None = None  # the task it runs
    tasks: int = 0  # tasks it was given
    retiring: bool = False  # told to stop


class ProcessExecutor(Executor):
    """`workers` spawned processes, supervised: the main process hands each one task at a time
    over its own pipe, starts a replacement when one retires or dies, and retries the task of a
    dead one. One pipe per worker (not a shared queue) so that a worker killed mid-message can
    corrupt nothing but its own pipe. Spawned, not forked: a fresh interpreter per worker, no
    inherited libsumo, Embree or thread state (libsumo holds one simulation per process, so
    threads would not do)."""

    def __init__(self, fn: TaskFn, **options):
        super().__init__(fn, **options)
        import multiprocessing as mp

        self._ctx = mp.get_context("spawn")
        self._queue: deque[str] = deque()
        self._pool: list[_Worker] = []

    def _enqueue(self, key: str, payload: object) -> None:
        self._queue.append(key)

    def _spawn(self) -> _Worker:
        ours, theirs = self._ctx.Pipe(duplex=True)
        process = self._ctx.Process(
            target=_worker_main, args=(theirs, self.fn), name="datagen-worker"
        )
        try:
            process.start()
        except OSError as e:
            raise ExecutorError(f"cannot start a worker process: {e}") from None
        theirs.close()
        worker = _Worker(process, ours)
        self._pool.append(worker)
        return worker

    def _assign(self) -> None:
        idle = [w for w in self._pool if w.key is None and not w.retiring]
        while self._queue:
            if not idle:
                if len([w for w in self._pool if not w.retiring]) >= self.workers:
                    return
                idle.append(self._spawn())
            worker = idle.pop()
            key = self._queue.popleft()
            try:
                worker.conn.send((key, self._payloads[key]))
            except (OSError, EOFError):  # it died while idle: _poll buries it
                self._queue.appendleft(key)
                worker.retiring = True
                continue
            worker.key = key
            worker.tasks += 1
            self._attempts[key] += 1  # its clock starts when the worker says "start"

    def _poll(self, timeout_s: float) -> list[Progress | Done]:
        from multiprocessing.connection import wait

        self._assign()
        events: list[Progress | Done] = []
        handles = {}
        for w in self._pool:
            handles[w.conn] = w
            handles[w.process.sentinel] = w
        ready = wait(list(handles), timeout=timeout_s) if handles else []
        if not handles:
            time.sleep(timeout_s)
        touched = {id(handles[h]): handles[h] for h in ready}
        for w in touched.values():
            self._read(w, events)
        for w in list(self._pool):
            if not w.process.is_alive():
                self._read(w, events)  # what it sent before it went
                self._bury(w)
        self._assign()
        return events

    def _read(self, w: _Worker, events: list) -> None:
        try:
            while w.conn.poll():
                msg = w.conn.recv()
                self._handle(w, msg, events)
        except (EOFError, OSError):
            pass  # it is dead or dying; its sentinel tells

    def _handle(self, w: _Worker, msg: tuple, events: list) -> None:
        kind, key = msg[0], msg[1]
        if kind == "start":
            self._task_started(key, attempt=False)
            events.append(Progress(key, 0))
            return
        if kind == "progress":
            events.append(Progress(key, msg[2]))
            return
        w.key = None
        if kind == "done":
            events.append(Done(key, msg[2], msg[3], msg[4], self._attempts[key]))
            if self.max_tasks_per_worker and w.tasks >= self.max_tasks_per_worker:
                self._retire(w)
        elif kind == "user_error":
            raise UserError(msg[2])
        else:
            raise _failed(self.noun, key, msg[2], msg[3], msg[4])

    def _retire(self, w: _Worker) -> None:
        w.retiring = True
        try:
            w.conn.send(None)
        except (OSError, EOFError):
            pass

    def _bury(self, w: _Worker) -> None:
        w.process.join()
        w.conn.close()
        self._pool.remove(w)
        if w.key is not None:
            code = w.process.exitcode
            why = (
                f"was killed by {signal.Signals(-code).name}"
                if code is not None and code < 0
                else f"exited with status {code}"
            )
            key, w.key = w.key, None
            if self._task_lost(key, why):
                self._queue.appendleft(key)

    def close(self, cancel: bool = False) -> None:
        for w in self._pool:
            if cancel:
                w.process.terminate()
            else:
                self._retire(w)
        deadline = time.monotonic() + (2.0 if cancel else 30.0)
        for w in self._pool:
            w.process.join(max(0.0, deadline - time.monotonic()))
            if w.process.is_alive():
                w.process.kill()
                w.process.join()
            w.conn.close()
        self._pool.clear()
        self._queue.clear()


# --------------------------------------------------------------------------------------------
# Ray


class RayExecutor(Executor):
    """Tasks as Ray tasks (one CPU each) on a local Ray instance or an existing cluster
    (`address`). Every node must have this package installed (and, for the build, see its output
    directory at the same path: a shared filesystem). Ray itself retries a task whose worker died
    (`max_retries`) and recycles workers (`max_calls`); progress comes back through a small
    actor, whose events also start each attempt's watchdog clock."""

    def __init__(self, fn: TaskFn, address: str | None = None, **options):
        super().__init__(fn, **options)
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
                kwargs["num_cpus"] = self.workers
            sigterm = signal.getsignal(signal.SIGTERM)
            try:
                ray.init(**kwargs)
            except (ConnectionError, RuntimeError, ValueError) as e:
                where = address or "a local instance"
                raise UserError(f"cannot start Ray on {where}: {str(e).splitlines()[0]}") from None
            finally:
                # ray.init installs its own SIGTERM handlers (sys.exit in Python, an abort in its
                # C++ core); the caller's (stop_on_sigterm) must stay in charge of stopping.
                if sigterm is not None and threading.current_thread() is threading.main_thread():
                    signal.signal(signal.SIGTERM, sigterm)
        self.progress = ray.remote(num_cpus=0)(_RayProgress).remote()
        options = {"num_cpus": 1, "max_retries": self.retries, "retry_exceptions": False}
        if self.max_tasks_per_worker:
            options["max_calls"] = self.max_tasks_per_worker
        self.task = ray.remote(**options)(_ray_task)
        self.refs: dict = {}  # ObjectRef -> key
        self.fn_ref = ray.put(fn)

    def _enqueue(self, key: str, payload: object) -> None:
        self.refs[self.task.remote(self.fn_ref, key, payload, self.progress)] = key

    def _poll(self, timeout_s: float) -> list[Progress | Done]:
        ray = self.ray
        if not self.refs:
            time.sleep(timeout_s)
            return []
        ready, _ = ray.wait(list(self.refs), num_returns=len(self.refs), timeout=timeout_s)
        events: list[Progress | Done] = []
        for kind, key, amount in ray.get(self.progress.drain.remote()):
            if key not in self._payloads:
                continue
            if kind == "start":
                if self._attempts[key] and key in self._last_seen:
                    print(f"{self.noun} {key}: its worker died; Ray retried it", file=sys.stderr)
                self._task_started(key)
            events.append(Progress(key, amount))
        for ref in ready:
            key = self.refs.pop(ref)
            try:
                result, worker, rss = ray.get(ref)
            except ray.exceptions.RayTaskError as e:
                cause = e.as_instanceof_cause()
                if isinstance(cause, UserError):
                    raise UserError(str(cause).splitlines()[-1]) from None
                raise _failed(self.noun, key, type(cause).__name__, str(cause), str(e)) from None
            except ray.exceptions.RayError as e:
                self._attempts[key] = max(self._attempts[key], self.retries + 1)
                self._task_lost(key, f"was lost to Ray ({type(e).__name__})")
            else:
                events.append(Done(key, result, worker, rss, max(1, self._attempts[key])))
        return events

    def close(self, cancel: bool = False) -> None:
        if cancel:
            for ref in self.refs:
                self.ray.cancel(ref, force=True)
        self.refs.clear()
        if self.started:
            self.ray.shutdown()


class _RayProgress:
    """The Ray actor that collects (kind, key, amount) events from running tasks."""

    def __init__(self):
        self.events: list[tuple] = []

    def add(self, kind: str, key: str, amount: int) -> None:
        self.events.append((kind, key, amount))

    def drain(self) -> list[tuple]:
        events, self.events = self.events, []
        return events


def _ray_task(fn: TaskFn, key: str, payload: object, actor) -> tuple:
    actor.add.remote("start", key, 0)

    def progress(amount: int = 1) -> None:
        actor.add.remote("progress", key, int(amount))

    result = fn(payload, progress)
    return result, f"{os.uname().nodename}:{os.getpid()}", _peak_rss_mb()


# --------------------------------------------------------------------------------------------


def make(
    kind: str,
    fn: TaskFn,
    *,
    workers: int,
    ray_address: str | None = None,
    **options,
) -> Executor:
    """An executor of `kind` ("process" or "ray"); options as for Executor."""
    if kind == "process":
        return ProcessExecutor(fn, workers=workers, **options)
    if kind == "ray":
        return RayExecutor(fn, ray_address, workers=workers, **options)
    raise UserError(f"unknown executor {kind!r} (process or ray)")
