from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import schemas
from schemas import codecs
from tests.synthetic import synthetic_table, write_shards
from training import data, decode
from training.errors import UserError
from training.targets import centres_to_objects, decode_centres, render_density, visible_boxes


@pytest.fixture(scope="module")
def shards(tmp_path_factory) -> Path:
    return write_shards(tmp_path_factory.mktemp("shards"), episodes=3, frames=5)


def test_frame_numbers_follow_pandas_order(shards):
    index = data.scan(shards)
    df = pd.read_parquet(shards, columns=["episode_id", "frame"])
    assert list(zip(index.episode_id, index.frame)) == list(zip(df.episode_id, df.frame))
    sample = data.read_frames(index.iloc[[7]], output_px=32)[0]
    assert (sample["episode_id"], sample["frame"]) == (df.episode_id[7], df.frame[7])


def test_split_never_puts_an_episode_on_both_sides(shards):
    index = data.scan(shards)
    for fraction in (0.2, 0.5, 0.9):
        is_val = data.split(index, fraction, seed=3)
        val, train = set(index.episode_id[is_val]), set(index.episode_id[~is_val])
        assert val and train and not val & train
        streamed = {s["episode_id"] for s in data.FrameStream(index[~is_val], 32, shuffle=True)}
        assert streamed == train
    is_val = data.split(index, val_towns=("beta",))
    assert set(index.town[is_val]) == {"beta"} and set(index.town[~is_val]) == {"alpha"}
    with pytest.raises(UserError, match="no town gamma"):
        data.split(index, val_towns=("gamma",))


def test_ranks_share_the_frames_without_overlap(shards):
    index = data.scan(shards)
    seen = []
    for rank in (0, 1):
        stream = data.FrameStream(index, 32, shuffle=True, seed=1, rank=rank, world=2)
        stream.set_epoch(4)
        seen.append([(s["episode_id"], s["frame"]) for s in stream])
    assert abs(len(seen[0]) - len(seen[1])) <= 1
    assert not set(seen[0]) & set(seen[1])
    assert set(seen[0]) | set(seen[1]) == set(zip(index.episode_id, index.frame))


def test_shuffle_depends_on_seed_and_epoch_only(shards):
    index = data.scan(shards)

    def order(epoch):
        stream = data.FrameStream(index, 32, shuffle=True, seed=0, buffer_size=4)
        stream.set_epoch(epoch)
        return [(s["episode_id"], s["frame"]) for s in stream]

    assert order(1) == order(1) != order(2)
    assert sorted(order(1)) == sorted(zip(index.episode_id, index.frame))


def test_loader_batches_have_documented_shapes(shards):
    index = data.scan(shards)
    batch = next(iter(data.make_loader(data.FrameStream(index, 32), 4, num_workers=1)))
    assert (
        batch["image"].shape == (4, 3, 256, 256) and batch["image"].dtype.is_floating_point is False
    )
    assert batch["lidar"].shape == (4, 4, 256, 256)
    assert batch["waypoints"].shape == (4, 4, 2) and batch["heatmap"].shape == (4, 3, 32, 32)
    assert batch["bev"].shape == (4, 32, 32) and batch["traffic"].shape == (4, 2)
    assert batch["centre_reg"].shape[-1] == 6 and batch["weather"].shape == (4,)


def test_targets_decode_back_to_the_boxes():
    boxes = {
        "t": np.array([0, 0, 1, 2]),
        "x": np.array([10.3, 2.0, -5.0, 31.9]),  # -5 m: behind the ego, off the grid
        "y": np.array([-3.7, 15.9, 0.0, 0.1]),
        "yaw": np.array([0.4, -2.0, 0.0, 3.0]),
        "length": np.array([4.5, 0.5, 4.0, 4.0]),
        "width": np.array([1.8, 0.5, 2.0, 2.0]),
    }
    R = 64
    t = render_density(boxes, R)
    assert t["heatmap"].max() == 1.0 and t["centre_mask"].sum(1).tolist() == [2, 0, 1]
    objs = centres_to_objects(t["centre_index"][0], t["centre_reg"][0], t["centre_mask"][0], R)
    near_first = np.array([[10.3, -3.7, 1.8, 4.5, 0.4], [2.0, 15.9, 0.5, 0.5, -2.0]])
    np.testing.assert_allclose(objs[:, 1:], near_first, atol=1e-5)
    # The heatmap's peaks, read with a dense regression map, give the same centres.
    import torch

    reg = torch.zeros(1, 6, R, R)
    reg.view(1, 6, -1)[0, :, t["centre_index"][0, :2]] = torch.tensor(t["centre_reg"][0, :2]).T
    decoded = decode_centres(torch.tensor(t["heatmap"][:1]), reg, threshold=0.99)[0]
    by_x = decoded[np.argsort(-decoded[:, 1])]
    np.testing.assert_allclose(by_x[:, 1:3], near_first[:, :2], atol=1e-5)


