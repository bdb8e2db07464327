"""`datagen build`: planning, shards, manifest, resume, errors.

The first half drives the build machinery with synthetic episodes (tests/fakes.py) so that
planning, resume and determinism are pinned without the simulator's cost; the second half runs
real SUMO episodes through the `datagen` command."""

import functools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pyarrow.dataset as ds
import pytest

import schemas
from datagen.dataset import build, executors, plan, validate
from datagen.dataset.manifest import LOCK, MANIFEST, BuildLock
from datagen.errors import UserError
from tests.fakes import FAKE_TOWNS, fake_build, fake_config, fake_runner

ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------------------------
# Synthetic episodes


def killing_runner(spec, sensors, progress, kill: str = "", marker_dir: str | None = None):
    """fake_runner, but the worker running episode `kill` SIGKILLs itself mid-episode: on every
    attempt, or (`marker_dir`) on the first attempt only."""
    if spec.episode_id == kill:
        marker = Path(marker_dir or "/nonexistent") / f"{kill}.killed"
        if marker_dir is None or not marker.exists():
            if marker_dir is not None:
                marker.touch()
            progress(1)
            os.kill(os.getpid(), signal.SIGKILL)
    return fake_runner(spec, sensors, progress)


def stalling_runner(spec, sensors, progress, stall: str = ""):
    """fake_runner, but episode `stall` hangs (a deadlock in the simulator, say)."""
    if spec.episode_id == stall:
        progress(1)
        time.sleep(3600)
    return fake_runner(spec, sensors, progress)


def failing_runner(spec, sensors, progress):
    if spec.episode_id == "alpha-7-0003":
        raise ValueError("the simulator fell over")
    return fake_runner(spec, sensors, progress)


