import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import cv2
import pytest
import torch

from tests.synthetic import write_shards
from training import curves, data, fit
from training.config import PRESETS, preset
from training.errors import UserError
from training.losses import loss_terms

TINY_MODEL, TINY_TRAIN = PRESETS["tiny"]


@pytest.fixture(scope="module")
def shards(synthetic_shards) -> Path:
    return synthetic_shards  # two towns x two episodes x four frames


def _train_cfg(shards: Path, out: Path, **changes):
    base = dict(shards=str(shards), out=str(out), batch_size=4, num_workers=0, val_fraction=0.25)
    base["cache_dir"] = str(Path(out).parent / "decoded")  # not the user's ~/.cache
    return dataclasses.replace(TINY_TRAIN, **{**base, **changes})


def test_lr_warms_up_then_decays_by_cosine():
    cfg = dataclasses.replace(TINY_TRAIN, lr=1.0, warmup_frac=0.1, min_lr_frac=0.01)
    lrs = [fit.lr_at(s, 100, cfg) for s in range(100)]
    assert lrs[0] == pytest.approx(0.1) and lrs[9] == pytest.approx(1.0)
    assert all(a >= b for a, b in zip(lrs[9:], lrs[10:]))
    assert lrs[-1] == pytest.approx(0.01, abs=1e-3)


@pytest.mark.slow
@pytest.mark.parametrize("ema_decay", [0.0, 0.5])
def test_resume_continues_with_identical_state(shards, tmp_path, monkeypatch, ema_decay):
    # Stochastic depth on, so the restored RNG state matters. On the CPU, where runs are
    # bit-exact (CUDA's backward kernels are not: on an H200 the weights differed by ~1e-5).
    model_cfg = dataclasses.replace(TINY_MODEL, drop_path=0.2)
    whole_cfg = _train_cfg(shards, tmp_path / "whole", epochs=2, ema_decay=ema_decay)
    whole = fit.fit(model_cfg, whole_cfg, device="cpu")

    # The same run, interrupted as epoch 2 starts, then resumed.
    cut = _train_cfg(shards, tmp_path / "cut", epochs=2, ema_decay=ema_decay)
    set_epoch = data.FrameStream.set_epoch

    def interrupt(self, epoch):
        if epoch == 1:
            raise KeyboardInterrupt
        set_epoch(self, epoch)

    monkeypatch.setattr(data.FrameStream, "set_epoch", interrupt)
    with pytest.raises(KeyboardInterrupt):
        fit.fit(model_cfg, cut, device="cpu")
    assert torch.load(tmp_path / "cut" / "last.pt", weights_only=True)["epoch"] == 1
    monkeypatch.setattr(data.FrameStream, "set_epoch", set_epoch)
    resumed = fit.fit(model_cfg, cut, resume=True, device="cpu")

    a, b = (torch.load(p, weights_only=True) for p in (whole, resumed))
    assert (a["epoch"], a["step"]) == (b["epoch"], b["step"]) == (2, 6)
    assert ("train_model" in a) == ("train_model" in b) == (ema_decay > 0)
    for weights in ("model", "train_model") if ema_decay else ("model",):
        for k in a[weights]:
            assert torch.equal(a[weights][k], b[weights][k]), (weights, k)
    for (i, sa), (j, sb) in zip(a["optimizer"]["state"].items(), b["optimizer"]["state"].items()):
        assert i == j and all(torch.equal(sa[k], sb[k]) for k in sa)
    assert torch.equal(a["rng"][0]["torch"], b["rng"][0]["torch"])

    def losses(path):
        lines = (path.parent / "metrics.jsonl").read_text().splitlines()
        return [(m["train"], m["val"]) for m in map(json.loads, lines)]

    assert losses(whole) == losses(resumed)

    def steps(path):  # the per-step log, cut back to the checkpoint and continued
        lines = (path.parent / fit.STEPS).read_text().splitlines()
        return [
            {k: v for k, v in m.items() if k != "samples_per_s"} for m in map(json.loads, lines)
        ]

    assert steps(whole) == steps(resumed) and len(steps(whole)) == 2


@pytest.mark.slow
def test_the_decoded_frame_cache_changes_no_loss(shards, tmp_path, capsys):
    def run(name: str, **changes) -> list[dict]:
        out = tmp_path / name
        fit.fit(TINY_MODEL, _train_cfg(shards, out, epochs=2, **changes), device="cpu")
        lines = (out / fit.METRICS).read_text().splitlines()
        return [(m["train"], m["val"], m["val_metrics"]) for m in map(json.loads, lines)]

    decoded = run("decoded", cache_gb=0)
    assert "0 frames in the decoded-frame cache" in capsys.readouterr().out
    filled = run("filled", num_workers=1)
    assert "decoding 16 frames of 4 shards into the cache" in capsys.readouterr().out
    hit = run("hit")
    assert "16 frames in the decoded-frame cache" in capsys.readouterr().out
    assert decoded == filled == hit


@pytest.mark.slow
def test_ema_is_the_checkpoints_model_and_tracks_the_trained_weights(shards, tmp_path):
    def weights(decay: float) -> tuple[dict, dict]:
        out = tmp_path / str(decay)
        state = torch.load(
            fit.fit(TINY_MODEL, _train_cfg(shards, out, epochs=1, ema_decay=decay), device="cpu"),
            weights_only=True,
        )
        return state["model"], state["train_model"]

    # An average that forgets at once is the trained weights; a slow one lags behind them.
    quick, trained = weights(1e-6)
    slow, trained_too = weights(0.9)
    floats = [k for k, v in trained.items() if v.is_floating_point()]
    assert all(torch.equal(trained[k], trained_too[k]) for k in floats)  # EMA does not steer
    assert all(torch.allclose(quick[k], trained[k], atol=1e-5) for k in floats)
    moved = [k for k in floats if not torch.allclose(slow[k], trained[k], atol=1e-5)]
    assert len(moved) > len(floats) // 2