def test_bad_directories_give_clear_errors(tmp_path):
    with pytest.raises(UserError, match="no such file or directory"):
        data.scan(tmp_path / "missing")
    with pytest.raises(UserError, match="no shards"):
        data.scan(tmp_path)
    (tmp_path / "notes.parquet").write_text("not parquet")
    with pytest.raises(UserError, match="notes.parquet: not a Parquet shard"):
        data.scan(tmp_path)
    (tmp_path / "notes.parquet").unlink()
    table = synthetic_table(2)
    meta = dict(table.schema.metadata)
    meta[schemas.META_SCHEMA_VERSION.encode()] = b"2.0"
    pq.write_table(table.replace_schema_metadata(meta), tmp_path / "new.parquet")
    with pytest.raises(UserError, match="schema version 2.0"):
        data.scan(tmp_path)
    pq.write_table(synthetic_table(2).drop_columns(["boxes"]), tmp_path / "new.parquet")
    with pytest.raises(UserError, match="missing column 'boxes'"):
        data.scan(tmp_path)


def test_keys_give_the_streamed_order(shards):
    index = data.scan(shards)
    for shuffle in (True, False):
        stream = data.FrameStream(index, 32, shuffle=shuffle, seed=5, buffer_size=3, open_units=2)
        stream.set_epoch(2)
        assert list(stream.keys()) == [(s["episode_id"], s["frame"]) for s in stream]


def _paper_scale_index(episodes: int, frames: int) -> pd.DataFrame:
    """The index of `episodes` one-row-group shards of `frames` frames (no files behind it)."""
    return pd.DataFrame(
        {
            "path": np.repeat([f"/none/e{e}.parquet" for e in range(episodes)], frames),
            "row_group": 0,
            "row": np.tile(np.arange(frames), episodes),
            "episode_id": np.repeat([f"e{e}" for e in range(episodes)], frames),
            "town": "t",
            "frame": np.tile(np.arange(frames), episodes),
        }
    )


def test_batches_mix_many_episodes_of_a_large_build():
    # 400 episodes of 360 frames, each one row group (as datagen writes them): a whole-group
    # reader gave batches of 32 frames from ~6 episodes; interleaving 64 open groups, >= 16.
    index = _paper_scale_index(400, 360)
    stream = data.FrameStream(index, 64, shuffle=True, buffer_size=512, open_units=64)
    counts, seen = [], []
    for worker in (0, 1):
        keys = list(stream.keys(worker, 2))
        seen += keys
        counts += [len({e for e, _ in keys[i : i + 32]}) for i in range(0, len(keys) - 31, 32)]
    assert sorted(seen) == sorted(zip(index.episode_id, index.frame))  # each frame once
    assert np.mean(counts) >= 16
    whole = data.FrameStream(index, 64, shuffle=True, buffer_size=512, open_units=1)
    keys = list(whole.keys(0, 2))
    assert np.mean([len({e for e, _ in keys[i : i + 32]}) for i in range(0, 3200, 32)]) < 8


def test_downsampling_keeps_lane_markings():
    bev = np.zeros((256, 256), np.uint8)
    bev[:, 64:192] = 1  # a 16 m road
    bev[:, 127] = 2  # a one-pixel (12 cm) centre line
    small = decode.downsample_bev(bev, 64)
    assert small.shape == (64, 64)
    assert (small[:, 31] == 2).all() and (small == 2).sum() == 64
    assert (small[:, 16:31] == 1).all() and (small[:, :16] == 0).all()
    assert (decode.downsample_bev(bev, 256) == bev).all()


