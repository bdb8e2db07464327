"""bench/learn.py across sessions (issue 46): the --record file keeps finished seeds, refuses
a run of another setting, and --paired gives B - A with a t interval over the seeds."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("bench_learn", ROOT / "bench" / "learn.py")
learn = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(learn)


def _record(path: Path, arch: str, ade: list[float]) -> Path:
    seeds = {
        str(s): {"figures": {"ade_m": v, "weather_accuracy": 0.9}, "build": {"seed": 41}}
        for s, v in enumerate(ade)
    }
    doc = {"arch": arch, "val_towns": "downtown", "epochs": 6, "fit_args": [], "seeds": seeds}
    path.write_text(json.dumps(doc))
    return path


def test_paired_gives_the_mean_difference_and_its_t_interval(tmp_path):
    a = json.loads(_record(tmp_path / "a.json", "paper", [1.0, 1.0, 1.0]).read_text())
    b = json.loads(_record(tmp_path / "b.json", "ours", [2.0, 3.0, 4.0]).read_text())
    _, out = learn.paired(a, b)
    assert out["ade_m"]["diff"] == [1.0, 2.0, 3.0] and out["ade_m"]["mean"] == 2.0
    half = 4.303 * 1.0 / 3**0.5  # t(2 dof) * sample std / sqrt(n)
    assert out["ade_m"]["ci95"] == pytest.approx([2.0 - half, 2.0 + half])
    assert out["weather_accuracy"]["ci95"] == [0.0, 0.0]


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "bench" / "learn.py"), *args],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip


def test_recorded_seeds_are_not_trained_again_and_another_setting_is_refused(tmp_path):
    record = _record(tmp_path / "paper.json", "paper", [0.7, 0.8, 0.9])
    common = ["--record", str(record), "--val-towns", "downtown", "--out", str(tmp_path / "o")]
    # every seed is recorded: the table comes from the record, no build, no fit
    done = _run(*common, "--seeds", "0,1,2", "--data", str(tmp_path / "none"))
    assert done.returncode == 0, done.stderr
    assert "3 seed(s)" in done.stdout and "0.8000 +- 0.1000" in done.stdout
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["figures"]["ade_m"]["seeds"] == {"0": 0.7, "1": 0.8, "2": 0.9}
    refused = _run(*common, "--seeds", "0", "--arch", "ours")
    assert refused.returncode != 0 and "made with" in refused.stderr
    both = _run("--paired", str(record), str(_record(tmp_path / "ours.json", "ours", [0.6] * 3)))
    assert both.returncode == 0 and "ade_m" in both.stdout, both.stderr
