"""`train`: fit, evaluate, analyze and show the II-DSU model on iidsu shards.

train fit --shards data/ --config tiny --epochs 1 --out runs/demo     train (OUT/last.pt)
train eval --ckpt runs/demo/last.pt --shards data/                   metrics table + JSON
train analyze --ckpt runs/demo/last.pt                               ECA similarity (Table II)
train show --ckpt runs/demo/last.pt --shards data/ --frame 10 --out f.png   inputs + outputs
train curves --run runs/demo                                         loss curves PNG

Data-parallel: torchrun --standalone --nproc_per_node N -m training.cli fit ...
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import sys
from pathlib import Path

# OpenMP threads that spin while they wait take the cores the DataLoader workers need. Measured
# on the 2-core CI machine with other jobs running (load average 3-4): `train fit --config tiny
# --epochs 1` on 200 frames took 24-42 s with the default policy and 6 s with passive waiting.
# It must be set before torch is imported (this module imports it lazily); the user's wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from schemas import cli, outputs
from training.config import (
    ARCHITECTURES,
    OURS_TRAIN,
    POOLS,
    PRESETS,
    ModelConfig,
    TrainConfig,
    preset,
    with_architecture,
)
from training.errors import UserError

FRAME_ORDER = (
    "frames are numbered as `pd.read_parquet(DIR)` orders them: shard files in sorted path "
    "order, rows in file order"
)


def _checked(kind, ok, need: str):
    """An argparse type: `kind(text)`, refused unless `ok(value)` ("must be {need}")."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a valid {kind.__name__}: {text!r}") from None
        if not ok(value):
            raise argparse.ArgumentTypeError(f"must be {need}, got {text}")
        return value

    return parse


_positive_int = _checked(int, lambda v: v > 0, "positive")
_positive_float = _checked(float, lambda v: v > 0, "positive")
_fraction = _checked(float, lambda v: 0 <= v < 1, "in [0, 1)")
_workers = _checked(int, lambda v: v >= 0, "0 or more")


DEVICES = ("auto", "cpu", "cuda")
DEVICE_HELP = "auto: CUDA if present (bf16 autocast), else the CPU"

# fit flags -> (config, field); a flag left out keeps the preset's (or checkpoint's) value.
TRAIN_FLAGS = {
    "shards": "shards",
    "out": "out",
    "epochs": "epochs",
    "batch_size": "batch_size",
    "lr": "lr",
    "workers": "num_workers",
    "val_fraction": "val_fraction",
    "val_towns": "val_towns",
    "seed": "seed",
    "zoom_out": "zoom_out",
    "traffic_context_weight": "traffic_context_weight",
    "ema": "ema_decay",
    "compile": "compile",
    "cache_dir": "cache_dir",
    "cache_gb": "cache_gb",
    "threads": "threads",
    "init": "init",
}
PRIVILEGED_FLAGS = ("planner_output", "go_weight", "stay_weight", "stood_input")
MODEL_FLAGS = {
    "output_px": "output_px",
    "no_detection": "detection",
    "no_bev": "bev",
    "no_traffic": "traffic",
    "no_weather": "weather",
    "single_frame_lidar": "single_frame_lidar",
    "planner_speed": "planner_speed",
    "speed_input": "speed_input",
    "camera_traffic": "camera_traffic",
    "traffic_pool": "traffic_pool",
    "lamp_channels": "lamp_channels",
    "pixel_lamp_channels": "pixel_lamp_channels",
    "traffic_residual": "traffic_residual",
    "traffic_residual_dropout": "traffic_residual_dropout",
}
# may change on --resume
RESUMABLE = {"shards", "out", "epochs", "workers", "compile", "cache_dir", "cache_gb", "threads"}


