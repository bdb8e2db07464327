"""schemas/dataset.py: which files are shards, reading rows and episodes, box corners."""

import numpy as np
import pyarrow.dataset as ds
import pyarrow.parquet as pq
import pytest

from schemas import dataset
from tests.synthetic import synthetic_table


def _write(root, rel, n=2, episode="e-0-0"):
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(synthetic_table(n, episode), path)
    return path


def test_shards_are_parquet_files_at_any_depth_in_pyarrows_order(tmp_path):
    for rel in ("a/x.parquet", "a-b/x.parquet", "B/q.parquet", "top.parquet", "a/b/c/deep.parquet"):
        _write(tmp_path, rel)
    # the same files as pyarrow's discovery, in its order, when the directory holds only shards
    assert [str(p) for p in dataset.shard_files(tmp_path)] == ds.dataset(tmp_path).files
    for rel in ("_tmp/x.parquet", ".hidden/x.parquet", "a/_partial.parquet", "a/.x.parquet"):
        _write(tmp_path, rel)
    (tmp_path / "README.md").write_text("# not data")
    (tmp_path / "a" / "frame.png").write_bytes(b"\x89PNG")
    names = [p.relative_to(tmp_path).as_posix() for p in dataset.shard_files(tmp_path)]
    # by path string, as pyarrow sorts: "a-b/" before "a/" ("-" < "/")
    assert names == [
        "B/q.parquet",
        "a-b/x.parquet",
        "a/b/c/deep.parquet",
        "a/x.parquet",
        "top.parquet",
    ]


def test_a_file_is_its_own_shard_and_a_missing_path_is_an_error(tmp_path):
    shard = _write(tmp_path, "one.parquet")
    assert dataset.shard_files(shard) == [shard]
    assert dataset.shard_files(tmp_path / "one.parquet") == [shard]
    (tmp_path / "empty").mkdir()
    assert dataset.shard_files(tmp_path / "empty") == []
    with pytest.raises(dataset.DatasetError, match="no such file or directory"):
        dataset.shard_files(tmp_path / "nope")
    with pytest.raises(dataset.DatasetError, match="no shards"):
        dataset.read_row(tmp_path / "empty", 0)


def test_rows_and_episodes_are_read_in_order(tmp_path):
    _write(tmp_path, "t/a.parquet", 3, "a-0-0")
    table = synthetic_table(4, "b-0-0", seed=1)
    pq.write_table(table.take([3, 1, 0, 2]), tmp_path / "t" / "b.parquet")  # frames shuffled
    assert dataset.episode_ids(tmp_path) == ["a-0-0", "b-0-0"]
    row = dataset.read_row(tmp_path, 4)  # row 4 in read order: the second file's row 1
    assert (row["episode_id"], row["frame"]) == ("b-0-0", 1)  # file order, not frame order
    assert dataset.read_row(tmp_path, 2, episode="b-0-0")["frame"] == 2
    episode = dataset.read_episode(tmp_path, "b-0-0", columns=["episode_id", "frame"])
    assert episode.column("frame").to_pylist() == [0, 1, 2, 3]
    with pytest.raises(dataset.DatasetError, match="no episode 'zz' .*a-0-0"):
        dataset.read_episode(tmp_path, "zz")
    with pytest.raises(dataset.DatasetError, match="out of range"):
        dataset.read_row(tmp_path, 7)


def test_a_file_that_is_not_parquet_is_a_one_line_error(tmp_path):
    (tmp_path / "x.parquet").write_text("not parquet")
    with pytest.raises(dataset.DatasetError, match="not a readable Parquet file"):
        dataset.read_row(tmp_path, 0)


def test_box_corners_start_front_right_and_turn_counter_clockwise():
    corners = dataset.box_corners(10.0, 2.0, 0.0, 4.0, 2.0)
    np.testing.assert_allclose(corners, [(12, 1), (12, 3), (8, 3), (8, 1)])
    # a quarter turn left: the front points along +y, front-right lies at +x
    turned = dataset.box_corners(0.0, 0.0, np.pi / 2, 4.0, 2.0)
    np.testing.assert_allclose(turned, [(1, 2), (-1, 2), (-1, -2), (1, -2)], atol=1e-12)
    many = dataset.box_corners(np.zeros((3, 5)), 0.0, np.linspace(0, 3, 5), 4.0, 2.0)
    assert many.shape == (3, 5, 4, 2)
    np.testing.assert_allclose(np.linalg.norm(many, axis=-1), np.sqrt(5.0))
