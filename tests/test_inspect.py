"""`datagen inspect`: a frame to a PNG, an episode to a video or a Rerun recording, bad input."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest

from datagen import cli
from datagen.dataset import inspect
from schemas import dataset
from tests.synthetic import synthetic_table


def _dataset(tmp_path):
    (tmp_path / "synth").mkdir(parents=True)
    pq.write_table(synthetic_table(3, "synth-0-0"), tmp_path / "synth" / "synth-0-0.parquet")
    pq.write_table(
        synthetic_table(4, "synth-1-0", seed=1), tmp_path / "synth" / "synth-1-0.parquet"
    )
    (tmp_path / "_manifest.json").write_text("{}")
    (tmp_path / "README.md").write_text("# not a shard")  # as data/README.md beside data/shards
    return tmp_path


def _inspect(*args) -> int:
    return cli.main(["inspect", *map(str, args)])


def _leftovers(folder, name):
    """Files under `folder` whose names contain `name` (final or partial)."""
    return sorted(p.name for p in folder.iterdir() if name in p.name)


def test_inspect_writes_a_png_of_the_frame(tmp_path):
    data = _dataset(tmp_path)
    out = tmp_path / "frame.png"
    assert _inspect(data, "--frame", 4, "--out", out) == 0
    img = cv2.imread(str(out))
    assert img is not None and img.shape[0] == 512 and img.shape[1] > 1000
    # row 4 across the shards is frame 1 of the second episode
    row = dataset.read_row(data, 4)
    assert (row["episode_id"], row["frame"]) == ("synth-1-0", 1)
    assert np.array_equal(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), inspect.draw(row))
    assert dataset.read_row(data, 2, episode="synth-1-0")["frame"] == 2


def test_inspect_reads_a_single_shard(tmp_path):
    data = _dataset(tmp_path)
    out = tmp_path / "one.png"
    shard = data / "synth" / "synth-0-0.parquet"
    assert _inspect(shard, "--frame", 2, "--out", out) == 0
    assert out.exists()


def test_video_holds_every_frame_of_the_episode_in_h264(tmp_path, capsys):
    av = pytest.importorskip("av")
    data = _dataset(tmp_path)
    out = tmp_path / "ep.mp4"
    assert _inspect(data, "--episode", "synth-1-0", "--video", out, "--speed", 4) == 0
    assert "4 frames at 8 fps, libx264" in capsys.readouterr().out
    with av.open(str(out)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264" and stream.average_rate == 8
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
    assert len(frames) == 4 and frames[0].shape == (
        512,
        inspect.draw(dataset.read_row(data, 3)).shape[1],
        3,
    )
    # the first frame is the episode's frame 0 (lossy, so compare loosely)
    want = inspect.draw(dataset.read_row(data, 0, episode="synth-1-0")).astype(int)
    assert np.abs(frames[0].astype(int) - want).mean() < 12
    assert _leftovers(tmp_path, "ep.") == ["ep.mp4"]


def test_without_pyav_the_video_falls_back_to_mp4v_and_says_so(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "av", None)  # import av -> ImportError
    data = _dataset(tmp_path)
    out = tmp_path / "ep.mp4"
    assert _inspect(data, "--episode", "synth-0-0", "--video", out) == 0
    captured = capsys.readouterr()
    assert "PyAV is not installed" in captured.err and "not in browsers" in captured.err
    assert "mp4v" in captured.out
    capture = cv2.VideoCapture(str(out))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == 3
    assert capture.get(cv2.CAP_PROP_FPS) == pytest.approx(2.0)


def test_rerun_recording_holds_the_episode_on_a_timeline(tmp_path):
    pytest.importorskip("rerun")
    from rerun.chunk import RrdReader

    data = _dataset(tmp_path)
    out = tmp_path / "ep.rrd"
    assert _inspect(data, "--episode", "synth-1-0", "--rerun", out) == 0
    chunks = list(RrdReader(out).stream())
    paths = {c.entity_path for c in chunks}
    expected = {
        "/camera/image",
        "/bev/map",
        "/bev/lidar",
        "/bev/boxes",
        "/bev/waypoints",
        "/bev/target_point",
        "/world/driven_path",
        "/world/ego",
        "/world/ego/lidar/ground",
        "/world/ego/lidar/above",
        "/world/ego/boxes",
        "/world/ego/waypoints",
        "/world/ego/target_point",
        "/labels/ego_speed_mps",
        "/labels/red_light",
        "/labels/traffic_light",
        "/labels/expert_reason",
    }
    assert expected <= paths
    camera = [c for c in chunks if c.entity_path == "/camera/image"]
    assert all({"frame", "time"} <= set(c.timeline_names) for c in camera)
    assert sum(c.num_rows for c in camera) == 4  # one image per frame
    boxes = [c for c in chunks if c.entity_path == "/world/ego/boxes" and not c.is_static]
    assert "veh0" in str(boxes[0].to_record_batch())  # track ids are the boxes' labels
    assert _leftovers(tmp_path, "ep.") == ["ep.rrd"]


def _error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def test_inspect_reports_a_missing_frame(tmp_path, capsys):
    data = _dataset(tmp_path)
    assert _inspect(data, "--frame", 99, "--out", tmp_path / "x.png") == 2
    assert "out of range" in _error(capsys)
    assert _inspect(tmp_path / "nope", "--out", tmp_path / "x.png") == 2
    assert "no such file or directory" in _error(capsys)


@pytest.mark.parametrize("what", ["--video", "--rerun"])
def test_bad_input_is_one_line_and_leaves_no_file(tmp_path, capsys, what):
    data = _dataset(tmp_path / "data")
    out = tmp_path / ("ep.mp4" if what == "--video" else "ep.rrd")
    assert _inspect(data, "--episode", "nope-0-0", what, out) == 2
    assert "no episode 'nope-0-0'" in _error(capsys)
    (tmp_path / "empty").mkdir()
    assert _inspect(tmp_path / "empty", what, out) == 2
    assert "no shards" in _error(capsys)
    (tmp_path / "file").write_text("")
    blocked = tmp_path / "file" / out.name  # its folder is a file: unwritable
    assert _inspect(data, "--episode", "synth-0-0", what, blocked) == 2
    assert "file is not a directory" in _error(capsys)
    assert _leftovers(tmp_path, "ep.") == []


def test_rerun_missing_is_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)
    data = _dataset(tmp_path)
    assert _inspect(data, "--episode", "synth-0-0", "--rerun", tmp_path / "ep.rrd") == 2
    assert "needs rerun-sdk: pip install 'iidsu[viz]'" in _error(capsys)
    assert _leftovers(tmp_path, "ep.") == []