def _add_fit(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--shards",
        metavar="DIR",
        help="shard directory or .parquet file, or several comma-separated",
    )
    p.add_argument(
        "--config",
        choices=sorted(PRESETS),
        help="size: paper (the paper's, default) or tiny (the same architecture shrunk for CPUs)",
    )
    p.add_argument(
        "--arch",
        choices=(*ARCHITECTURES, "privileged"),
        help="paper: the paper's II-DSU (Sec. III), nothing of ours (default); ours: the "
        "paper's plus every addition below; privileged: a small CNN planning from the labels "
        "(ground-truth BEV map, boxes, lights; training/privileged.py), driven by `drive eval` "
        "from the world's ground truth",
    )
    p.add_argument("--out", metavar="DIR", help="run directory")
    p.add_argument(
        "--epochs",
        type=_positive_int,
        metavar="N",
        help="epochs in all (ours: the paper gives no schedule)",
    )
    p.add_argument(
        "--batch-size",
        type=_positive_int,
        metavar="N",
        help="frames per optimizer step per process (ours: the paper gives none)",
    )
    p.add_argument(
        "--lr",
        type=_positive_float,
        metavar="F",
        help="AdamW peak learning rate (the paper preset's is TransFuser's, tiny's ours; the "
        "paper names neither optimizer nor rate)",
    )
    p.add_argument("--workers", type=_workers, metavar="N", help="DataLoader workers per process")
    p.add_argument("--val-fraction", type=_fraction, metavar="F", help="share of episodes held out")
    p.add_argument(
        "--val-towns",
        type=lambda s: tuple(t for t in s.split(",") if t),
        metavar="A,B",
        help="hold out these towns' episodes instead of --val-fraction (comma-separated; "
        "default: none)",
    )
    p.add_argument("--seed", type=int, metavar="N", help="seed of weights, split and data order")
    p.add_argument(
        "--traffic-context-weight",
        type=_positive_float,
        metavar="W",
        help="weight in L_light and L_sign of the frames where the ego's speed contradicts the "
        "label (red or stop sign while moving, neither while stopped) (1: off; ours, in neither "
        "architecture)",
    )
    # --arch privileged only (PRIVILEGED_FLAGS)
    p.add_argument("--planner-output", choices=("waypoints", "path_speed"), help="--arch "
                   "privileged: the paper's GRU waypoints (default) or TransFuser++'s path and "
                   "target-speed classes (training/pathspeed.py)")  # fmt: skip
    p.add_argument("--go-weight", type=_positive_float, metavar="W", help="--arch privileged: "
                   "weight of the stand -> go frames in the loss (default 1)")  # fmt: skip
    p.add_argument("--stay-weight", type=_positive_float, metavar="W", help="--arch privileged: "
                   "weight of the frames that stand and stay (default 1)")  # fmt: skip
    p.add_argument("--stood-input", action="store_const", const=True, help="--arch privileged: "
                   "it also reads how long the ego has stood (training/ego_history.py)")  # fmt: skip
    p.add_argument(
        "--ema",
        type=_fraction,
        metavar="D",
        help="keep an exponential moving average of the weights with decay D per step; "
        "validation and last.pt use it (0: off; ours)",
    )
    p.add_argument(
        "--output-px", type=_positive_int, metavar="R", help="R, side of the dense heads' maps"
    )
    p.add_argument(
        "--compile",
        action="store_true",
        default=None,
        help="torch.compile the model (default: off)",
    )
    p.add_argument(
        "--cache-dir",
        metavar="DIR",
        help="decoded-frame cache, safe to delete (default: $IIDSU_CACHE/decoded, else "
        "~/.cache/iidsu/decoded)",
    )
    p.add_argument(
        "--cache-gb",
        type=_checked(float, lambda v: v >= 0, "0 or more"),
        metavar="N",
        help="bound of the decoded-frame cache in GB; frames past it are decoded every epoch "
        "(0: no cache)",
    )
    p.add_argument(
        "--threads",
        type=_workers,
        metavar="N",
        help="intra-op CPU threads per process (0: the cores it may use / processes per machine)",
    )
    p.add_argument("--device", choices=DEVICES, default="auto", help=DEVICE_HELP)
    p.add_argument(
        "--init",
        metavar="CKPT",
        help="start from this checkpoint's weights (fine-tuning; the optimizer and schedule "
        "start afresh; --config and the model flags must describe its model; default: none, "
        "random weights)",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue OUT/last.pt exactly; only --epochs, --shards, --workers, --compile, "
        "--cache-dir, --cache-gb, --threads may change",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the run in OUT (its checkpoint, logs and TensorBoard events) and start anew",
    )
    p.add_argument(
        "--allow-unfinished",
        action="store_true",
        help="train on a build that is not finished (its _manifest.json says building)",
    )
    ablation = p.add_argument_group("ablations (the paper's Table III)")
    for flag, what in (
        ("--no-detection", "object density (detection & prediction) head"),
        ("--no-bev", "BEV map head"),
        ("--no-traffic", "traffic rule head"),
        ("--no-weather", "weather head"),
    ):
        ablation.add_argument(flag, action="store_true", default=None, help=f"drop the {what}")
    ablation.add_argument(
        "--single-frame-lidar",
        action="store_true",
        default=None,
        help="LiDAR input of the current sweep only (2 channels)",
    )
    ours = p.add_argument_group(
        "additions of ours (none is in the paper; each is off in --arch paper, on in --arch "
        "ours, and a flag here sets it either way; what each measured: docs/learning.md)"
    )
    ours.add_argument(
        "--planner-speed",
        action=argparse.BooleanOptionalAction,
        help="ours: the planner's MLP also reads the ego speed",
    )
    ours.add_argument(
        "--speed-input",
        action=argparse.BooleanOptionalAction,
        help="--no-speed-input: ours, in neither architecture: the model never reads the ego "
        "speed (fusion and planner get 0), against the inertia of a model that plans from it "
        "(docs/closed-loop.md)",
    )
    ours.add_argument(
        "--camera-traffic",
        action=argparse.BooleanOptionalAction,
        help="ours: a traffic-rule training head on the camera alone, before fusion",
    )
    ours.add_argument(
        "--traffic-pool",
        choices=POOLS,
        help="ours: traffic-rule heads pool their 8x8 map by avgmax (mean and maximum; --arch "
        "ours) or avg (the paper's mean)",
    )
    ours.add_argument(
        "--lamp-channels",
        type=_checked(int, lambda v: v >= 0, "0 or more"),
        metavar="N",
        help="ours: N lamp maps from the camera's first stage into F_DSU (--arch ours: 8; 0: off)",
    )
    ours.add_argument(
        "--pixel-lamp-channels",
        type=_checked(int, lambda v: v >= 0, "0 or more"),
        metavar="N",
        help="ours: N lamp maps from per-pixel colour detectors into F_DSU (--arch ours: 8; "
        "0: off)",
    )
    ours.add_argument(
        "--traffic-residual",
        action=argparse.BooleanOptionalAction,
        help="ours: F_DSU's traffic head corrects the camera-only head's logits (needs it)",
    )
    ours.add_argument(
        "--traffic-residual-dropout",
        type=_checked(float, lambda v: 0.0 <= v < 1.0, "in [0, 1)"),
        metavar="P",
        help="ours: in training, drop that correction with probability P (--arch ours: 0.5; "
        "0: off)",
    )
    ours.add_argument(
        "--zoom-out",
        type=_positive_float,
        metavar="S",
        help="ours: camera zoom-out augmentation, half the training frames shrunk by a factor "
        "in [S, 1) (--arch ours: 0.55; 1: off)",
    )
    _preset_defaults(p)


