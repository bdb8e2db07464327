"""Does II-DSU learn the scene? The issue-13 check: build 8 towns, train the tiny config with
towns held out, and score the held-out towns, for one or more training seeds. Prints figures
and the goals; asserts nothing.

    python bench/learn.py                                  # 2,880 frames, 6 epochs (45 min here)
    python bench/learn.py --frames 8000 --epochs 10 --out runs/learn8k
    python bench/learn.py --data /tmp/d8 --reuse           # train again on an existing build
    python bench/learn.py --data runs/d41 --reuse --val-towns downtown --seeds 0,1,2 \
        --arch ours --out runs/learn-d41-ours             # 3 seeds: per seed, mean +- spread
    python bench/learn.py --eval-only runs/learn/s0 --compare old.eval.json   # table only

Steps (each a real command, so the figures are what a user gets):
1. `datagen build --towns 8 --frames F --seed S --out DATA` (without --reuse; with it, DATA
   must already hold a complete build, which is never rebuilt);
2. per training seed N: `train fit --shards DATA --config tiny --arch A --epochs E --val-towns
   TOWNS --seed N --out OUT/sN`;
3. `train eval --ckpt OUT/sN/last.pt --shards DATA --split val` (the held-out towns).

Per seed the table: ADE/FDE of the model and of the constant-velocity baseline (goal: model ADE
below 0.8x the baseline's), weather accuracy (goal >= 95 %), red-light F1 (>= 0.8), BEV IoU
per class (lane marking > 0), detection AP per timestep; then the per-epoch validation metrics
from OUT/sN/metrics.jsonl, the build's frames (goal <= 20k) and the training wall time (goal
<= 1 h on a 2-core machine). With several seeds, a last table gives each figure per seed, its
mean and spread (sample standard deviation, and min-max), and OUT/summary.json holds them.
`--resume` keeps the seeds that finished (OUT/sN/learn.json) and continues an interrupted fit.
`--compare JSON` adds a column from another `train eval` JSON (e.g. the same check on an older
commit).

Across sessions (whose run directories do not survive): `--record FILE` (a JSON kept in git,
e.g. docs/results/learn-d41-paper.json) holds each finished seed's figures, its build's
identity and the commit; a seed in it is not trained again, and the seeds' table waits until
every seed of --seeds is in it (the build is rebuilt when needed: the same seed gives the same
bytes). `--paired A.json B.json` prints B - A per figure and seed with the mean and a 95 %
interval over the seeds both hold (Student's t).
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


def kinematic_baselines(data: Path, towns: list[str]) -> dict[str, float]:
    """ADE (m) on `towns`' frames that have a frame 0.5 s before in their episode, of constant
    velocity (what `train eval` reports over all frames) and of constant acceleration from the
    speed 0.5 s before (never a model input: how much of the waypoints is ego dynamics alone)."""
    import numpy as np
    import pyarrow.parquet as pq

    cols = ["episode_id", "time_s", "ego_speed", "waypoints"]
    filters = [("town", "in", towns)]
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


SUMMARY = (
    "ade_m", "cv_ade_m", "ade_ratio", "weather_accuracy", "red_light_f1", "stop_sign_f1",
    "camera_red_light_f1", "iou_lane_marking", "miou", "det_map_t", "det_map_t+0.5s",
    "det_map_t+1.0s", "fit_min",
)  # fmt: skip
"""The figures of the seeds' table, in order (fit_min: `train fit`'s wall time, minutes)."""


def spread(values: list[float]) -> dict[str, float]:
    """Mean, sample standard deviation (0 for one value), min and max of `values`."""
    import numpy as np

    v = np.asarray(values, dtype=np.float64)
    std = float(v.std(ddof=1)) if len(v) > 1 else 0.0
    return {"mean": float(v.mean()), "std": std, "min": float(v.min()), "max": float(v.max())}


def seeds_table(per_seed: dict[int, dict]) -> tuple[str, dict]:
    """The text table of SUMMARY's figures per seed with mean +- std [min, max], and the same as
    a dict (figure -> {"seeds": {seed: value}, "mean", "std", "min", "max"})."""
    seeds = sorted(per_seed)
    head = f"{'':<20}" + "".join(f"{f's{s}':>9}" for s in seeds) + "   mean +- std   [min, max]"
    lines, out = [head], {}
    for key in SUMMARY:
        values = {s: per_seed[s].get(key) for s in seeds}
        if all(v is None for v in values.values()):
            continue
        row = f"{key:<20}" + "".join(f"{_fmt(v):>9}" for v in values.values())
        known = [v for v in values.values() if v is not None]
        st = spread(known)
        out[key] = {"seeds": {str(s): v for s, v in values.items()}, **st}
        row += f"   {st['mean']:.4f} +- {st['std']:.4f}   [{st['min']:.4f}, {st['max']:.4f}]"
        lines.append(row)
    return "\n".join(lines), out


def _fit_done(run: Path, epochs: int) -> bool:
    """`run` holds a checkpoint of all `epochs`."""
    if not (run / "last.pt").is_file():
        return False
    from training.checkpoint import load_checkpoint

    return int(load_checkpoint(run / "last.pt").get("epoch", 0)) >= epochs


def train_seed(args, seed: int, run: Path) -> float | None:
    """Fit and evaluate one seed into `run` (OUT/sN); `train fit`'s wall seconds, or None when
    --resume found the seed finished. Writes run/learn.json (seed, arch, towns, fit seconds)."""
    done = run / "learn.json"
    if args.resume and done.is_file():
        old = json.loads(done.read_text())
        if (old["arch"], old["val_towns"]) != (args.arch, args.val_towns):
            sys.exit(f"{run}: trained with --arch {old['arch']} --val-towns {old['val_towns']}")
    if args.resume and done.is_file() and (run / "eval.json").is_file():
        print(f"seed {seed}: done ({run})")
        return json.loads(done.read_text())["fit_s"]
    fit = ["training.cli", "fit", "--shards", str(args.data), "--config", "tiny"]
    fit += ["--arch", args.arch, "--epochs", str(args.epochs), "--val-towns", args.val_towns]
    fit += ["--seed", str(seed), "--out", str(run), "--device", "cpu", *args.fit_arg]
    fit_s = 0.0
    if args.resume and (run / "last.pt").is_file():
        previous = json.loads(done.read_text())["fit_s"] if done.is_file() else 0.0
        if not _fit_done(run, args.epochs):
            fit_s = _run([*fit, "--resume"])
        fit_s += previous
    else:
        fit_s = _run([*fit, "--force"])  # a fresh run, whatever an earlier one left in run
    record = {"seed": seed, "arch": args.arch, "val_towns": args.val_towns, "fit_s": fit_s}
    done.write_text(json.dumps(record) + "\n")  # before eval: a resume keeps the fit's time
    ev = ["training.cli", "eval", "--ckpt", str(run / "last.pt"), "--shards", str(args.data)]
    _run([*ev, "--split", "val", "--device", "cpu", "--out", str(run / "eval.json")])
    return fit_s


def _report(args, run: Path, fit_s: float | None) -> dict:
    """Print one run's tables; its headline figures (plus fit_min)."""
    evals = [p for p in (run / "eval.json", run / "last.eval.json") if p.is_file()]
    if not evals:
        sys.exit(f"{run}: no eval.json (run `train eval --ckpt {run}/last.pt ...` first)")
    result = json.loads(evals[0].read_text())
    compare = json.loads(args.compare.read_text()) if args.compare else None
    print()
    print(table(result, compare))
    print(epochs_table(run))
    figures = headline(result)
    if fit_s is not None:
        figures["fit_min"] = fit_s / 60
        print(
            f"\nbuild: {_built(args.data)} frames (goal <= 20000); train fit: {fit_s / 60:.1f} "
            "min (goal <= 60 on 2 cores; this machine is shared, so wall time is an upper bound)"
        )
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "runs" / "learn-data")
    parser.add_argument("--frames", type=int, default=2880, help="frames to build (<= 20k)")
    parser.add_argument("--seed", type=int, default=21, help="the build's seed")
    parser.add_argument(
        "--episode-seconds", type=float, default=None, help="per episode (datagen's default)"
    )
    parser.add_argument(
        "--val-towns", default="arterial", metavar="A,B", help="held-out towns (comma-separated)"
    )
    parser.add_argument(
        "--seeds",
        type=lambda text: [int(x) for x in text.split(",") if x],
        default=[0],
        metavar="N,M",
        help="training seeds, one fit each into OUT/sN (0)",
    )
    parser.add_argument(
        "--arch", choices=("paper", "ours"), default="paper", help="train fit --arch (paper)"
    )
    parser.add_argument("--epochs", type=int, default=6)
    parser.add_argument("--workers", type=int, default=2, help="build processes")
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "learn")
    parser.add_argument(
        "--reuse", action="store_true", help="use the complete build in --data; never rebuild"
    )
    parser.add_argument(
        "--resume", action="store_true", help="keep finished seeds, continue interrupted fits"
    )
    parser.add_argument("--eval-only", type=Path, metavar="RUN", help="print RUN's table only")
    parser.add_argument("--compare", type=Path, metavar="JSON", help="another eval JSON")
    parser.add_argument("--fit-arg", action="append", default=[], help="extra train fit flag")
    parser.add_argument(
        "--record", type=Path, metavar="JSON", help="finished seeds across sessions (kept in git)"
    )
    parser.add_argument(
        "--paired", type=Path, nargs=2, metavar=("A", "B"), help="B - A of two --record files"
    )
    args = parser.parse_args()
    towns = [t for t in args.val_towns.split(",") if t]
    if args.paired:
        a, b = (json.loads(p.read_text()) for p in args.paired)
        text, _ = paired(a, b)
        print(f"{b['arch']} - {a['arch']}, held out: {a['val_towns']}\n{text}")
        return
    recorded = load_record(args.record, args) if args.record else {}
    todo = [s for s in args.seeds if str(s) not in recorded]
    if args.record and not todo:
        _summary(args, {int(s): e["figures"] for s, e in recorded.items() if int(s) in args.seeds})
        return

    if args.eval_only is not None:
        _report(args, args.eval_only, None)
        if args.data.is_dir():
            _print_baselines(args.data, towns)
        return
    if args.reuse and not _built(args.data):
        sys.exit(f"{args.data}: no complete build (--reuse never rebuilds; wait for it or drop it)")
    if not args.reuse:
        build = ["datagen.cli", "build", "--towns", "8", "--frames", str(args.frames)]
        build += ["--seed", str(args.seed), "--workers", str(args.workers), "--force"]
        if args.episode_seconds is not None:  # shorter episodes: more towns x weathers
            build += ["--episode-seconds", str(args.episode_seconds)]
        _run([*build, "--out", str(args.data), "--no-progress"])
    if any(e["build"] != build_identity(args.data) for e in recorded.values()):
        sys.exit(f"{args.data}: another build than the one --record {args.record} holds")
    per_seed = {int(s): e["figures"] for s, e in recorded.items() if int(s) in args.seeds}
    for seed in todo:
        run = args.out / f"s{seed}"
        fit_s = train_seed(args, seed, run)
        print(f"\n=== seed {seed} ({args.arch}, held out: {args.val_towns}): {run}")
        per_seed[seed] = _report(args, run, fit_s)
        if args.record:  # this seed is done for good, whatever stops the next one
            recorded[str(seed)] = {"figures": per_seed[seed], "build": build_identity(args.data),
                                   "commit": _commit()}  # fmt: skip
            save_record(args.record, args, recorded)
    _print_baselines(args.data, towns)
    _summary(args, per_seed)