@pytest.mark.slow
def test_ddp_runs_with_two_cpu_processes(shards, tmp_path):
    out = tmp_path / "ddp"
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone"]
    command += ["--nproc_per_node", "2", "-m", "training.cli", "fit", "--shards", str(shards)]
    command += ["--config", "tiny", "--epochs", "1", "--batch-size", "2", "--workers", "0"]
    command += ["--val-fraction", "0.25", "--device", "cpu", "--out", str(out)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    state = torch.load(out / "last.pt", weights_only=True)
    assert len(state["rng"]) == 2  # both ranks' generator states
    # 12 training frames: 6 per rank, 3 steps of 2 on each, all 12 frames seen.
    assert state["step"] == math.ceil(12 / 2 / 2)
    (metrics,) = map(json.loads, (out / "metrics.jsonl").read_text().splitlines())
    assert metrics["val"]["total"] > 0 and metrics["train"]["total"] > 0
    # `train eval`'s metrics are of both ranks' shares of the 4 held-out frames, not rank 0's
    index = data.scan(shards)
    assert index.episode_id.isin(state["val_episodes"]).sum() == 4
    assert metrics["val_metrics"]["frames"] == 4


@pytest.mark.slow
def test_fit_logs_every_term_to_jsonl_and_tensorboard(shards, tmp_path):
    event_accumulator = pytest.importorskip(
        "tensorboard.backend.event_processing.event_accumulator"
    )
    out = tmp_path / "run"
    ours = preset("tiny", "ours")[0]  # every term, ours' camera-only traffic term too
    fit.fit(ours, _train_cfg(shards, out, epochs=2))
    terms = set(loss_terms(ours.heads, ours.has_camera_traffic))
    assert "camera_tf" in terms
    steps = [json.loads(line) for line in (out / fit.STEPS).read_text().splitlines()]
    assert [s["step"] for s in steps] == [3, 6]  # the last step of each epoch (3 per epoch)
    assert all(set(s["train"]) == terms and s["lr"] > 0 and s["samples_per_s"] > 0 for s in steps)
    epochs = [json.loads(line) for line in (out / fit.METRICS).read_text().splitlines()]
    assert {"ade_m", "cv_ade_m", "weather_accuracy", "red_light_f1", "iou_lane_marking"} <= set(
        epochs[-1]["val_metrics"]
    )
    assert "camera_red_light_f1" in epochs[-1]["val_metrics"]
    (events,) = (out / fit.TENSORBOARD).glob("events.out.tfevents.*")
    acc = event_accumulator.EventAccumulator(str(events))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert {f"step/train/{t}" for t in terms} | {"step/lr", "step/samples_per_s"} <= tags
    assert {f"epoch/val/{t}" for t in terms} | {"epoch/val_metrics/ade_m", "epoch/lr"} <= tags
    assert [e.step for e in acc.Scalars("step/train/total")] == [3, 6]
    assert acc.Scalars("step/train/total")[-1].value == pytest.approx(steps[-1]["train"]["total"])


@pytest.mark.slow
def test_curves_draw_a_png_without_tensorboard(shards, tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "run"
    fit.fit(TINY_MODEL, _train_cfg(shards, out, epochs=1))
    png = curves.draw(out, tmp_path / "curves.png")
    image = cv2.imread(str(png))
    assert image is not None and image.shape[0] > 200 and image.std() > 0
    with pytest.raises(UserError, match="no steps.jsonl or metrics.jsonl"):
        curves.draw(tmp_path, tmp_path / "x.png")


def test_several_datasets_read_as_one_and_a_repeated_episode_is_refused(shards, tmp_path):
    other = write_shards(tmp_path / "other", towns=("gamma",), episodes=2, frames=4)
    union = data.scan(f"{shards},{other}")
    assert len(union) == len(data.scan(shards)) + len(data.scan(other))
    assert set(union.town) == {"alpha", "beta", "gamma"}
    with pytest.raises(UserError, match="in two shards"):
        data.scan(f"{shards},{shards}")


def test_init_starts_from_another_runs_weights(shards, tmp_path):
    first = fit.fit(TINY_MODEL, _train_cfg(shards, tmp_path / "a", epochs=1), device="cpu")
    cfg = _train_cfg(shards, tmp_path / "b", epochs=1, init=str(first), lr=0.0)
    tuned = fit.fit(TINY_MODEL, cfg, device="cpu")
    a, b = torch.load(first, weights_only=False), torch.load(tuned, weights_only=False)
    for k, v in a["model"].items():  # lr 0: the weights it started from are the ones it saved
        if v.is_floating_point() and "running_" not in k:  # (BatchNorm's statistics move on)
            assert torch.equal(v, b["model"][k]), k
    wider = dataclasses.replace(TINY_MODEL, output_px=TINY_MODEL.output_px * 2)
    with pytest.raises(UserError, match="not this --config's"):
        fit.fit(wider, _train_cfg(shards, tmp_path / "c", epochs=1, init=str(first)), device="cpu")