def _preset_defaults(p: argparse.ArgumentParser) -> None:
    """Append to the help of each flag that sets a config field the value it takes when left
    out: the preset's (`paper`, `tiny`), read from training/config.py so that it cannot drift;
    on --resume, the checkpoint's."""
    for action in p._actions:
        if action.default is not None or (action.help or "").count("default:"):
            continue
        if action.dest in TRAIN_FLAGS:
            which, field = 1, TRAIN_FLAGS[action.dest]
        elif action.dest in MODEL_FLAGS:
            which, field = 0, MODEL_FLAGS[action.dest]
        else:
            continue
        values = {name: getattr(cfgs[which], field) for name, cfgs in PRESETS.items()}
        if any(isinstance(v, bool) for v in values.values()):
            continue  # a switch: its help says what it turns on or off
        shown = {k: ",".join(v) or "none" if isinstance(v, tuple) else v for k, v in values.items()}
        if len(set(shown.values())) == 1:
            action.help += f" (default: {next(iter(shown.values()))})"
        else:
            action.help += f" (default: {', '.join(f'{k} {v}' for k, v in shown.items())})"


FIT_EPILOG = """\
Where the defaults come from. The paper (Sec. III-IV) fixes the model: LiDAR BEV 256x256 at
8 px/m (32 m ahead, 16 m each side), T_past = 3, the camera crop 256x256, ConvNeXt widths
64-128-256-512 with /4 /2 /2 /2, four TransFuser layers, F_DSU 8x8x1024, one ECA per head,
4 waypoints from 4 GRU steps, the five heads and the form of the loss (Eq. 1-3), 2 Hz data.
Where it is silent the model takes TransFuser's choice (Prakash et al. 2021, the paper's
closest baseline): 8 attention blocks of 4 heads per fusion layer, 8x8 token anchors, learned
position and velocity embeddings (training/config.py ModelConfig). `--arch paper` (the
default) is that model and nothing else; `--arch ours` adds every option of the group
"additions of ours" (training/lamps.py), each also settable on its own.
The paper gives no training recipe: optimizer, learning rate and schedule, epochs, batch size
and the loss weights lambda/alpha/beta/gamma/delta are ours. AdamW at 1e-4 is TransFuser's;
weight decay 0.01 is AdamW's usual default; batch 32, 30 epochs, the warm-up + cosine schedule
and the loss weights (planning 1.0, detection 0.2, BEV 0.2, traffic 0.1, weather 0.1) are our
choice, set so that planning dominates as Sec. III-C wishes; the BEV class weights (1, 1, 3:
lane markings are thin) and the red-light / stop-sign positive weights (3, 3: both are the
minority) are ours too, and so is an optional context weight (--traffic-context-weight W, off
in both architectures) for frames where the ego's speed contradicts the red-light or
stop-sign label. The tiny preset's values (lr 1e-3, batch 8, R = 64) are ours, for CPUs;
bench/learn.py measures what either architecture learns on a held-out town
(docs/learning.md).
"""


