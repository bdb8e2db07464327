"""datagen/dataset/executors.py: results, retries of dead workers, the watchdog, failures, SIGTERM, on
local processes and on Ray. Task functions live at module level: workers import them by name."""

import os
import signal
import time
from pathlib import Path

import pytest

from datagen.dataset import executors
from datagen.errors import UserError


def square(x, progress):
    progress(1)
    return x * x


def dies(payload, progress):
    """SIGKILL the worker itself: always (`marker` None), or on the first attempt only (the
    marker file tells a retry from the first attempt)."""
    x, marker = payload
    if marker is None or not Path(marker).exists():
        if marker is not None:
            Path(marker).touch()
        os.kill(os.getpid(), signal.SIGKILL)
    return x * x


def stalls(x, progress):
    if x == 3:
        time.sleep(3600)
    return x


def raises(x, progress):
    if x == 2:
        raise ValueError("two is bad")
    if x == 3:
        raise UserError("three: a user's mistake")
    return x


@pytest.mark.slow
def test_map_returns_every_result_through_recycled_workers():
    n = 40
    with executors.make("process", square, workers=2, max_tasks_per_worker=8) as ex:
        done = list(ex.map((str(i), i) for i in range(n)))
    assert sorted(d.result for d in done) == [i * i for i in range(n)]
    assert {d.key for d in done} == {str(i) for i in range(n)}
    # every worker retired after 8 tasks and was replaced: no deadlock, n / 8 processes
    assert len({d.worker for d in done}) >= n // 8
    assert all(d.peak_rss_mb > 0 and d.attempts == 1 for d in done)


@pytest.mark.slow
def test_a_killed_worker_is_detected_and_its_task_retried(tmp_path, capsys):
    (tmp_path / "never").touch()  # all but task 5 run normally
    tasks = [(str(i), (i, str(tmp_path / ("once" if i == 5 else "never")))) for i in range(8)]
    with executors.make("process", dies, workers=2) as ex:
        done = {d.key: d for d in ex.map(tasks)}
    assert {k: d.result for k, d in done.items()} == {str(i): i * i for i in range(8)}
    assert done["5"].attempts == 2 and done["4"].attempts == 1
    assert "task 5: its worker was killed by SIGKILL; retrying (1 of 3" in capsys.readouterr().err


def test_a_task_whose_worker_always_dies_stops_the_run_naming_it():
    t0 = time.monotonic()
    with pytest.raises(executors.TaskLost, match=r"episode 7: its worker was killed by SIGKILL"):
        with executors.make("process", dies, workers=2, retries=1, noun="episode") as ex:
            list(ex.map([("7", (7, None))]))
    assert time.monotonic() - t0 < 60


def test_with_on_lost_a_task_whose_worker_always_dies_is_a_result_and_the_others_go_on(tmp_path):
    """drive eval's crashed route (SUMO killed its worker each time): recorded, the rest driven."""
    (tmp_path / "never").touch()
    tasks = [(str(i), (i, None if i == 2 else str(tmp_path / "never"))) for i in range(5)]
    lost = []

    def on_lost(key, message):
        lost.append(key)
        return f"lost: {message}"

    with executors.make("process", dies, workers=2, retries=1, on_lost=on_lost) as ex:
        done = {d.key: d for d in ex.map(tasks)}
    assert lost == ["2"] and done["2"].attempts == 2
    assert done["2"].result.startswith("lost: task 2: its worker was killed by SIGKILL, on each")
    assert {k: d.result for k, d in done.items() if k != "2"} == {"0": 0, "1": 1, "3": 9, "4": 16}


def test_a_stalled_task_hits_the_watchdog_and_is_named():
    t0 = time.monotonic()
    with pytest.raises(executors.Stalled, match=r"^task 3 made no progress for 1 s") as e:
        with executors.make("process", stalls, workers=2, stall_s=1.0) as ex:
            list(ex.map((str(i), i) for i in range(6)))
    assert e.value.keys == ("3",)
    assert time.monotonic() - t0 < 30  # the stalled worker was killed, not waited for


def test_the_default_watchdog_is_ten_times_the_slowest_task_with_a_floor():
    ex = executors.ProcessExecutor(square, workers=1)
    assert ex.stall_limit_s() == executors.STALL_FLOOR_S
    ex._slowest_s = 100.0
    assert ex.stall_limit_s() == 1000.0
    ex.close()


@pytest.mark.slow
def test_a_raising_task_stops_the_run_with_its_traceback(capsys):
    with pytest.raises(executors.TaskFailed, match=r"task 2 failed \(ValueError: two is bad"):
        with executors.make("process", raises, workers=1) as ex:
            list(ex.map([("0", 0), ("2", 2)]))
    assert "Traceback" in capsys.readouterr().err
    with pytest.raises(UserError, match="^three: a user's mistake$"):
        with executors.make("process", raises, workers=1) as ex:
            list(ex.map([("3", 3)]))


def test_sigterm_raises_keyboard_interrupt_inside_the_block_only():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt):
        with executors.stop_on_sigterm():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
    assert signal.getsignal(signal.SIGTERM) == before


# --------------------------------------------------------------------------------------------
# Ray: one local instance for the module (an executor leaves a running instance alone)


@pytest.fixture(scope="module")
def ray_local():
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install 'iidsu[ray]')")
    ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING")
    yield
    ray.shutdown()


@pytest.mark.slow
def test_ray_returns_results_and_retries_a_killed_worker(ray_local, tmp_path):
    (tmp_path / "never").touch()
    tasks = [(str(i), (i, str(tmp_path / ("once" if i == 2 else "never")))) for i in range(6)]
    with executors.make("ray", dies, workers=2) as ex:
        done = {d.key: d for d in ex.map(tasks)}
    assert {k: d.result for k, d in done.items()} == {str(i): i * i for i in range(6)}
    assert (tmp_path / "once").exists()  # task 2's first worker was killed; Ray ran it again


@pytest.mark.slow
def test_ray_stalled_task_hits_the_watchdog(ray_local):
    with pytest.raises(executors.Stalled, match=r"^task 3 made no progress"):
        with executors.make("ray", stalls, workers=2, stall_s=2.0) as ex:
            list(ex.map((str(i), i) for i in range(5)))
