"""`datagen validate`: every problem is found, named per file on one line, and fails the run."""

import argparse
import json
import shutil

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import schemas
from datagen.dataset import shards, validate
from datagen.dataset.manifest import MANIFEST
from tests.fakes import fake_build


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "data"
    fake_build(out, workers=1, frames=32)
    return out


@pytest.fixture
def copy(dataset, tmp_path):
    shutil.copytree(dataset, tmp_path / "data")
    return tmp_path / "data"


def run(path, capsys):
    status = validate.run(argparse.Namespace(path=path, workers=1))
    out, err = capsys.readouterr()
    return status, out, err.splitlines()


def first_shard(root):
    return sorted(root.glob("*/*.parquet"))[0]


def test_a_built_dataset_validates(dataset, capsys):
    status, out, err = run(dataset, capsys)
    assert (status, err) == (0, [])
    assert out.startswith("ok: ") and "32 frames" in out


def test_the_parent_of_a_build_names_the_build_to_validate(copy, capsys):
    status, _, err = run(copy.parent, capsys)  # like `datagen validate data` for data/shards
    assert status == 1
    assert [e for e in err if "_manifest.json: missing" in e] == [
        f"_manifest.json: missing (not a directory written by datagen build?); "
        f"datagen build wrote {copy}: validate that"
    ]


def test_a_corrupt_shard_is_one_line_and_fails(copy, capsys):
    path = first_shard(copy)
    data = bytearray(path.read_bytes())
    data[len(data) // 2 : len(data) // 2 + 4096] = b"\0" * 4096  # page data and headers garbled
    path.write_bytes(bytes(data))
    status, _, err = run(copy, capsys)
    assert status == 1
    assert err and all(line.startswith(str(path.relative_to(copy))) for line in err)
    assert not any("Traceback" in line for line in err)


def test_a_truncated_shard_is_reported(copy, capsys):
    path = first_shard(copy)
    path.write_bytes(path.read_bytes()[:1000])
    status, _, err = run(copy, capsys)
    rel = str(path.relative_to(copy))
    assert status == 1
    assert err == [f"{rel}: not a readable Parquet file" + err[0].split("file", 1)[1]]


def _rewrite(path, table):
    path.unlink()
    shards.write_shard(table, path, validate=False)


def test_an_undecodable_image_is_reported(copy, capsys):
    path = first_shard(copy)
    table = pq.read_table(path)
    images = [b"not a jpeg"] + table.column("image").to_pylist()[1:]
    i = table.schema.get_field_index("image")
    _rewrite(path, table.set_column(i, table.schema.field(i), pa.array(images, pa.binary())))
    status, _, err = run(copy, capsys)
    assert status == 1
    assert err == [
        f"{path.relative_to(copy)}: frame 0: image does not decode (not a decodable image)"
    ]


def test_another_schema_version_is_reported(copy, capsys):
    path = first_shard(copy)
    table = pq.read_table(path)
    meta = {**table.schema.metadata, schemas.META_SCHEMA_VERSION.encode(): b"2.0"}
    _rewrite(path, table.replace_schema_metadata(meta))
    status, _, err = run(copy, capsys)
    assert status == 1 and "schema version 2.0 is not readable" in err[0]


def test_manifest_row_counts_and_listing_are_checked(copy, capsys):
    manifest = json.loads((copy / MANIFEST).read_text())
    first = next(e for e in manifest["episodes"] if e["rows"])
    first["rows"] += 1
    (copy / MANIFEST).write_text(json.dumps(manifest))
    stray = copy / "alpha" / "alpha-9-0000.parquet"
    shutil.copy(copy / first["file"], stray)
    status, _, err = run(copy, capsys)
    assert status == 1
    assert f"{first['file']}: {first['rows'] - 1} rows, _manifest.json says {first['rows']}" in err
    assert (
        "alpha/alpha-9-0000.parquet: holds episode 'alpha-7-0000' but is named 'alpha-9-0000.parquet'"
        in err
    )
    assert "alpha/alpha-9-0000.parquet: not listed in _manifest.json" in err


def test_an_incomplete_build_is_reported(copy, capsys):
    manifest = json.loads((copy / MANIFEST).read_text())
    manifest["status"] = "building"
    (copy / MANIFEST).write_text(json.dumps(manifest))
    status, _, err = run(copy, capsys)
    assert status == 1 and "the build is not complete" in err[0]


def test_parallel_validation_finds_the_same(copy, capsys):
    path = first_shard(copy)
    path.write_bytes(b"garbage")
    serial = validate.validate_dir(copy, workers=1)
    parallel = validate.validate_dir(copy, workers=2)
    assert serial[1] == parallel[1] and [r.problems for r in serial[0]] == [
        r.problems for r in parallel[0]
    ]