def _configs(args) -> tuple[ModelConfig, TrainConfig]:
    """Preset configs (`--config` size, `--arch` architecture) with the flags the user gave
    applied; on --resume, the checkpoint's, where only RESUMABLE flags may differ from what the
    run was started with."""
    given = {k for k in {*TRAIN_FLAGS, *MODEL_FLAGS} if getattr(args, k) is not None}
    train_changes = {f: getattr(args, a) for a, f in TRAIN_FLAGS.items() if a in given}
    model_changes = {}
    for a, f in MODEL_FLAGS.items():
        if a in given:  # --no-X switches head X off; the others set their field
            model_changes[f] = False if a.startswith("no_") else getattr(args, a)
    try:
        if not args.resume:
            model_cfg, train_cfg = preset(args.config or "paper", args.arch or "paper")
            return dataclasses.replace(model_cfg, **model_changes), dataclasses.replace(
                train_cfg, **train_changes
            )
        from training.checkpoint import load_checkpoint
        from training.fit import CHECKPOINT

        state = load_checkpoint(f"{args.out or TrainConfig.out}/{CHECKPOINT}")
        model_cfg = ModelConfig.from_dict(state["model_config"])
        train_cfg = TrainConfig.from_dict(state["train_config"])
        base, base_train = PRESETS[args.config][0] if args.config else model_cfg, train_cfg
        if args.arch:
            base, base_train = with_architecture(base, train_cfg, args.arch)
        arch_train = {f: getattr(base_train, f) for f in OURS_TRAIN if f not in train_changes}
        if dataclasses.replace(base, **model_changes) != model_cfg or any(
            getattr(train_cfg, f) != v for f, v in arch_train.items()
        ):
            raise UserError(
                "--config, --arch and the model flags must match the checkpoint's on --resume"
            )
    except ValueError as e:  # a field value the config refuses (e.g. --output-px)
        raise UserError(str(e)) from None
    changed = [
        "--" + a.replace("_", "-")
        for a, f in TRAIN_FLAGS.items()
        if a in given and a not in RESUMABLE and getattr(train_cfg, f) != getattr(args, a)
    ]
    if changed:
        raise UserError(f"{', '.join(changed)}: cannot change on --resume (the checkpoint's stay)")
    return model_cfg, dataclasses.replace(train_cfg, **train_changes)


