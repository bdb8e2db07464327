"""`train show`: a frame's figure as a PNG, an episode's as a video; one-line errors."""

from __future__ import annotations

import sys

import cv2
import pyarrow.parquet as pq
import pytest
import torch

from schemas import WEATHERS
from tests.synthetic import synthetic_table
from training.checkpoint import save_checkpoint
from training.cli import main
from training.config import PRESETS
from training.model import IIDSU


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """An untrained tiny model's checkpoint and two synthetic episodes (5 and 3 frames)."""
    root = tmp_path_factory.mktemp("show")
    (root / "data" / "shards" / "synth").mkdir(parents=True)
    for k, n in enumerate((5, 3)):
        table = synthetic_table(n, f"synth-{k}-0", "synth", WEATHERS[k], seed=k)
        pq.write_table(table, root / "data" / "shards" / "synth" / f"synth-{k}-0.parquet")
    (root / "data" / "README.md").write_text("# columns")  # not a shard: skipped
    cfg = PRESETS["tiny"][0]
    torch.manual_seed(0)
    ckpt = root / "untrained.pt"
    save_checkpoint(ckpt, {"model": IIDSU(cfg).state_dict(), "model_config": cfg.to_dict()})
    return root, ckpt


def _show(setup, *args) -> int:
    root, ckpt = setup
    return main(["show", "--ckpt", str(ckpt), "--shards", str(root / "data"), *map(str, args)])


def test_png_of_an_episodes_frame(setup):
    root, _ = setup
    out = root / "f.png"
    assert _show(setup, "--episode", "synth-1-0", "--frame", 2, "--out", out) == 0
    assert cv2.imread(str(out)).shape == (2 * (256 + 18), 4 * 256, 3)


def test_video_has_one_figure_per_frame_of_the_episode(setup, capsys):
    av = pytest.importorskip("av")
    root, _ = setup
    out = root / "show.mp4"
    assert _show(setup, "--episode", "synth-0-0", "--video", out, "--speed", 2) == 0
    assert "5 frames of synth-0-0 at 4 fps, libx264" in capsys.readouterr().out
    with av.open(str(out)) as container:
        stream = container.streams.video[0]
        frames = list(container.decode(stream))
        assert stream.codec_context.name == "h264" and stream.average_rate == 4
    assert len(frames) == 5 and (frames[0].height, frames[0].width) == (2 * 274, 4 * 256)


def test_bad_input_is_one_line_and_leaves_no_file(setup, capsys, monkeypatch):
    root, _ = setup
    out = root / "bad.mp4"
    assert _show(setup, "--episode", "nope", "--video", out) == 2
    assert "--episode 'nope': not in the shards" in capsys.readouterr().err
    (root / "a-file").write_text("")
    assert _show(setup, "--episode", "synth-0-0", "--video", root / "a-file" / "x.mp4") == 2
    assert "a-file is not a directory" in capsys.readouterr().err
    assert _show(setup, "--video", root / "x.avi") == 2
    assert "must end in .mp4 or .webm" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "av", None)  # no PyAV: OpenCV's mp4v, and a note
    assert _show(setup, "--episode", "synth-1-0", "--video", out) == 0
    assert "not in browsers" in capsys.readouterr().err
    assert int(cv2.VideoCapture(str(out)).get(cv2.CAP_PROP_FRAME_COUNT)) == 3
    assert sorted(p.name for p in root.iterdir() if "partial" in p.name) == []
