import errno
import json

import pandas as pd
import pyarrow.parquet as pq
import pytest

import schemas
from datagen.dataset import shards
from datagen.errors import UserError
from tests.synthetic import synthetic_table


def test_shard_round_trips_with_zstd_schema_and_file_metadata(tmp_path):
    table = synthetic_table(6, episode_id="synth-0-0003")
    path = shards.shard_path(tmp_path, "synth", "synth-0-0003")
    size = shards.write_shard(table, path)
    assert path == tmp_path / "synth" / "synth-0-0003.parquet"
    assert size == path.stat().st_size
    back = pq.read_table(path)
    schemas.validate(back)
    assert back.equals(table)
    assert back.schema.metadata == table.schema.metadata
    meta = pq.ParquetFile(path).metadata
    for g in range(meta.num_row_groups):
        for c in range(meta.num_columns):
            assert meta.row_group(g).column(c).compression == "ZSTD"
    assert list(tmp_path.rglob("_*")) == []  # no temporary left behind


def test_row_groups_are_sized_by_bytes():
    table = synthetic_table(8)
    per_row = table.nbytes // table.num_rows
    assert shards.rows_per_group(table, target_bytes=per_row * 3) == 3
    assert shards.rows_per_group(table, target_bytes=1) == 1
    assert shards.rows_per_group(table) == 8  # 8 small frames: one group
    assert 16 << 20 <= shards.ROW_GROUP_TARGET_BYTES <= 64 << 20  # "tens of MB"


def test_readers_see_only_complete_shards(tmp_path):
    shards.write_shard(synthetic_table(3, "synth-0-0000"), tmp_path / "a" / "synth-0-0000.parquet")
    # A writer killed mid-write leaves its temporary, whose name starts with "_".
    (tmp_path / "a" / "_synth-0-0001.parquet.123.tmp").write_bytes(b"PAR1 half a file")
    shards.write_json({"x": 1}, tmp_path / "_manifest.json")
    assert len(pd.read_parquet(tmp_path)) == 3
    assert shards.remove_temporaries(tmp_path) == 1
    assert sorted(p.name for p in tmp_path.rglob("*")) == [
        "_manifest.json",
        "a",
        "synth-0-0000.parquet",
    ]


def test_failed_write_leaves_no_file(tmp_path, monkeypatch):
    def half_write(table, where, **kwargs):
        with open(where, "wb") as f:
            f.write(b"PAR1 and then the process dies")
        raise KeyboardInterrupt

    monkeypatch.setattr(pq, "write_table", half_write)
    with pytest.raises(KeyboardInterrupt):
        shards.write_shard(synthetic_table(2), tmp_path / "t" / "e.parquet")
    assert list((tmp_path / "t").iterdir()) == []


@pytest.mark.parametrize(
    "code, message",
    [(errno.ENOSPC, "disk full"), (errno.EACCES, "cannot write to"), (errno.EROFS, "cannot write")],
)
def test_disk_full_or_unwritable_is_a_user_error(tmp_path, monkeypatch, code, message):
    def failing(table, where, **kwargs):
        raise OSError(code, "simulated")

    monkeypatch.setattr(pq, "write_table", failing)
    with pytest.raises(UserError, match=message):
        shards.write_shard(synthetic_table(2), tmp_path / "t" / "e.parquet")
    assert list((tmp_path / "t").iterdir()) == []


def test_output_under_a_file_is_a_user_error(tmp_path):
    (tmp_path / "file").write_text("not a directory")
    with pytest.raises(UserError, match="cannot write"):
        shards.check_writable(tmp_path / "file" / "data")
    with pytest.raises(UserError, match="cannot write"):
        shards.write_shard(synthetic_table(2), tmp_path / "file" / "t" / "e.parquet")


def test_invalid_table_is_refused_before_writing(tmp_path):
    table = synthetic_table(2)
    table = table.set_column(
        table.schema.get_field_index("weather"), "weather", [["sunny", "snowy"]]
    )
    with pytest.raises(schemas.SchemaError, match="weather"):
        shards.write_shard(table, tmp_path / "e.parquet")
    assert not (tmp_path / "e.parquet").exists()


def test_json_is_written_atomically(tmp_path):
    shards.write_json({"a": [1, 2]}, tmp_path / "_manifest.json")
    shards.write_json({"a": [3]}, tmp_path / "_manifest.json")
    assert json.loads((tmp_path / "_manifest.json").read_text()) == {"a": [3]}
    assert [p.name for p in tmp_path.iterdir()] == ["_manifest.json"]