def _run_fit(args) -> int:
    from training.fit import fit

    if args.arch == "privileged":  # its own loop and flags (training/privileged.py)
        from training.privileged import run_fit

        given = sorted(k for k in {*TRAIN_FLAGS, *MODEL_FLAGS} if getattr(args, k) is not None)
        _check_unfinished_build(Path(args.shards or "."), args.allow_unfinished)
        return run_fit(args, given)
    if any(getattr(args, a) is not None for a in PRIVILEGED_FLAGS):
        flags = ", ".join("--" + a.replace("_", "-") for a in PRIVILEGED_FLAGS)
        raise UserError(f"{flags}: --arch privileged only")
    if args.resume and args.force:
        raise UserError("--resume continues the run in OUT, --force replaces it: give one")
    model_cfg, train_cfg = _configs(args)
    out = outputs.check_dir(train_cfg.out)
    _check_unfinished_build(Path(train_cfg.shards), args.allow_unfinished)
    if not args.resume and int(os.environ.get("RANK", "0")) == 0:  # torchrun: one rank looks
        _fresh_run_dir(out, args.force)
    fit(model_cfg, train_cfg, resume=args.resume, device=args.device)
    return 0


def _fresh_run_dir(out: Path, force: bool) -> None:
    """Refuse a run directory that holds a run (unless `force`: then remove what `train fit`
    wrote there, so no old log line or TensorBoard event is read as the new run's)."""
    from training.fit import CHECKPOINT, METRICS, STEPS, TENSORBOARD

    found = [n for n in (CHECKPOINT, METRICS, STEPS, TENSORBOARD) if (out / n).exists()]
    if not found:
        return
    if not force:
        raise UserError(
            f"{out} holds a run ({', '.join(found)}); continue it with --resume or replace it "
            "with --force"
        )
    for name in found:
        path = out / name
        shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)


def _check_unfinished_build(shards: Path, allowed: bool) -> None:
    """Refuse shards whose build is still running or was interrupted (unless `allowed`)."""
    manifest = shards / "_manifest.json"  # datagen.manifest.MANIFEST (training reads no datagen)
    if allowed or not manifest.is_file():
        return
    try:
        doc = json.loads(manifest.read_text())
    except (OSError, ValueError):
        return  # not a manifest of ours: data.scan judges the shards
    if isinstance(doc, dict) and doc.get("status") == "building":
        frames = (doc.get("statistics") or {}).get("frames", "?")
        asked = (doc.get("build") or {}).get("frames", "?")
        raise UserError(
            f"{shards}: the build is not finished ({manifest.name}: building, {frames} of "
            f"{asked} frames); run the same `datagen build` again to finish it, or give "
            "--allow-unfinished to train on what is there"
        )


def _fit_resume_hint(args) -> str | None:
    """After a stop: how to continue, if a checkpoint was written."""
    from training.fit import CHECKPOINT

    ckpt = Path(args.out or TrainConfig.out) / CHECKPOINT
    if not ckpt.is_file():
        return None
    if args.resume:
        return f"run the same command again to continue from {ckpt}"
    return f"run it again with --resume (and without --force) to continue from {ckpt}"


