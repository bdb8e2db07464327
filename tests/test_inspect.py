"""`datagen inspect`: draws one frame of a shard or a dataset directory to a PNG."""

from __future__ import annotations

import cv2
import pyarrow.parquet as pq

from datagen import cli, inspect
from tests.synthetic import synthetic_table


def _dataset(tmp_path):
    (tmp_path / "synth").mkdir()
    pq.write_table(synthetic_table(3, "synth-0-0"), tmp_path / "synth" / "synth-0-0.parquet")
    pq.write_table(
        synthetic_table(4, "synth-1-0", seed=1), tmp_path / "synth" / "synth-1-0.parquet"
    )
    (tmp_path / "_manifest.json").write_text("{}")
    return tmp_path


def test_inspect_writes_a_png_of_the_frame(tmp_path):
    data = _dataset(tmp_path)
    out = tmp_path / "frame.png"
    assert cli.main(["inspect", str(data), "--frame", "4", "--out", str(out)]) == 0
    img = cv2.imread(str(out))
    assert img is not None and img.shape[0] == 512 and img.shape[1] > 1000
    # row 4 across the shards is frame 1 of the second episode
    row = inspect.read_row(data, 4)
    assert (row["episode_id"], row["frame"]) == ("synth-1-0", 1)
    assert inspect.read_row(data, 2, episode="synth-1-0")["frame"] == 2


def test_inspect_reads_a_single_shard(tmp_path):
    data = _dataset(tmp_path)
    out = tmp_path / "one.png"
    shard = data / "synth" / "synth-0-0.parquet"
    assert cli.main(["inspect", str(shard), "--frame", "2", "--out", str(out)]) == 0
    assert out.exists()


def test_inspect_reports_a_missing_frame(tmp_path, capsys):
    data = _dataset(tmp_path)
    assert cli.main(["inspect", str(data), "--frame", "99", "--out", str(tmp_path / "x.png")]) == 2
    assert "out of range" in capsys.readouterr().err
    assert cli.main(["inspect", str(tmp_path / "nope"), "--out", str(tmp_path / "x.png")]) == 2
