"""Every head learns on real frames: a tiny SUMO build, a few epochs of `train fit`."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from training import fit

pytestmark = pytest.mark.slow  # minutes of building, training or driving

ROOT = Path(__file__).resolve().parents[1]


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
    # 6 epochs of 6 steps on the same 48 frames, through `train fit` (its loop and loader). A
    # head whose output is cut off from its loss, or never updated, keeps its first epoch's
    # loss and fails. Through the CLI, as a user runs it (it sets OMP_WAIT_POLICY=PASSIVE,
    # without which spinning OpenMP threads slow this test ten-fold on a busy 2-core machine).
    out = tmp_path / "run"
    command = [sys.executable, "-m", "training.cli", "fit", "--shards", str(build), "--config"]
    command += ["tiny", "--epochs", "6", "--val-fraction", "0", "--workers", "0"]
    command += ["--device", "cpu", "--out", str(out)]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    epochs = [json.loads(line) for line in (out / fit.METRICS).read_text().splitlines()]
    first, last = epochs[0]["train"], epochs[-1]["train"]
    change = {t: round(last[t] / first[t], 3) for t in first}
    for term in ("wp", "heat", "reg", "bev", "light", "stop", "weather"):
        assert last[term] < 0.95 * first[term], (term, change)
    assert last["total"] < 0.5 * first["total"], change
