"""Every head learns on real frames: a tiny SUMO build, a few epochs of `train fit`."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest

from training import fit
from training.config import PRESETS

ROOT = Path(__file__).resolve().parents[1]
TINY_MODEL, TINY_TRAIN = PRESETS["tiny"]


@pytest.fixture(scope="module")
def build(tmp_path_factory) -> Path:
    """One town, four weathers, 48 frames: four 12-frame episodes of real SUMO driving."""
    out = tmp_path_factory.mktemp("learn") / "data"
    command = [sys.executable, "-m", "datagen.cli", "build", "--town", "downtown"]
    command += ["--frames", "48", "--episode-seconds", "6", "--seed", "5", "--workers", "2"]
    done = subprocess.run(
        [*command, "--out", str(out), "--no-progress"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return out


def test_loss_falls_on_every_head(build, tmp_path):
    # 8 epochs of 6 steps on the same 48 frames, through the real loop and loader. A head whose
    # output is cut off from its loss, or never updated, keeps its first epoch's loss and fails.
    cfg = dataclasses.replace(
        TINY_TRAIN,
        shards=str(build),
        out=str(tmp_path / "run"),
        epochs=8,
        num_workers=0,
        val_fraction=0.0,
        val_metrics=False,
    )
    fit.fit(TINY_MODEL, cfg, device="cpu")
    epochs = [
        json.loads(line) for line in (tmp_path / "run" / fit.METRICS).read_text().splitlines()
    ]
    first, last = epochs[0]["train"], epochs[-1]["train"]
    for term in ("wp", "heat", "reg", "bev", "light", "stop", "weather"):
        assert last[term] < 0.8 * first[term], (term, first[term], last[term])
    assert last["total"] < 0.5 * first["total"]
