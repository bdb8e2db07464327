"""Same seed, same bytes: a small real build (SUMO, sensors, labels, shard writer) is pinned
by the sha256 of its shard files, so a pure speed-up or a pure move cannot change the data.

How to update the stored hashes: ONLY together with a change of what the data is, i.e. a bump
of the generator version (datagen.episode.DATA_VERSION / scene.SCENE_VERSION) or of the
schema version, documented in data/README.md. Run
    PYTHONPATH=$PWD .venv/bin/python -m tests.test_identical
which prints the new digests (and one per column, to see what changed), and paste them below.
A mismatch without such a bump is a bug in the change under test, not in this file.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from datagen import episode
from datagen.dataset import shards
from datagen.world import towns
from tests.scenes import build_test_network

# (episode_id, seed, weather, behaviour, frames): sunny exercises shadows, rainy the LiDAR
# weather draws, the rain streaks and the wet road.
EPISODES = (
    ("grid3-3-0", 3, "sunny", "normal", 5),
    ("grid3-8-1", 8, "rainy", "aggressive", 3),
)
EXPECTED_SHA256 = {  # scene v2, data v10, schema 1.2 (config_json: recovery_*, driver)
    "grid3-3-0": "a01f75be744b2ff1a0e4bdae94627b7ca935d72cb21582dbf18dfb0c8764453b",
    "grid3-8-1": "ec6a9c608b172db2eb398c7b8a6ce49ee393310b8ad9a7ff92c997e67f6f2f5a",
}


def build_small(out: Path) -> dict[str, Path]:
    """Run the EPISODES on the grid3 test network and write one shard each under `out`."""
    net = build_test_network(out / "grid3.net.xml")
    towns._strip_header(net)  # netconvert's dated header comment would change the hash
    paths = {}
    for episode_id, seed, weather, behaviour, frames in EPISODES:
        spec = episode.EpisodeSpec(episode_id, "grid3", str(net), seed, weather, behaviour, frames)
        result = episode.run_episode(spec)
        path = shards.shard_path(out, "grid3", episode_id)
        path.parent.mkdir(parents=True, exist_ok=True)
        shards.write_shard(result.table, path)
        paths[episode_id] = path
    return paths


def file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def column_sha256(path: Path) -> dict[str, str]:
    """Per-column digests (of the column's Python values), to tell which column changed."""
    table = pq.read_table(path)
    return {
        name: hashlib.sha256(repr(table.column(name).to_pylist()).encode()).hexdigest()[:16]
        for name in table.column_names
    }


@pytest.fixture(scope="module")
def built(tmp_path_factory, fresh_cache):
    return build_small(tmp_path_factory.mktemp("data"))


@pytest.mark.parametrize("episode_id", sorted(EXPECTED_SHA256))
def test_small_build_is_byte_identical_to_the_stored_hash(built, episode_id):
    path = built[episode_id]
    assert file_sha256(path) == EXPECTED_SHA256[episode_id], (
        f"{episode_id}: shard bytes changed (columns: {column_sha256(path)}); see the module "
        "docstring for when updating the hash is legitimate"
    )


if __name__ == "__main__":
    os.environ.setdefault("IIDSU_CACHE", tempfile.mkdtemp(prefix="iidsu-identical-"))
    for eid, p in build_small(Path(tempfile.mkdtemp(prefix="iidsu-identical-data-"))).items():
        print(f'    "{eid}": "{file_sha256(p)}",')
        print(f"    # {column_sha256(p)}")
