import json
from pathlib import Path

import cv2
import pytest

from tests.synthetic import write_shards
from training.cli import main

pytestmark = pytest.mark.slow  # minutes of building, training or driving


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[Path, Path]:
    """Shards and a run directory trained by the lead's demo command (on fewer frames)."""
    root = tmp_path_factory.mktemp("cli")
    shards = write_shards(root / "data", episodes=2, frames=6)
    out = root / "runs" / "demo"
    argv = ["fit", "--shards", str(shards), "--config", "tiny", "--epochs", "1", "--out", str(out)]
    assert main(argv + ["--workers", "0"]) == 0
    return shards, out


def test_demo_commands_write_checkpoint_and_figure(run):
    shards, out = run
    assert (out / "last.pt").is_file() and (out / "metrics.jsonl").read_text().count("\n") == 1
    png = out / "show.png"
    argv = ["show", "--ckpt", str(out / "last.pt"), "--shards", str(shards), "--frame", "10"]
    assert main(argv + ["--out", str(png)]) == 0
    assert cv2.imread(str(png)).shape == (2 * (256 + 18), 4 * 256, 3)


def test_eval_writes_every_metric(run, capsys):
    shards, out = run
    argv = ["eval", "--ckpt", str(out / "last.pt"), "--shards", str(shards), "--split", "val"]
    assert main(argv + ["--workers", "0"]) == 0
    result = json.loads((out / "last.eval.json").read_text())
    assert result["frames"] == 6  # one of four episodes held out
    assert {"planning", "constant_velocity", "detection", "bev", "traffic", "weather"} <= set(
        result
    )
    assert set(result["detection"]["t"]) == {"ap@0.5m", "ap@1m", "ap@2m", "ap@4m", "map"}
    assert len(result["weather"]["confusion"]) == 4
    assert "ADE" in capsys.readouterr().out


def test_analyze_compares_each_aux_head_with_planning(run):
    _, out = run
    assert main(["analyze", "--ckpt", str(out / "last.pt"), "--frames", "8"]) == 0
    result = json.loads((out / "last.analyze.json").read_text())
    sims = result["cosine_similarity"]
    assert set(sims) == {"detection", "bev", "traffic", "weather"}
    assert all(0 < v <= 1 for v in sims.values())
    for model in ("trained", "untrained"):  # the untrained reference line, same forms
        assert set(result[model]) == set(sims)
        for forms in result[model].values():
            assert set(forms) == {"raw", "centred", "kernel"}
            assert all(-1 <= v <= 1 for v in forms.values())
    assert {h: f["raw"] for h, f in result["trained"].items()} == sims


def _bad(tmp_path: Path, run) -> dict[str, tuple[list[str], str]]:
    shards, out = run
    ckpt = str(out / "last.pt")
    (tmp_path / "empty").mkdir()
    (tmp_path / "junk.pt").write_text("junk")
    return {
        "missing dir": (["fit", "--shards", str(tmp_path / "nope")], "no such file or directory"),
        "empty dir": (["fit", "--shards", str(tmp_path / "empty")], "no shards"),
        "zero epochs": (["fit", "--epochs", "0"], "must be positive"),
        "bad fraction": (["fit", "--val-fraction", "1.5"], "must be in [0, 1)"),
        "bad R": (
            ["fit", "--config", "tiny", "--output-px", "48", "--shards", str(shards)],
            "output_px",
        ),
        "no checkpoint": (
            ["eval", "--ckpt", str(tmp_path / "x.pt"), "--shards", str(shards)],
            "no such checkpoint",
        ),
        "junk checkpoint": (
            ["show", "--ckpt", str(tmp_path / "junk.pt"), "--shards", str(shards)],
            "not a checkpoint",
        ),
        "frame range": (
            ["show", "--ckpt", ckpt, "--shards", str(shards), "--frame", "999"],
            "frames 0..23",
        ),
        "resume nothing": (
            ["fit", "--resume", "--out", str(tmp_path / "fresh")],
            "no such checkpoint",
        ),
        "resume done": (["fit", "--resume", "--out", str(out)], "has finished 1 of 1 epochs"),
        "resume change": (
            ["fit", "--resume", "--out", str(out), "--lr", "0.5"],
            "--lr: cannot change on --resume",
        ),
        "unknown town": (
            ["fit", "--shards", str(shards), "--config", "tiny", "--val-towns", "x"],
            "no town x",
        ),
        "unknown command": (["dance"], "invalid choice"),
    }


@pytest.mark.parametrize(
    "case",
    [
        "missing dir",
        "empty dir",
        "zero epochs",
        "bad fraction",
        "bad R",
        "no checkpoint",
        "junk checkpoint",
        "frame range",
        "resume nothing",
        "resume done",
        "resume change",
        "unknown town",
        "unknown command",
    ],
)
def test_user_mistakes_give_one_line_and_exit_2(case, tmp_path, run, capsys):
    argv, message = _bad(tmp_path, run)[case]
    try:
        status = main(argv)
    except SystemExit as e:  # argparse's own errors
        status = e.code
    err = capsys.readouterr().err
    assert status == 2
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_fit_builds_the_papers_model_by_default_and_ours_with_one_flag(run, tmp_path):
    from training.checkpoint import load_checkpoint
    from training.config import OURS_MODEL, ModelConfig, TrainConfig, architecture

    shards, out = run
    state = load_checkpoint(out / "last.pt")
    paper = ModelConfig.from_dict(state["model_config"])
    assert architecture(paper, TrainConfig.from_dict(state["train_config"])) == "paper"
    # ours, with one addition switched back off on its own
    ours = tmp_path / "ours"
    argv = ["fit", "--shards", str(shards), "--config", "tiny", "--arch", "ours", "--epochs", "1"]
    assert main(argv + ["--no-planner-speed", "--workers", "0", "--out", str(ours)]) == 0
    state = load_checkpoint(ours / "last.pt")
    model_cfg = ModelConfig.from_dict(state["model_config"])
    assert model_cfg.additions == tuple(k for k in OURS_MODEL if k != "planner_speed")
    assert TrainConfig.from_dict(state["train_config"]).zoom_out == 0.55
    assert main(["eval", "--ckpt", str(ours / "last.pt"), "--shards", str(shards)]) == 0
    # one addition on the paper's model
    argv = ["fit", "--shards", str(shards), "--config", "tiny", "--no-speed-input", "--epochs", "1"]
    assert main(argv + ["--workers", "0", "--out", str(tmp_path / "blind")]) == 0
    cfg = ModelConfig.from_dict(load_checkpoint(tmp_path / "blind" / "last.pt")["model_config"])
    assert not cfg.speed_input and architecture(cfg) == "paper + speed_input"
    argv = ["fit", "--shards", str(shards), "--config", "tiny", "--planner-speed", "--epochs", "2"]
    assert main(argv + ["--workers", "0", "--out", str(tmp_path / "one"), "--seed", "3"]) == 0
    cfg = ModelConfig.from_dict(load_checkpoint(tmp_path / "one" / "last.pt")["model_config"])
    assert architecture(cfg) == "paper + planner_speed"


def test_resume_refuses_another_architecture(run, tmp_path, capsys):
    _, out = run
    assert main(["fit", "--resume", "--out", str(out), "--arch", "ours", "--epochs", "2"]) == 2
    err = capsys.readouterr().err
    assert "--arch and the model flags must match the checkpoint's" in err