def _content(out: Path) -> dict:
    """Everything that should be identical between two builds of the same arguments."""
    manifest = json.loads((out / MANIFEST).read_text())
    manifest.pop("run")
    files = {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*.parquet"))}
    return {"manifest": manifest, "files": files}


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> dict:
    """_content of the uninterrupted fake_build() that every interrupted one must equal."""
    out = tmp_path_factory.mktemp("reference") / "data"
    fake_build(out)
    return _content(out)


def test_plan_splits_the_budget_across_towns_and_weathers_deterministically():
    cfg = fake_config(frames=1001, episode_seconds=60.0)  # 120 frames per episode
    plans = plan.plan(cfg, {})
    assert plans == plan.plan(cfg, {})
    episodes = [e for p in plans.values() for e in p.episodes]
    assert sum(e.n_frames for e in episodes) == 1001
    assert max(e.n_frames for e in episodes) <= 120
    assert len({e.episode_id for e in episodes}) == len(episodes)
    assert len({e.seed for e in episodes}) == len(episodes)
    per_cell = {}
    for e in episodes:
        per_cell[(e.town, e.weather)] = per_cell.get((e.town, e.weather), 0) + e.n_frames
        assert e.behaviour in {
            "sunny": ("normal", "aggressive"),
            "cloudy": ("normal", "aggressive"),
        }.get(e.weather, ("cautious",))
    assert sorted(per_cell.values()) == [125] * 7 + [126]
    assert [e.episode_id for e in plans["alpha"].episodes[:2]] == ["alpha-7-0000", "alpha-7-0001"]
    # the same town and index give the same episode whatever the other towns are
    alone = plan.plan(plan.BuildConfig(FAKE_TOWNS[:1], 501, 7, 60.0, sensors={}), {})
    assert alone["alpha"].episodes == plans["alpha"].episodes


def test_weather_mix_apportions_frames():
    cfg = plan.BuildConfig(
        FAKE_TOWNS[:1], 100, 0, 600.0, build.parse_weather_mix("sunny=3,foggy=1"), sensors={}
    )
    frames = {}
    for e in plan.plan(cfg, {})["alpha"].episodes:
        frames[e.weather] = frames.get(e.weather, 0) + e.n_frames
    assert frames == {"sunny": 75, "foggy": 25}
    with pytest.raises(UserError, match="unknown weather 'snowy'"):
        build.parse_weather_mix("snowy=1")


def _finish(plan, rows_of):
    return {e.episode_id: {**e.key(), "rows": rows_of(e)} for e in plan.episodes}


def test_episodes_that_end_early_are_topped_up_by_a_further_round():
    cfg = fake_config(frames=40, episode_seconds=5.0)  # 10 frames per episode, 20 per town
    quota = plan.town_quotas(cfg)["alpha"]
    first = plan.plan_town(cfg, "alpha", quota, {})
    assert not first.complete and len(first.episodes) == 4
    done = _finish(first, lambda e: e.n_frames - 3 if e.weather == "rainy" else e.n_frames)
    second = plan.plan_town(cfg, "alpha", quota, done)
    extra = second.episodes[len(first.episodes) :]
    assert [(e.weather, e.n_frames, e.round) for e in extra] == [("rainy", 3, 1)]
    assert extra[0].episode_id == "alpha-7-0004"
    done.update({e.episode_id: {**e.key(), "rows": e.n_frames} for e in extra})
    third = plan.plan_town(cfg, "alpha", quota, done)
    assert third.complete and third.episodes == second.episodes and not third.shortfall


def test_a_weather_whose_round_delivers_nothing_is_given_up():
    cfg = fake_config(frames=40, episode_seconds=5.0)
    quota = plan.town_quotas(cfg)["alpha"]
    p = plan.plan_town(cfg, "alpha", quota, {})
    done = _finish(p, lambda e: 0 if e.weather == "foggy" else e.n_frames)
    p = plan.plan_town(cfg, "alpha", quota, done)
    assert p.complete and p.shortfall == {"foggy": 5}


def test_synthetic_build_is_readable_and_matches_its_manifest(tmp_path):
    report = fake_build(tmp_path)
    m = report.manifest
    assert m["status"] == "complete"
    df = pd.read_parquet(tmp_path, columns=["episode_id", "frame", "town", "weather"])
    assert len(df) == 96 == m["statistics"]["frames"]
    assert not df.duplicated(["episode_id", "frame"]).any()
    counts = df.groupby(["town", "weather"]).size()
    assert {f"{t}/{w}": n for (t, w), n in counts.items()} == m["statistics"][
        "frames_by_town_weather"
    ]
    early = [e for e in m["episodes"] if e["rows"] < e["n_frames"]]
    assert early and all(e["end_reason"] == "route_end" for e in early)
    assert any(e["round"] > 0 for e in m["episodes"])  # the early ones were topped up
    assert m["statistics"]["episodes_ended_early"] == {"route_end": len(early)}
    reports, problems, rows = validate.validate_dir(tmp_path, workers=1)
    assert problems == [] and all(not r.problems for r in reports) and rows == 96
    assert "route_end" in build.summary(report)


@pytest.mark.slow
def test_dataset_does_not_depend_on_worker_count(tmp_path):
    fake_build(tmp_path / "one", workers=1)
    fake_build(tmp_path / "two", workers=2)
    assert _content(tmp_path / "one") == _content(tmp_path / "two")


@pytest.mark.slow
def test_rerun_keeps_finished_episodes_and_adopts_unrecorded_shards(tmp_path, reference):
    out = tmp_path / "out"
    fake_build(out)
    manifest = json.loads((out / MANIFEST).read_text())
    # As if killed: one shard renamed but not yet recorded, one not written at all, one
    # temporary left, the manifest still "building".
    recorded = [e for e in manifest["episodes"] if e["rows"]]
    recorded[0]["status"] = "pending"
    (out / recorded[1]["file"]).unlink()
    (out / recorded[2]["file"]).write_bytes(b"PAR1 damaged")  # e.g. a disk error
    (out / "alpha" / "_alpha-7-0009.parquet.99.tmp").write_bytes(b"half")
    manifest["status"] = "building"
    (out / MANIFEST).write_text(json.dumps(manifest))
    report = fake_build(out)
    # only the missing and the damaged episodes were redone
    assert report.new_frames == recorded[1]["rows"] + recorded[2]["rows"]
    assert _content(out) == reference


@pytest.mark.slow
def test_different_arguments_are_refused_unless_forced(tmp_path):
    fake_build(tmp_path)
    with pytest.raises(UserError, match=r"different arguments \(frames: 96 != 48\).*--force"):
        fake_build(tmp_path, frames=48)
    fake_build_forced = build.build(
        fake_config(frames=48),
        tmp_path,
        workers=1,
        runner=fake_runner,
        force=True,
        progress_bar=False,
    )
    assert fake_build_forced.manifest["statistics"]["frames"] == 48
    assert len(pd.read_parquet(tmp_path, columns=["frame"])) == 48


@pytest.mark.slow
def test_a_failing_episode_stops_the_build_and_keeps_the_rest(tmp_path, capsys):
    with pytest.raises(UserError, match=r"episode alpha-7-0003 failed \(ValueError: the sim"):
        build.build(fake_config(), tmp_path, workers=1, runner=failing_runner, progress_bar=False)
    assert "Traceback" in capsys.readouterr().err  # the worker's, for the bug report
    manifest = json.loads((tmp_path / MANIFEST).read_text())
    done = [e["episode_id"] for e in manifest["episodes"] if e["status"] == "done"]
    assert "alpha-7-0000" in done and "alpha-7-0003" not in done
    assert fake_build(tmp_path).manifest["status"] == "complete"  # resumes once fixed


def test_two_builds_never_write_one_directory(tmp_path):
    with BuildLock(tmp_path):
        with pytest.raises(UserError, match="another datagen build is writing"):
            fake_build(tmp_path)
    assert fake_build(tmp_path).manifest["status"] == "complete"
    assert not (tmp_path / LOCK).exists()


def test_foreign_parquet_files_are_never_touched(tmp_path):
    pd.DataFrame({"a": [1]}).to_parquet(tmp_path / "mine.parquet")
    (tmp_path / "alpha").mkdir()
    (tmp_path / "alpha" / "notes.parquet").write_bytes(b"not even parquet")
    (tmp_path / "alpha" / "beta").mkdir()  # any depth: a reader of tmp_path would read it too
    pd.DataFrame({"b": [2]}).to_parquet(tmp_path / "alpha" / "beta" / "deep.parquet")
    for name in ("alpha/beta/deep.parquet", "alpha/notes.parquet", "mine.parquet"):
        with pytest.raises(UserError, match=f"not iidsu shards \\(e.g. {tmp_path / name}\\)"):
            build.build(fake_config(), tmp_path, runner=fake_runner, force=True, progress_bar=False)
        assert (tmp_path / name).exists()
        (tmp_path / name).rename(tmp_path / f"_{name.replace('/', '_')}")  # hidden from readers


def _spawn_fake_build(out: Path, env_extra: dict, executor: str = "process") -> subprocess.Popen:
    code = "import sys; from tests.fakes import fake_build_main; fake_build_main(*sys.argv[1:])"
    env = {**os.environ, **env_extra}
    return subprocess.Popen(
        [sys.executable, "-c", code, str(out), "2", executor],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,  # so that the test can signal the whole build
        # as a terminal's foreground job: a test run started in the background of a script
        # (`cmd &`) inherits SIGINT ignored, and Ctrl-C would then never reach the build
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def _wait_for_shards(out: Path, n: int, proc: subprocess.Popen, timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while len(list(out.glob("*/*.parquet"))) < n:
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "build made no progress"
        time.sleep(0.05)


@pytest.mark.slow
def test_sigkill_then_rerun_equals_an_uninterrupted_build(tmp_path, reference):
    out = tmp_path / "out"
    proc = _spawn_fake_build(out, {"FAKE_FRAME_SECONDS": "0.02"})
    _wait_for_shards(out, 3, proc)
    os.killpg(proc.pid, signal.SIGKILL)  # the build and its workers, mid-episode
    proc.wait()
    partial = len(list(out.glob("*/*.parquet")))
    assert 3 <= partial < len(reference["files"])
    report = fake_build(out)
    assert 0 < report.new_frames < 96
    assert _content(out) == reference


@pytest.mark.slow
def test_ctrl_c_stops_cleanly_and_the_rerun_finishes(tmp_path, reference):
    out = tmp_path / "out"
    proc = _spawn_fake_build(out, {"FAKE_FRAME_SECONDS": "0.4"})  # 6.4 s an episode
    _wait_for_shards(out, 2, proc)
    at_stop = len(list(out.glob("*/*.parquet")))
    os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does
    _, stderr = proc.communicate(timeout=60)
    # running episodes are stopped, not waited for: the two workers' episodes do not finish
    # (at most one that was writing its shard at that instant); counted, not timed, so a
    # loaded machine cannot fail it (a 2 s bound did, twice, in full suites under load)
    assert len(list(out.glob("*/*.parquet"))) <= at_stop + 1
    assert proc.returncode == 130
    assert "run the same command again to resume" in stderr.decode()
    assert "Traceback" not in stderr.decode()
    assert list(out.rglob("_*.tmp")) == []
    fake_build(out)
    assert _content(out) == reference


@pytest.mark.slow
def test_hundreds_of_episodes_over_two_workers_complete_with_the_exact_row_count(tmp_path):
    # 2-frame episodes: the build that hung after 2 workers x 50 episodes (issue 11)
    cfg = fake_config(frames=600, episode_seconds=1.0)
    report = build.build(cfg, tmp_path, workers=2, runner=fake_runner, progress_bar=False)
    m = report.manifest
    assert m["status"] == "complete" and m["statistics"]["frames"] == 600
    assert len(pd.read_parquet(tmp_path, columns=["frame"])) == 600
    episodes = m["statistics"]["episodes"]
    assert episodes == len(m["episodes"]) > 300  # 300 planned, and the top-up rounds
    # workers were recycled (50 episodes each) and replaced, and none was left waiting
    assert len(report.peak_rss_mb) >= episodes // executors.MAX_TASKS_PER_WORKER
    assert len(report.episode_log) == episodes


@pytest.mark.slow
def test_a_worker_killed_mid_episode_is_retried_and_the_dataset_is_exact(
    tmp_path, capsys, reference
):
    runner = functools.partial(killing_runner, kill="alpha-7-0003", marker_dir=str(tmp_path))
    out = tmp_path / "out"
    build.build(fake_config(), out, workers=2, runner=runner, progress_bar=False)
    assert "episode alpha-7-0003: its worker was killed by SIGKILL; retrying" in (
        capsys.readouterr().err
    )
    assert _content(out) == reference


@pytest.mark.slow
def test_kill_9_of_a_worker_alone_is_retried_and_the_build_finishes_exact(tmp_path, reference):
    out = tmp_path / "out"
    proc = _spawn_fake_build(out, {"FAKE_FRAME_SECONDS": "0.1"})
    _wait_for_shards(out, 2, proc, timeout_s=120)
    workers = [p for p in _children(proc.pid) if "spawn_main" in " ".join(_cmdline(p))]
    assert workers, "no worker process found"
    os.kill(workers[0], signal.SIGKILL)  # one worker, mid-episode (1.6 s an episode)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 0, stderr.decode()  # its episode (if it had one) ran again
    assert _content(out) == reference


def _children(pid: int) -> list[int]:
    with open(f"/proc/{pid}/task/{pid}/children") as f:
        return [int(c) for c in f.read().split()]


def _cmdline(pid: int) -> list[str]:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().decode(errors="replace").split("\0")
    except OSError:
        return []


@pytest.mark.slow
def test_a_worker_that_always_dies_stops_the_build_clearly_and_the_rerun_is_exact(
    tmp_path, reference
):
    out = tmp_path / "out"
    runner = functools.partial(killing_runner, kill="beta-7-0002")
    options = build.RunOptions(workers=2, retries=1)
    with pytest.raises(UserError) as e:
        build.build(fake_config(), out, runner=runner, progress_bar=False, options=options)
    message = str(e.value)
    assert message.startswith("episode beta-7-0002: its worker was killed by SIGKILL, on each")
    assert message.endswith(build.RESUME) and "\n" not in message
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["status"] == "building"
    assert all((out / r["file"]).exists() for r in manifest["episodes"] if r.get("file"))
    assert fake_build(out).new_frames < 96  # the finished episodes were kept
    assert _content(out) == reference


@pytest.mark.slow
def test_a_stalled_episode_hits_the_watchdog_and_the_rerun_is_exact(tmp_path, reference):
    out = tmp_path / "out"
    runner = functools.partial(stalling_runner, stall="alpha-7-0002")
    options = build.RunOptions(workers=2, stall_s=2.0)
    t0 = time.monotonic()
    with pytest.raises(UserError, match=r"^episode alpha-7-0002 made no progress for 2 s"):
        build.build(fake_config(), out, runner=runner, progress_bar=False, options=options)
    assert time.monotonic() - t0 < 60
    assert list(out.rglob("_*.tmp")) == []
    fake_build(out)
    assert _content(out) == reference


@pytest.mark.slow
@pytest.mark.parametrize("executor", ["process", "ray"])
def test_sigterm_stops_like_ctrl_c_and_the_rerun_finishes(tmp_path, executor, reference):
    if executor == "ray":
        pytest.importorskip("ray", reason="ray is not installed (pip install 'iidsu[ray]')")
    out = tmp_path / "out"
    proc = _spawn_fake_build(out, {"FAKE_FRAME_SECONDS": "0.15"}, executor)
    _wait_for_shards(out, 2, proc, timeout_s=120)
    proc.send_signal(signal.SIGTERM)  # the build alone, as `timeout` or a batch scheduler does
    _, stderr = proc.communicate(timeout=60)
    stderr = stderr.decode()
    assert proc.returncode == 128 + signal.SIGTERM, stderr
    assert "datagen build: stopped (SIGTERM) with" in stderr and build.RESUME in stderr
    assert "Traceback" not in stderr
    assert list(out.rglob("_*.tmp")) == []
    assert json.loads((out / MANIFEST).read_text())["status"] == "building"
    fake_build(out)
    assert _content(out) == reference


@pytest.mark.slow
def test_ray_retries_a_killed_worker_and_equals_the_process_build(tmp_path, reference):
    pytest.importorskip("ray", reason="ray is not installed (pip install 'iidsu[ray]')")
    runner = functools.partial(killing_runner, kill="alpha-7-0003", marker_dir=str(tmp_path))
    out = tmp_path / "out"
    build.build(fake_config(), out, workers=2, executor="ray", runner=runner, progress_bar=False)
    assert (tmp_path / "alpha-7-0003.killed").exists()
    assert _content(out) == reference


# --------------------------------------------------------------------------------------------
# Real episodes through the `datagen` command (SUMO, ray-cast sensors)

SMALL = ["--town", "grid_small", "--town", "downtown", "--frames", "160", "--seed", "3"]
SMALL += ["--episode-seconds", "20"]  # 4 weathers x 2 towns = 8 episodes of 20 frames


def datagen(*args, check=True, **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        [sys.executable, "-m", "datagen.cli", *map(str, args)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        **kw,
    )
    if check:
        assert proc.returncode == 0, proc.stderr
    return proc


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    """The reference build: two towns, 160 frames, --workers 2."""
    out = tmp_path_factory.mktemp("small") / "data"
    proc = datagen("build", *SMALL, "--workers", "2", "--out", out)
    assert "grid_small" in proc.stdout and "episodes ended early" in proc.stdout
    return out


@pytest.mark.slow
def test_small_build_is_read_by_pandas_pyarrow_and_validate(small):
    manifest = json.loads((small / MANIFEST).read_text())
    stats = manifest["statistics"]
    assert manifest["status"] == "complete" and stats["frames"] == 160
    df = pd.read_parquet(small)
    assert len(df) == 160 and list(df.columns) == list(schemas.COLUMNS)
    assert not df.duplicated(["episode_id", "frame"]).any()
    cells = df.groupby(["town", "weather"]).size()
    assert {f"{t}/{w}": n for (t, w), n in cells.items()} == stats["frames_by_town_weather"]
    assert df.groupby("town").size().to_dict() == stats["frames_by_town"]
    assert df.groupby("weather").size().to_dict() == stats["frames_by_weather"]
    dataset = ds.dataset(small, format="parquet")
    assert dataset.count_rows() == 160
    assert sorted(dataset.to_table(columns=["town"]).column("town").unique().to_pylist()) == [
        "downtown",
        "grid_small",
    ]
    for path in small.glob("*/*.parquet"):
        schemas.check_version(ds.dataset(path).schema.metadata)
    assert datagen("validate", small).stdout.startswith("ok: 8 shard(s), 160 frames")


@pytest.mark.slow
def test_sigkill_mid_build_then_rerun_equals_the_uninterrupted_build(small, tmp_path):
    out = tmp_path / "data"
    cmd = [sys.executable, "-m", "datagen.cli", "build", *SMALL, "--workers", "2"]
    proc = subprocess.Popen(
        [*cmd, "--out", str(out)],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    _wait_for_shards(out, 2, proc, timeout_s=120)
    os.killpg(proc.pid, signal.SIGKILL)  # the build and its workers, mid-episode
    proc.wait()
    assert len(list(out.glob("*/*.parquet"))) < 8
    datagen("build", *SMALL, "--workers", "2", "--out", out)
    keys = pd.read_parquet(out, columns=["episode_id", "frame"])
    ref = pd.read_parquet(small, columns=["episode_id", "frame"])
    assert not keys.duplicated().any()
    assert set(map(tuple, keys.to_numpy())) == set(map(tuple, ref.to_numpy()))
    assert _content(out) == _content(small)  # byte for byte, manifest included


@pytest.mark.slow
def test_different_arguments_into_a_built_directory_are_refused(small):
    args = [("80" if a == "160" else a) for a in SMALL]
    proc = datagen("build", *args, "--out", small, check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"datagen build: error: {small} was built with different arguments (frames: 160 != 80); "
        "use --force to replace it, or choose another --out"
    ]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--net", "/nonexistent/city.net.xml"], "--net /nonexistent/city.net.xml: no such file"),
        (["--net", ROOT / "README.md"], "README.md"),
        (["--frames", "0"], "--frames must be at least 1, got 0"),
        (["--town", "atlantis"], "unknown town 'atlantis'"),
        (["--towns", "9"], "--towns must be between 1 and 8"),
        (["--weather-mix", "sunny=-1"], "--weather-mix: weight of sunny must be >= 0"),
        (["--stall-timeout", "0"], "--stall-timeout must be a positive number of seconds"),
        (["--retries", "-1"], "--retries must be at least 0, got -1"),
        (["--workers", "0"], "--workers must be at least 1, got 0"),
    ],
)
def test_bad_input_is_a_one_line_error(tmp_path, args, message):
    proc = datagen("build", *args, "--out", tmp_path / "data", check=False)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("datagen build: error: "), proc.stderr
    assert message in lines[0]


def test_the_held_out_town_is_refused_under_any_name(tmp_path):
    """Issue 38 item 7: `--net` with the cached held-out network (copied, renamed, gzipped)."""
    import gzip
    import shutil

    from datagen.world.towns import HELD_OUT_TOWNS, town_net_path

    cached = town_net_path(HELD_OUT_TOWNS[0])
    copy = tmp_path / "my_city.net.xml"
    shutil.copyfile(cached, copy)
    packed = tmp_path / "other.net.xml.gz"
    packed.write_bytes(gzip.compress(cached.read_bytes()))
    for net in (cached, copy, packed):
        proc = datagen("build", "--net", net, "--frames", "4", "--out", tmp_path / "d", check=False)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr
        assert f"the network of the held-out town '{HELD_OUT_TOWNS[0]}'" in lines[0]
    assert not (tmp_path / "d").exists()


@pytest.mark.slow
def test_a_user_network_is_a_town_named_by_its_stem(tmp_path):
    import sumo

    net = Path(sumo.SUMO_HOME) / "tools" / "game" / "fokr_bs_demo" / "fokr_bs.net.xml.gz"
    out = tmp_path / "data"
    datagen("build", "--net", net, "--frames", "12", "--workers", "2", "--out", out)
    manifest = json.loads((out / MANIFEST).read_text())
    assert [t["name"] for t in manifest["towns"]] == ["fokr_bs"]
    assert manifest["towns"][0]["net_path"] == str(net)
    df = pd.read_parquet(out, columns=["town", "episode_id"])
    assert set(df.town) == {"fokr_bs"} and len(df) == 12
    assert datagen("validate", out).returncode == 0


def test_sensor_overrides_reach_the_config():
    sensors = build.parse_sensors(["jpeg_quality=80", "lidar.azimuth_steps=500"])
    assert sensors.jpeg_quality == 80 and sensors.lidar.azimuth_steps == 500
    with pytest.raises(UserError, match="no field 'bogus'"):
        build.parse_sensors(["lidar.bogus=1"])
    with pytest.raises(UserError, match="cannot read 'many'"):
        build.parse_sensors(["jpeg_quality=many"])
    # the target point's form is recorded with the sensors (iidsu.config_json); sparse by default
    assert build.parse_sensors([]).to_dict()["target_point"] == "sparse"
    assert build.parse_sensors(["target_point=dense"]).target_point == "dense"
    with pytest.raises(UserError, match="target_point must be one of"):
        build.parse_sensors(["target_point=lane"])


@pytest.mark.slow
def test_validate_reports_a_corrupt_shard_on_one_line(small, tmp_path):
    import shutil

    copy = tmp_path / "data"
    shutil.copytree(small, copy)
    shard = sorted(copy.glob("*/*.parquet"))[3]
    shard.write_bytes(shard.read_bytes()[: shard.stat().st_size // 2])
    proc = datagen("validate", copy, check=False)
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{shard.relative_to(copy)}: not a readable")
    missing = datagen("validate", tmp_path / "nope", check=False)
    assert missing.returncode == 2
    assert (
        missing.stderr.strip()
        == f"datagen validate: error: {tmp_path / 'nope'}: no such file or directory"
    )


@pytest.mark.slow
def test_ray_build_on_a_local_instance_equals_the_process_build(small, tmp_path):
    pytest.importorskip("ray", reason="ray is not installed (pip install 'iidsu[ray]')")
    out = tmp_path / "data"
    proc = datagen("build", *SMALL, "--workers", "2", "--executor", "ray", "--out", out)
    assert "grid_small" in proc.stdout
    assert _content(out) == _content(small)
