"""The data/ layout (issue 14.1): data/README.md beside the shards, which `datagen build`
writes to data/shards/ by default; the README's pandas line reads them, `train fit --shards
data/` trains on them, and no file of the repository sits where pandas would read it."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "data" / "README.md"


def _run(*args, cwd) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        [sys.executable, "-m", *map(str, args)],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert proc.returncode == 0, proc.stderr
    return proc


@pytest.mark.slow
def test_readme_line_reads_the_default_build_and_train_fit_reads_data(tmp_path, monkeypatch):
    (tmp_path / "data").mkdir()
    shutil.copy(README, tmp_path / "data" / "README.md")
    # 4 weathers x 1 frame of real SUMO driving, into the default --out
    _run(
        "datagen.cli",
        "build",
        "--town",
        "grid_small",
        "--frames",
        "4",
        "--workers",
        "1",
        cwd=tmp_path,
    )
    assert (tmp_path / "data" / "shards" / "_manifest.json").is_file()

    line = re.search(r'^df = (pd\.read_parquet\("[^"]+"\))', README.read_text(), re.M)
    assert line, "data/README.md shows no one-line pandas read"
    monkeypatch.chdir(tmp_path)  # where the README sits: data/README.md
    df = eval(line.group(1), {"pd": pd})  # the README's own line, as shown
    assert len(df) == 4 and df.weather.nunique() == 4

    out = tmp_path / "runs" / "t"
    fit = _run(
        "training.cli",
        "fit",
        "--shards",
        "data/",
        "--config",
        "tiny",
        "--epochs",
        "1",
        "--workers",
        "0",
        "--val-fraction",
        "0",
        "--out",
        out,
        cwd=tmp_path,
    )
    assert "4 frames" in fit.stdout + fit.stderr and (out / "last.pt").is_file()
    _run("datagen.cli", "validate", "data/shards", cwd=tmp_path)


def test_no_repository_file_sits_among_the_shards():
    shards = ROOT / "data" / "shards"
    tracked = subprocess.run(
        ["git", "ls-files", "data"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    assert tracked == ["data/README.md"]
    if shards.is_dir():  # a local build: only shards and `_` files
        for p in shards.rglob("*"):
            if p.is_file():
                assert p.suffix == ".parquet" or p.name.startswith(("_", ".")), p
