import re
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import schemas
from schemas import codecs
from tests.synthetic import synthetic_table


def test_round_trip_through_parquet_and_pandas(tmp_path):
    table = synthetic_table(5)
    schemas.validate(table)
    pq.write_table(table, tmp_path / "a.parquet")
    (tmp_path / "_manifest.json").write_text("{}")  # non-data files start with _
    df = pd.read_parquet(tmp_path)
    assert len(df) == 5 and list(df.columns) == list(schemas.COLUMNS)
    assert (df.frame.to_numpy() == np.arange(5)).all()
    back = pq.read_table(tmp_path / "a.parquet")
    schemas.validate(back)
    assert schemas.check_version(back.schema.metadata) == schemas.SCHEMA_VERSION
    for name in schemas.COLUMNS:
        assert back.schema.field(name).metadata[b"description"]


def test_rejects_missing_column():
    table = synthetic_table(2).drop_columns(["waypoints"])
    with pytest.raises(schemas.SchemaError, match="missing column 'waypoints'"):
        schemas.validate(table)


def test_a_1_0_shard_without_lidar_ground_t_still_validates():
    table = synthetic_table(2).drop_columns(["lidar_ground_t"])
    with pytest.raises(schemas.SchemaError, match="missing column 'lidar_ground_t'"):
        schemas.validate(table)  # a 1.1 file must have it
    table = table.drop_columns(["rig_shift_m", "rig_yaw_rad"])  # added in 1.2
    meta = dict(table.schema.metadata)
    meta[schemas.META_SCHEMA_VERSION.encode()] = b"1.0"
    schemas.validate(table.replace_schema_metadata(meta))  # a 1.0 file predates it
    assert schemas.ADDED_IN["lidar_ground_t"] == "1.1"


def test_a_1_1_shard_without_the_rig_columns_still_validates():
    table = synthetic_table(2).drop_columns(["rig_shift_m", "rig_yaw_rad"])
    with pytest.raises(schemas.SchemaError, match="missing column 'rig_shift_m'"):
        schemas.validate(table)  # a 1.2 file must have them
    meta = dict(table.schema.metadata)
    meta[schemas.META_SCHEMA_VERSION.encode()] = b"1.1"
    schemas.validate(table.replace_schema_metadata(meta))  # a 1.1 file predates them
    assert schemas.ADDED_IN["rig_shift_m"] == schemas.SCHEMA_VERSION == "1.2"


def test_rejects_wrong_type():
    table = synthetic_table(2)
    i = table.schema.get_field_index("frame")
    table = table.set_column(i, pa.field("frame", pa.int64()), table.column("frame").cast("int64"))
    with pytest.raises(schemas.SchemaError, match="column 'frame' has type int64"):
        schemas.validate(table)


def test_rejects_other_major_version_and_missing_version():
    table = synthetic_table(2)
    meta = dict(table.schema.metadata)
    meta[schemas.META_SCHEMA_VERSION.encode()] = b"2.0"
    with pytest.raises(schemas.SchemaError, match="schema version 2.0"):
        schemas.validate(table.replace_schema_metadata(meta))
    with pytest.raises(schemas.SchemaError, match="not an iidsu shard"):
        schemas.validate(table.replace_schema_metadata({}))


def test_rejects_unknown_category():
    table = synthetic_table(2)
    i = table.schema.get_field_index("weather")
    table = table.set_column(i, table.schema.field("weather"), pa.array(["sunny", "snowy"]))
    with pytest.raises(schemas.SchemaError, match="column 'weather' has value 'snowy'"):
        schemas.validate(table)


def test_codecs_keep_channel_order():
    rng = np.random.default_rng(0)
    bev = rng.integers(0, 255, (256, 256, 4), dtype=np.uint8)
    assert (codecs.decode_lidar_bev(codecs.encode_lidar_bev(bev)) == bev).all()
    sem = rng.integers(0, 3, (256, 256), dtype=np.uint8)
    assert (codecs.decode_bev_semantic(codecs.encode_bev_semantic(sem)) == sem).all()
    ground = rng.integers(0, 255, (256, 256), dtype=np.uint8)
    assert (codecs.decode_lidar_ground(codecs.encode_lidar_ground(ground)) == ground).all()
    red = np.zeros((64, 64, 3), np.uint8)
    red[..., 0] = 255
    assert codecs.decode_image(codecs.encode_image(red))[..., 0].mean() > 240


def test_a_lamp_two_pixels_wide_keeps_its_colour_through_the_jpeg():
    """A red signal lamp 2 px wide on a grey sky, straddling JPEG's 2x2 chroma blocks: 4:2:0
    subsampling would average its red with the grey around it (data v10 keeps 4:4:4)."""
    sky = np.full((32, 32, 3), 150, np.uint8)
    sky[11:13, 15:17] = (255, 45, 30)  # rows 11-12, columns 15-16: across block borders
    lamp = codecs.decode_image(codecs.encode_image(sky)).astype(int)[11:13, 15:17]
    redness = lamp[..., 0] - np.maximum(lamp[..., 1], lamp[..., 2])
    assert redness.min() > 150, redness


def test_bev_grid_puts_ego_at_bottom_centre():
    row, col = schemas.ego_to_bev_px(0.0, 0.0)
    assert (row, col) == (256.0, 128.0)
    row, col = schemas.ego_to_bev_px(32.0, 16.0)  # 32 m ahead, 16 m left
    assert (row, col) == (0.0, 0.0)
    x, y = schemas.bev_pixel_centres()
    assert x[0, 0] == pytest.approx(32 - 1 / 16) and y[0, 0] == pytest.approx(16 - 1 / 16)


def test_every_column_is_documented_in_data_readme():
    text = (Path(__file__).parents[1] / "data" / "README.md").read_text()
    documented = set(re.findall(r"^\| `(\w+)`", text, flags=re.M))
    missing = [c for c in schemas.COLUMNS if c not in documented]
    assert not missing, f"data/README.md does not document {missing}"
