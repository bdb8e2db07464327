"""A fake `datagen build`: the real build machinery (plan, executors, shards, manifest) with
synthetic episodes (tests/synthetic.py) in place of SUMO's, a few ms an episode, so tests can
build hundreds of episodes, kill workers and resume.

    fake_config     a BuildConfig over two fake towns
    fake_runner     a deterministic stand-in for run_episode (every fourth seed ends early)
    fake_build      build.build(fake_config(...), out, runner=fake_runner)
    fake_build_main the `datagen build` command line with both in place (subprocess builds)
"""

from __future__ import annotations

import functools
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa

import schemas
from datagen.dataset import build, plan
from tests.synthetic import synthetic_table

FAKE_TOWNS = (
    plan.Town("alpha", "/nonexistent/alpha.net.xml", "a" * 64, False),
    plan.Town("beta", "/nonexistent/beta.net.xml", "b" * 64, False),
)


@dataclass
class FakeResult:
    table: pa.Table
    end_reason: str | None
    stats: dict


def fake_runner(spec, sensors, progress):
    """A deterministic stand-in for run_episode: every fourth seed ends at half its frames."""
    early = spec.seed % 4 == 0
    rows = spec.n_frames // 2 if early else spec.n_frames
    delay = float(os.environ.get("FAKE_FRAME_SECONDS", "0"))
    for _ in range(rows):
        time.sleep(delay)
        if progress:
            progress(1)
    seed = spec.seed % 1000
    # flat images: a few ms an episode, so that tests can build hundreds of them
    table = synthetic_table(rows, spec.episode_id, spec.town, spec.weather, seed, noise=False)
    i = table.schema.get_field_index("behaviour")
    field = table.schema.field(i)
    behaviour = pa.array([spec.behaviour] * rows, pa.string()).cast(field.type)
    table = table.set_column(i, field, behaviour)
    sha = {t.name: t.network_sha256 for t in FAKE_TOWNS}[spec.town]
    meta = {**table.schema.metadata, schemas.META_NETWORK_HASH.encode(): sha.encode()}
    table = table.replace_schema_metadata(meta)
    return FakeResult(table, "route_end" if early else None, {"collisions": 0, "teleports": 0})


def fake_config(frames=96, seed=7, episode_seconds=8.0) -> plan.BuildConfig:
    return plan.BuildConfig(
        towns=FAKE_TOWNS, frames=frames, seed=seed, episode_seconds=episode_seconds, sensors={}
    )


def fake_build(out, workers=2, **kw):
    return build.build(
        fake_config(**kw), Path(out), workers=workers, runner=fake_runner, progress_bar=False
    )


def fake_build_main(out: str, workers: str, executor: str = "process") -> None:
    """Entry point of the subprocess builds (kill -9, Ctrl-C, SIGTERM): the `datagen build`
    command line itself, with the synthetic config and runner in place of SUMO's."""
    from datagen import cli

    build.config_from_args = lambda args: fake_config()
    build.build = functools.partial(build.build, runner=fake_runner)
    argv = ["build", "--out", out, "--workers", workers, "--executor", executor, "--no-progress"]
    sys.exit(cli.main(argv))