def test_detection_targets_need_lidar_hits():
    boxes = {
        "track_id": np.array(["seen", "seen", "hidden", "hidden", "late"], object),
        "t": np.array([0, 1, 0, 2, 1]),
        "lidar_points": np.array([12, 0, 3, 0, 0]),
    }
    kept = visible_boxes(boxes, min_lidar_points=8)
    assert kept["track_id"].tolist() == ["seen", "seen"] and kept["t"].tolist() == [0, 1]
    assert len(visible_boxes(boxes, 0)["t"]) == 5


def test_targets_and_eval_truth_skip_agents_without_lidar_hits(tmp_path):
    table = synthetic_table(2, "e-0-0", "alpha")
    boxes = table.column("boxes").to_pylist()
    for frame in boxes:
        for box in frame:
            if box["track_id"] == "veh1" and box["t"] == 0:
                box["lidar_points"] = 2  # veh1 hidden, veh0 seen (40 hits)
    table = table.set_column(
        table.schema.get_field_index("boxes"),
        table.schema.field("boxes"),
        pa.array(boxes, table.schema.field("boxes").type),
    )
    (tmp_path / "alpha").mkdir()
    pq.write_table(table, tmp_path / "alpha" / "e-0-0.parquet")
    sample = data.read_frames(data.scan(tmp_path).iloc[[0]], 64)[0]
    assert sample["centre_mask"].sum(1).tolist() == [1, 1, 1]
    everyone = data.read_frames(data.scan(tmp_path).iloc[[0]], 64, min_lidar_points=0)[0]
    assert everyone["centre_mask"].sum(1).tolist() == [2, 2, 2]


def _with_ground_t(table, ground):
    """`table` with its `lidar_ground_t` column (added or replaced) holding `ground`."""
    column = pa.array([codecs.encode_lidar_ground(g) for g in ground], pa.binary())
    i = table.schema.get_field_index(data.GROUND_T)
    if i >= 0:
        return table.set_column(i, data.GROUND_T, column)
    return table.append_column(data.GROUND_T, column)


def test_single_frame_lidar_reads_the_current_sweeps_ground_hits(tmp_path):
    table = synthetic_table(3, "e-0-0", "alpha")
    ground = [np.full((256, 256), 7 + i, np.uint8) for i in range(3)]
    (tmp_path / "new" / "alpha").mkdir(parents=True)
    pq.write_table(_with_ground_t(table, ground), tmp_path / "new" / "alpha" / "e-0-0.parquet")
    index = data.scan(tmp_path / "new")
    multi = data.read_frames(index, 32)
    single = list(data.FrameStream(index, 32, single_frame_lidar=True))
    assert [s["lidar"].shape for s in single] == [(2, 256, 256)] * 3
    for i, (m, s) in enumerate(zip(multi, single)):
        assert m["lidar"].shape == (4, 256, 256)
        assert (s["lidar"][0] == 7 + i).all()  # lidar_ground_t, not ch0's three-sweep sum
        assert (s["lidar"][1] == m["lidar"][1]).all()  # above-ground hits at t
    # A dataset written before the column existed: one clear error for the ablation only.
    (tmp_path / "old" / "alpha").mkdir(parents=True)
    # a schema 1.0 shard: no such column, and 1.0 in its metadata
    old_meta = {**table.schema.metadata, schemas.META_SCHEMA_VERSION.encode(): b"1.0"}
    old_table = table.drop_columns([data.GROUND_T]).replace_schema_metadata(old_meta)
    pq.write_table(old_table, tmp_path / "old" / "alpha" / "e-0-0.parquet")
    old = data.scan(tmp_path / "old")
    assert len(list(data.FrameStream(old, 32))) == 3
    with pytest.raises(UserError, match="no 'lidar_ground_t' column.*--single-frame-lidar"):
        data.FrameStream(old, 32, single_frame_lidar=True)