def _summary(args, per_seed: dict[int, dict]) -> None:
    """The seeds' table and OUT/summary.json."""
    text, summary = seeds_table(per_seed)
    print(f"\n=== {args.arch}, {len(per_seed)} seed(s), held out: {args.val_towns}, {args.data}")
    print(text)
    towns = [t for t in args.val_towns.split(",") if t]
    record = {"arch": args.arch, "val_towns": towns, "data": str(args.data), "epochs": args.epochs}
    record |= {"fit_args": args.fit_arg, "figures": summary}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "summary.json").write_text(json.dumps(record, indent=1) + "\n")


def build_identity(data: Path) -> dict:
    """What makes two builds the same data: the manifest's build section (seed, frames, towns
    and their networks, sensors, generator version)."""
    m = json.loads((data / "_manifest.json").read_text())
    return m["build"]


def _commit() -> str:
    out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    return out.stdout.strip()


def load_record(path: Path, args) -> dict:
    """The --record file's seeds (str(seed) -> entry), refused when it was made with another
    architecture, held-out towns or epochs."""
    if not path.is_file():
        return {}
    doc = json.loads(path.read_text())
    mine = {"arch": args.arch, "val_towns": args.val_towns, "epochs": args.epochs}
    theirs = {k: doc.get(k) for k in mine}
    if theirs != mine:
        sys.exit(f"--record {path}: made with {theirs}, this run is {mine}")
    return doc.get("seeds", {})


