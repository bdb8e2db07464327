"""The test suite's shared fixtures (pytest hands them to any test that names them), and the
index of the shared builders a test calls with its own arguments:

    tests/scenes.py     hand-made frames and agents in an ego's frame (EGO_POSE, agent_at,
                        frame_at), a flat road scene (flat_scene), the 3x3 SUMO test network
                        (build_test_network)
    tests/synthetic.py  schema-valid synthetic rows (synthetic_table) and shard directories laid
                        out as `datagen build` writes them (write_shards)
    tests/fakes.py      a fake `datagen build`: the real machinery, synthetic episodes
                        (fake_config, fake_runner, fake_build, fake_build_main)

A test imports from those modules and uses these fixtures; it never imports another test file.
Tests mirror the packages (tests/test_<module>.py). A test that builds, trains or drives for more
than ~20 s carries `@pytest.mark.slow`: `pytest -m "not slow"` is the inner loop, `make test`
runs everything.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from datagen.sensors.scene import StaticScene, build_static_scene
from tests.scenes import build_test_network
from tests.synthetic import write_shards


@pytest.fixture(scope="session")
def grid3(tmp_path_factory) -> tuple[Path, StaticScene]:
    """(network path, static scene) of the 3x3 test network (tests/scenes.py
    build_test_network), built once per session: SUMO's netconvert and the town mesh cost
    seconds."""
    net = build_test_network(tmp_path_factory.mktemp("grid3") / "grid3.net.xml")
    return net, build_static_scene(net)


@pytest.fixture(scope="module")
def fresh_cache(tmp_path_factory):
    """IIDSU_CACHE set to an empty directory for the module's tests: towns and static scenes
    are built anew instead of read from ~/.cache/iidsu (whose copies other runs wrote)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("IIDSU_CACHE", str(tmp_path_factory.mktemp("cache")))
        yield


@pytest.fixture(scope="module")
def synthetic_shards(tmp_path_factory) -> Path:
    """A synthetic dataset on disk, shared by a module's tests: towns alpha and beta, two
    episodes each of four frames, row groups of three (tests/synthetic.py write_shards)."""
    return write_shards(tmp_path_factory.mktemp("shards"))
