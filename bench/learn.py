"""Does II-DSU learn the scene? The issue-13 check: build 8 towns, train the tiny config with one
town held out, and score the held-out town. Prints figures and the goals; asserts nothing.

    python bench/learn.py                                  # 2,880 frames, 6 epochs (45 min here)
    python bench/learn.py --frames 8000 --epochs 10 --out runs/learn8k
    python bench/learn.py --data /tmp/d8 --reuse           # train again on an existing build
    python bench/learn.py --eval-only runs/learn --compare old.eval.json   # table only

Steps (each a real command, so the figures are what a user gets):
1. `datagen build --towns 8 --frames F --seed S --out DATA` unless DATA already holds a
   complete build (with --reuse);
2. `train fit --shards DATA --config tiny --epochs E --val-towns TOWN --out OUT`;
3. `train eval --ckpt OUT/last.pt --shards DATA --split val` (the held-out town).

The table: ADE/FDE of the model and of the constant-velocity baseline (goal: model ADE below
0.8x the baseline's), weather accuracy (goal >= 95 %), red-light F1 (>= 0.8), BEV IoU per class
(lane marking > 0), detection AP per timestep; then the per-epoch validation metrics from
OUT/metrics.jsonl, the build's frames (goal <= 20k) and the training wall time (goal <= 1 h on
a 2-core machine). `--compare JSON` adds a column from another `train eval` JSON (e.g. the
same check on an older commit).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from schemas import WAYPOINT_TIMES_S  # noqa: E402
from schemas.dataset import shard_files  # noqa: E402
from training import evaluate  # noqa: E402

GOALS = {
    "ade_ratio": 0.8,
    "weather_accuracy": 0.95,
    "red_light_f1": 0.8,
    "iou_lane_marking": 0.0,
}


def _run(args: list[str]) -> float:
    """Run a project command (python -m ...) with this checkout first on the path; its wall s."""
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    print("$", " ".join(args), flush=True)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", *args], check=True, env=env, cwd=ROOT)
    return time.perf_counter() - t0


def _built(data: Path) -> int:
    """Frames of a complete build in `data`, else 0."""
    manifest = data / "_manifest.json"
    if not manifest.is_file():
        return 0
    m = json.loads(manifest.read_text())
    return int(m["statistics"]["frames"]) if m.get("status") == "complete" else 0


def headline(result: dict) -> dict:
    """The goal figures of a `train eval` JSON: what `train fit` logs per epoch
    (training.evaluate.headline), plus the ADE ratio to constant velocity and mAP per timestep."""
    out = evaluate.headline(result)
    out["ade_ratio"] = out["ade_m"] / out["cv_ade_m"]
    for t, aps in result.get("detection", {}).items():
        out[f"det_map_{t}"] = aps["map"]
    return out


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.4f}"


def _goal(key: str, v) -> str:
    if key not in GOALS or v is None:
        return ""
    ok = (
        v < GOALS[key]
        if key == "ade_ratio"
        else (v > 0 if key == "iou_lane_marking" else v >= GOALS[key])
    )
    rule = {"ade_ratio": "< 0.8", "iou_lane_marking": "> 0"}.get(key, f">= {GOALS[key]}")
    return f"goal {rule}: {'met' if ok else 'MISSED'}"


def table(result: dict, compare: dict | None) -> str:
    now = headline(result)
    old = headline(compare) if compare else {}
    lines = [f"held-out frames: {result['frames']}", ""]
    head = f"{'':<20}{'this run':>10}" + (f"{'compare':>10}" if compare else "")
    lines.append(head)
    for k, v in now.items():
        row = f"{k:<20}{_fmt(v):>10}" + (f"{_fmt(old.get(k)):>10}" if compare else "")
        lines.append(f"{row}   {_goal(k, v)}")
    return "\n".join(lines)


def kinematic_baselines(data: Path, town: str) -> dict[str, float]:
    """ADE (m) on `town`'s frames that have a frame 0.5 s before in their episode, of constant
    velocity (what `train eval` reports over all frames) and of constant acceleration from the
    speed 0.5 s before (never a model input: how much of the waypoints is ego dynamics alone)."""
    import numpy as np
    import pyarrow.parquet as pq

    cols = ["episode_id", "time_s", "ego_speed", "waypoints"]
    filters = [("town", "==", town)]
    t = pq.ParquetDataset(shard_files(data), filters=filters).read(columns=cols).to_pandas()
    t = t.sort_values(["episode_id", "time_s"]).reset_index(drop=True)
    wp = np.stack([np.asarray(w, dtype=np.float64).reshape(-1, 2) for w in t.waypoints])
    v, times = t.ego_speed.to_numpy(np.float64), np.asarray(WAYPOINT_TIMES_S)
    by_episode = t.groupby("episode_id")
    v_before, dt = by_episode.ego_speed.shift(1).to_numpy(), by_episode.time_s.diff().to_numpy()
    ok = np.isfinite(v_before) & (np.abs(dt - 0.5) < 1e-3)
    accel = np.where(ok, (v - np.nan_to_num(v_before)) / 0.5, 0.0)
    x_cv = v[:, None] * times
    x_ca = np.maximum.accumulate(np.maximum(x_cv + 0.5 * accel[:, None] * times**2, 0), axis=1)

    def ade(x: np.ndarray) -> float:
        pred = np.stack([x, np.zeros_like(x)], axis=2)
        return float(np.linalg.norm(pred - wp, axis=2).mean(1)[ok].mean())

    return {"frames": int(ok.sum()), "cv_ade_m": ade(x_cv), "ca_ade_m": ade(x_ca)}


def epochs_table(run: Path) -> str:
    lines = [
        "",
        "per epoch (held-out town):",
        "epoch  train   val    ADE    CV ADE  weather  red F1  lane IoU  red F1 (camera alone)",
    ]
    path = run / "metrics.jsonl"
    for m in map(json.loads, path.read_text().splitlines() if path.is_file() else []):
        v = m.get("val_metrics", {})
        lines.append(
            f"{m['epoch']:>5}  {m['train']['total']:.3f}  {m['val'].get('total', 0):.3f}  "
            f"{_fmt(v.get('ade_m')):>6} {_fmt(v.get('cv_ade_m')):>7}  "
            f"{_fmt(v.get('weather_accuracy')):>7}  {_fmt(v.get('red_light_f1')):>6}  "
            f"{_fmt(v.get('iou_lane_marking')):>8}  {_fmt(v.get('camera_red_light_f1')):>8}"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "runs" / "learn-data")
    parser.add_argument("--frames", type=int, default=2880, help="frames to build (<= 20k)")
    parser.add_argument("--seed", type=int, default=21)
    parser.add_argument(
        "--episode-seconds", type=float, default=None, help="per episode (datagen's default)"
    )
    parser.add_argument("--val-town", default="arterial")
    parser.add_argument("--epochs", type=int, default=6)
    parser.add_argument("--workers", type=int, default=2, help="build processes")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "learn")
    parser.add_argument("--reuse", action="store_true", help="keep a complete build in --data")
    parser.add_argument("--eval-only", type=Path, metavar="RUN", help="print RUN's table only")
    parser.add_argument("--compare", type=Path, metavar="JSON", help="another eval JSON")
    parser.add_argument("--fit-arg", action="append", default=[], help="extra train fit flag")
    args = parser.parse_args()

    run, fit_s = args.eval_only, None
    if run is None:
        run = args.out
        if not (args.reuse and _built(args.data)):
            build = ["datagen.cli", "build", "--towns", "8", "--frames", str(args.frames)]
            build += ["--seed", str(args.seed), "--workers", str(args.workers), "--force"]
            if args.episode_seconds is not None:  # shorter episodes: more towns x weathers
                build += ["--episode-seconds", str(args.episode_seconds)]
            _run([*build, "--out", str(args.data), "--no-progress"])
        fit = ["training.cli", "fit", "--shards", str(args.data), "--config", "tiny"]
        fit += ["--epochs", str(args.epochs), "--val-towns", args.val_town, "--out", str(run)]
        fit += ["--force"]  # a fresh run, whatever an earlier one left in --out
        fit_s = _run([*fit, "--device", "cpu", *args.fit_arg])
        ev = ["training.cli", "eval", "--ckpt", str(run / "last.pt"), "--shards", str(args.data)]
        _run([*ev, "--split", "val", "--device", "cpu", "--out", str(run / "eval.json")])
    evals = [p for p in (run / "eval.json", run / "last.eval.json") if p.is_file()]
    if not evals:
        sys.exit(f"{run}: no eval.json (run `train eval --ckpt {run}/last.pt ...` first)")
    result = json.loads(evals[0].read_text())
    compare = json.loads(args.compare.read_text()) if args.compare else None
    print()
    print(table(result, compare))
    if args.eval_only is None or args.data.is_dir():
        k = kinematic_baselines(args.data, args.val_town)
        print(
            f"\nego dynamics on {args.val_town} ({k['frames']} frames with one 0.5 s before): "
            f"constant velocity ADE {k['cv_ade_m']:.3f} m, constant acceleration from the speed "
            f"0.5 s before {k['ca_ade_m']:.3f} m (not a model input: a model given its past "
            "speeds could beat the ADE goal by extrapolation alone)"
        )
    print(epochs_table(run))
    if fit_s is not None:
        frames = _built(args.data)
        print(
            f"\nbuild: {frames} frames (goal <= 20000); train fit: {fit_s / 60:.1f} min "
            f"(goal <= 60 on 2 cores; this machine is shared, so wall time is an upper bound)"
        )


if __name__ == "__main__":
    main()