def save_record(path: Path, args, seeds: dict) -> None:
    doc = {"arch": args.arch, "val_towns": args.val_towns, "epochs": args.epochs}
    doc |= {
        "fit_args": args.fit_arg,
        "seeds": dict(sorted(seeds.items(), key=lambda kv: int(kv[0]))),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(doc, indent=1) + "\n")
    os.replace(tmp, path)


T95 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262}
"""Student's t, two-sided 95 %, by degrees of freedom."""


def paired(a: dict, b: dict) -> tuple[str, dict]:
    """B - A per SUMMARY figure over the seeds both records hold: per seed, mean, and the 95 %
    interval of the mean (t with n - 1 degrees of freedom; none for one seed)."""
    import numpy as np

    seeds = sorted(set(a["seeds"]) & set(b["seeds"]), key=int)
    lines = [
        f"{'B - A':<20}" + "".join(f"{f's{s}':>9}" for s in seeds) + "   mean   [95 % interval]"
    ]
    out = {}
    for key in SUMMARY:
        d = [b["seeds"][s]["figures"].get(key) for s in seeds]
        d = [x - a["seeds"][s]["figures"][key] for x, s in zip(d, seeds) if x is not None]
        if len(d) != len(seeds) or not d:
            continue
        v = np.asarray(d)
        half = T95[len(v) - 1] * v.std(ddof=1) / np.sqrt(len(v)) if len(v) > 1 else float("nan")
        out[key] = {
            "diff": d,
            "mean": float(v.mean()),
            "ci95": [float(v.mean() - half), float(v.mean() + half)],
        }
        lines.append(
            f"{key:<20}" + "".join(f"{x:>9.4f}" for x in d)
            + f"   {v.mean():.4f} [{v.mean() - half:.4f}, {v.mean() + half:.4f}]"
        )  # fmt: skip
    return "\n".join(lines), out


def _print_baselines(data: Path, towns: list[str]) -> None:
    k = kinematic_baselines(data, towns)
    print(
        f"\nego dynamics on {', '.join(towns)} ({k['frames']} frames with one 0.5 s before): "
        f"constant velocity ADE {k['cv_ade_m']:.3f} m, constant acceleration from the speed "
        f"0.5 s before {k['ca_ade_m']:.3f} m (not a model input: a model given its past "
        "speeds could beat the ADE goal by extrapolation alone)"
    )


if __name__ == "__main__":
    main()