def _add_curves(p: argparse.ArgumentParser) -> None:
    p.add_argument("--run", required=True, metavar="DIR", help="run directory of train fit")
    p.add_argument("--out", metavar="PNG", help="PNG to write; default DIR/curves.png")


def _run_curves(args) -> int:
    from training.curves import run

    return run(args)


def _add_eval(p: argparse.ArgumentParser) -> None:
    p.add_argument("--ckpt", required=True, help="checkpoint written by train fit")
    p.add_argument(
        "--shards", required=True, metavar="DIR", help="shard directory (or one .parquet file)"
    )
    p.add_argument(
        "--split",
        choices=("all", "val"),
        default="all",
        help="all frames (default; for a held-out directory) or the fit's validation episodes",
    )
    p.add_argument(
        "--out", metavar="JSON", help="JSON file for the metrics; default CKPT's stem + .eval.json"
    )
    p.add_argument("--batch-size", type=_positive_int, default=16, metavar="N", help="frames")
    p.add_argument(
        "--workers", type=_workers, default=2, metavar="N", help="DataLoader worker processes"
    )
    p.add_argument("--device", choices=DEVICES, default="auto", help=DEVICE_HELP)


def _run_eval(args) -> int:
    from training.evaluate import run

    return run(args)


def _add_analyze(p: argparse.ArgumentParser) -> None:
    p.add_argument("--ckpt", required=True, help="checkpoint written by train fit")
    p.add_argument(
        "--shards", metavar="DIR", help="frames to average over; default the fit's --shards"
    )
    p.add_argument(
        "--frames", type=_positive_int, default=256, metavar="N", help="at most this many"
    )
    p.add_argument("--out", metavar="JSON", help="JSON file; default CKPT's stem + .analyze.json")
    p.add_argument("--batch-size", type=_positive_int, default=16, metavar="N", help="frames")
    p.add_argument("--device", choices=DEVICES, default="auto", help=DEVICE_HELP)


def _run_analyze(args) -> int:
    from training.analyze import run

    return run(args)


def _add_show(p: argparse.ArgumentParser) -> None:
    p.add_argument("--ckpt", required=True, help="checkpoint written by train fit")
    p.add_argument(
        "--shards", required=True, metavar="DIR", help="shard directory (or one .parquet file)"
    )
    p.add_argument("--frame", type=int, default=0, metavar="N", help=f"frame number; {FRAME_ORDER}")
    p.add_argument("--out", metavar="PNG", help="PNG to write; default show-FRAME.png beside CKPT")
    p.add_argument("--episode", metavar="ID", help="pick this episode; --frame is its frame number")
    p.add_argument(
        "--video",
        metavar="MP4",
        help="draw every frame of the episode (default: the first) to an .mp4 or .webm",
    )
    p.add_argument(
        "--speed",
        type=_positive_float,
        default=1.0,
        help="video speed-up over the recording's 2 Hz",
    )


def _run_show(args) -> int:
    from training.show import run

    return run(args)


COMMANDS = (
    cli.Command(
        "fit",
        "train the model; writes OUT/last.pt and OUT/metrics.jsonl",
        _add_fit,
        _run_fit,
        resume=_fit_resume_hint,
        epilog=FIT_EPILOG,
    ),
    cli.Command(
        "eval", "planning, detection, BEV, traffic and weather metrics", _add_eval, _run_eval
    ),
    cli.Command(
        "analyze", "cosine similarity of ECA channel weights (Table II)", _add_analyze, _run_analyze
    ),
    cli.Command("show", "a PNG or video of inputs and predictions (Fig. 5)", _add_show, _run_show),
    cli.Command(
        "curves", "a PNG of a run's loss curves and validation metrics", _add_curves, _run_curves
    ),
)


def main(argv: list[str] | None = None) -> int:
    return cli.main("train", __doc__, COMMANDS, argv)


if __name__ == "__main__":
    sys.exit(main())
