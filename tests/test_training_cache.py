import os
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import torch

from tests.synthetic import synthetic_table, write_shards
from training import cache, data, decode

R = 32


@pytest.fixture(scope="module")
def shards(tmp_path_factory) -> Path:
    # 6 shards of 5 frames, row groups of 3: streaming crosses row-group boundaries
    return write_shards(tmp_path_factory.mktemp("shards"), episodes=3, frames=5)


def _files(root: Path) -> list[str]:
    return [str(f) for f in sorted(data.scan(root).path.unique())]


def _batches(index, cached, shuffle=True, workers=0, single_frame_lidar=False) -> list[dict]:
    stream = data.FrameStream(
        index,
        R,
        shuffle=shuffle,
        seed=3,
        buffer_size=4,
        open_units=3,
        zoom_out=(0.5, 0.5),
        single_frame_lidar=single_frame_lidar,
        cache=cached,
    )
    stream.set_epoch(1)
    return list(data.make_loader(stream, 4, workers))


def _assert_same(a: list[dict], b: list[dict]) -> None:
    assert len(a) == len(b) and a
    for x, y in zip(a, b):
        assert x.keys() == y.keys()
        for k in x:
            if isinstance(x[k], torch.Tensor):
                assert x[k].dtype == y[k].dtype and torch.equal(x[k], y[k]), k
            else:
                assert x[k] == y[k], k


def _no_decoding(*args):
    raise AssertionError("a cached frame was decoded")


@pytest.mark.parametrize("workers", [0, 2])
def test_a_cache_hit_and_a_miss_give_the_same_batches(shards, tmp_path, monkeypatch, workers):
    index = data.scan(shards)
    inputs = cache.Inputs(R)
    cached = cache.prepare(_files(shards), inputs, tmp_path, 1 << 40, log=lambda m: None)
    assert set(cached) == set(_files(shards))
    for shuffle in (True, False):  # training and evaluation order
        decoded = _batches(index, None, shuffle, workers)
        with monkeypatch.context() as m:
            m.setattr(data, "decode_inputs", _no_decoding)
            _assert_same(_batches(index, cached, shuffle, workers), decoded)
    # a second prepare finds every entry and decodes nothing
    lines = []
    assert cache.prepare(_files(shards), inputs, tmp_path, 1 << 40, log=lines.append) == cached
    assert lines == []


def test_the_single_frame_ablation_caches_its_own_lidar(shards, tmp_path):
    index = data.scan(shards)
    files = _files(shards)
    both = {}
    for single in (False, True):
        cached = cache.prepare(files, cache.Inputs(R, single), tmp_path, 1 << 40, log=print)
        both[single] = cached
        got = _batches(index, cached, single_frame_lidar=single)
        assert got[0]["lidar"].shape[1] == (2 if single else 4)
        _assert_same(got, _batches(index, None, single_frame_lidar=single))
    assert not {e.dir for e in both[False].values()} & {e.dir for e in both[True].values()}


def test_the_bound_caches_the_first_shards_and_the_rest_are_decoded(shards, tmp_path):
    index = data.scan(shards)
    files = _files(shards)
    inputs = cache.Inputs(R)
    rows = pq.ParquetFile(files[0]).metadata.num_rows
    limit = int(2.5 * rows * inputs.frame_bytes())  # room for two 5-frame shards
    cached = cache.prepare(files, inputs, tmp_path, limit, log=lambda m: None)
    assert list(cached) == files[:2]
    assert sum(f.stat().st_size for f in tmp_path.rglob("*.npy")) <= limit
    _assert_same(_batches(index, cached), _batches(index, None))
    # a lower bound removes the entries past it
    assert list(cache.prepare(files, inputs, tmp_path, limit // 2, log=print)) == files[:1]
    assert len(list(tmp_path.rglob("*.npy"))) == len(cache.ARRAYS)


def test_a_changed_shard_or_input_config_gets_a_new_entry(tmp_path):
    root = write_shards(tmp_path / "shards", towns=("alpha",), episodes=1, frames=3)
    (shard,) = _files(root)
    store = tmp_path / "cache"
    first = cache.prepare([shard], cache.Inputs(R), store, 1 << 40, log=print)[shard]
    assert cache.prepare([shard], cache.Inputs(R), store, 1 << 40, log=print)[shard] == first
    other_r = cache.prepare([shard], cache.Inputs(2 * R), store, 1 << 40, log=print)[shard]
    assert other_r.dir != first.dir
    # the same path rewritten with other frames: a new entry, whose frames are the new ones
    table = synthetic_table(3, "alpha-0-0", "alpha", seed=99)
    pq.write_table(table, shard, row_group_size=3)
    second = cache.prepare([shard], cache.Inputs(R), store, 1 << 40, log=print)[shard]
    assert second.dir != first.dir
    _assert_same(_batches(data.scan(root), {shard: second}), _batches(data.scan(root), None))


def test_an_interrupted_fill_leaves_no_entry(shards, tmp_path, monkeypatch):
    files = _files(shards)
    calls = []

    def failing(rows, i, output_px):
        calls.append(i)
        if len(calls) == 4:
            raise KeyboardInterrupt  # as a user's Ctrl-C mid-shard
        return real(rows, i, output_px)

    real = decode.decode_inputs
    monkeypatch.setattr(decode, "decode_inputs", failing)
    with pytest.raises(KeyboardInterrupt):
        cache.prepare(files, cache.Inputs(R), tmp_path, 1 << 40, log=print)
    monkeypatch.undo()
    # The first shard (5 frames) was not finished: nothing but the hash memo is left.
    assert [p.name for p in tmp_path.iterdir()] == [cache.SHARD_HASHES]
    # A process killed mid-fill leaves its temporary directory: the next fill removes it.
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        text=True,
        capture_output=True,
        check=True,
    )
    stale = tmp_path / f"{cache.TMP_PREFIX}{dead.stdout.strip()}-abc"
    (stale / "image.npy").parent.mkdir()
    (stale / "image.npy").write_bytes(b"half")
    mine = tmp_path / f"{cache.TMP_PREFIX}{os.getpid()}-abc"  # a live process's fill: kept
    mine.mkdir()
    cached = cache.prepare(files, cache.Inputs(R), tmp_path, 1 << 40, log=print)
    assert not stale.exists() and mine.exists() and len(cached) == len(files)


def test_a_new_shard_set_evicts_the_least_recently_used_entries(tmp_path):
    a = write_shards(tmp_path / "a", towns=("alpha",), episodes=2, frames=3)
    b = write_shards(tmp_path / "b", towns=("beta",), episodes=2, frames=3)
    inputs = cache.Inputs(R)
    store = tmp_path / "cache"
    limit = int(2.5 * 3 * inputs.frame_bytes())
    first = cache.prepare(_files(a), inputs, store, limit, log=print)
    assert len(first) == 2
    second = cache.prepare(_files(b), inputs, store, limit, log=print)
    assert len(second) == 2
    assert not any(Path(e.dir).exists() for e in first.values())


def test_a_deleted_cache_falls_back_to_decoding(shards, tmp_path):
    index = data.scan(shards)
    store = tmp_path / "cache"
    cached = cache.prepare(_files(shards), cache.Inputs(R), store, 1 << 40, log=print)
    for entry in list(cached.values())[:3]:
        for f in Path(entry.dir).iterdir():
            f.unlink()
        Path(entry.dir).rmdir()
    _assert_same(_batches(index, cached, workers=2), _batches(index, None, workers=2))
