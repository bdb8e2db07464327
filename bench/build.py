"""Benchmark `datagen build` end to end: a long-episode and a short-episode build, against the
bare-Embree limit measured in the same run; prints figures, asserts nothing.

    .venv/bin/python bench/build.py                      # 2 towns, 2880 + 480 frames, --workers 2
    .venv/bin/python bench/build.py --towns 8 --executor ray

The two builds are issue 12's: "long" runs full-length episodes (180 s, 360 frames: what a
paper-scale build runs) and "short" episodes of 30 s (60 frames); by default each has one
episode per town and weather. (A build splits each town's frames per weather into episodes of
at most that length, so fewer frames than towns x 4 x 360 would make the "long" episodes short:
this benchmark's defaults until 2026-12 did, 720 frames in 90-frame episodes.)

The limit: bench/frame.py's `measure()` casts one town's frames and replays the very same rays
as bare Embree queries (datagen/sensors/embree.py); `workers * 1000 / bare_ms` frames/s is what the ray caster alone allows,
and each build's end-to-end frames/s is reported as a share of it (same run, same load: the
machine is shared, so compare ratios, not absolute figures). Per build: frames/s end to end
(town preparation excluded: towns are cached after the first build), the stage breakdown summed
over the workers' episodes, peak memory per worker process and bytes per frame on disk, against
issue 12's targets for this 2-core machine: >= 55 frames/s for long episodes (146k frames in 45
minutes), >= 40 on short builds (30 s episodes), < 1.5 GB per worker, <= 60 KB per frame.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import schemas  # noqa: E402
from datagen.dataset import build  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from frame import measure  # noqa: E402

TARGET_FPS = {"long": 55.0, "short": 40.0}
TARGET_RSS_MB = 1536.0
TARGET_BYTES_PER_FRAME = 60_000


def run_build(args, frames: int, episode_seconds: float) -> dict:
    ns = argparse.Namespace(
        towns=args.towns,
        town=[],
        net=[],
        frames=frames,
        seed=args.seed,
        episode_seconds=episode_seconds,
        weather_mix=None,
        sensor=[],
        workers=args.workers,
    )
    cfg = build.config_from_args(ns)  # builds and caches the towns
    out = Path(tempfile.mkdtemp(prefix="iidsu-bench-")) / "data"
    try:
        t0, c0 = time.perf_counter(), os.times()
        report = build.build(
            cfg, out, workers=args.workers, force=True, executor=args.executor, progress_bar=False
        )
        wall_s = time.perf_counter() - t0
        c1 = os.times()
    finally:
        shutil.rmtree(out.parent, ignore_errors=True)
    stats = report.manifest["statistics"]
    return {
        "towns": len(cfg.towns),
        "frames": stats["frames"],
        "episodes": stats["episodes"],
        "wall_s": wall_s,
        "children_cpu_s": (c1.children_user + c1.children_system)
        - (c0.children_user + c0.children_system),
        "bytes": stats["bytes"],
        "stage": dict(report.stage_s),
        "peak_rss_mb": dict(report.peak_rss_mb),
    }


def print_build(name: str, r: dict, workers: int, limit_fps: float, bare_cpu_ms: float) -> None:
    frames = r["frames"]
    fps = frames / r["wall_s"]
    print(
        f"\n== {name} build: {r['towns']} towns, {frames} frames, {r['episodes']} episodes "
        f"({frames / max(r['episodes'], 1):.0f} frames each), --workers {workers}"
    )
    print(
        f"end to end: {r['wall_s']:.1f} s, {fps:.1f} frames/s (target >= {TARGET_FPS[name]:g}); "
        f"{fps / limit_fps:.2f} of the bare-Embree limit ({limit_fps:.1f} frames/s)"
    )
    if name == "long":
        print(f"paper scale (146k frames) at this rate: {build.PAPER_FRAMES / fps / 60:.0f} min")
    stage = dict(r["stage"])
    cpu_s = stage.pop("cpu_s", 0.0)
    busy = stage.get("episode_s", 0.0) + stage.get("write_s", 0.0)
    inner = {k: v for k, v in stage.items() if k not in ("episode_s", "write_s")}
    rows = [("run_episode (all stages below)", stage.get("episode_s", 0.0))]
    rows += [
        (f"  {k.removesuffix('_s')}", v) for k, v in sorted(inner.items(), key=lambda x: -x[1])
    ]
    rows += [("shard write (fsync, rename)", stage.get("write_s", 0.0))]
    rows += [("idle / process start / scheduling", max(0.0, workers * r["wall_s"] - busy))]
    print("stage breakdown, worker-seconds summed over episodes (per frame in ms):")
    for label, s in rows:
        print(f"  {label:<36} {s:8.1f} s  {1000 * s / frames:7.1f} ms/frame")
    print(
        f"  {'CPU time in run_episode':<36} {cpu_s:8.1f} s  {1000 * cpu_s / frames:7.1f} ms/frame"
        f"  -> {workers} idle cores: {workers * frames / max(cpu_s, 1e-9):.1f} frames/s"
    )
    print(
        f"  CPU-time view (steadier on a shared machine): {1000 * cpu_s / frames:.1f} ms a frame "
        f"vs bare Embree {bare_cpu_ms:.1f} ms CPU = {1000 * cpu_s / frames / bare_cpu_ms:.2f}x "
        "the ray-caster limit"
    )
    peak = max(r["peak_rss_mb"].values())
    per_frame = r["bytes"] / frames
    print(
        f"peak memory per worker: {peak:.0f} MB (target < {TARGET_RSS_MB:.0f}); output "
        f"{per_frame / 1e3:.1f} KB/frame (target <= {TARGET_BYTES_PER_FRAME / 1e3:g})"
    )
    ok = fps >= TARGET_FPS[name], peak < TARGET_RSS_MB, per_frame <= TARGET_BYTES_PER_FRAME
    print(
        "targets: "
        + ", ".join(
            f"{n} {'met' if k else 'MISSED'}" for n, k in zip(("speed", "memory", "size"), ok)
        )
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--towns", type=int, default=2)
    default = "towns x 4 weathers x one episode's frames: every episode runs its full length"
    p.add_argument("--long-frames", type=int, default=None, help=f"default: {default}")
    p.add_argument("--long-episode-seconds", type=float, default=build.EPISODE_SECONDS)
    p.add_argument("--short-frames", type=int, default=None, help=f"default: {default}")
    p.add_argument("--short-episode-seconds", type=float, default=30.0)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--executor", choices=("process", "ray"), default="process")
    p.add_argument("--limit-town", default="grid_small", help="town of the bare-Embree limit")
    p.add_argument("--limit-frames", type=int, default=20)
    args = p.parse_args()

    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at the start")
    m = measure(args.limit_town, frames=args.limit_frames)
    limit_fps = args.workers * 1e3 / m["bare_ms"]
    print(
        f"bare-Embree limit ({args.limit_town}, sunny, {m['rays']:.0f} rays a frame): "
        f"{m['bare_ms']:.1f} ms/frame wall -> {limit_fps:.1f} frames/s on {args.workers} workers; "
        f"sensors / bare in the same frames: {m['sensor_ms'] / m['bare_ms']:.2f}x wall, "
        f"{m['sensor_cpu_ms'] / m['bare_cpu_ms']:.2f}x CPU (bare {m['bare_cpu_ms']:.1f} ms CPU)"
    )
    for name, frames, secs in (
        ("long", args.long_frames, args.long_episode_seconds),
        ("short", args.short_frames, args.short_episode_seconds),
    ):
        if frames is None:  # a build cuts each town's quota per weather into episodes
            episode_frames = build.BuildConfig(towns=(), episode_seconds=secs).episode_frames
            frames = args.towns * len(schemas.WEATHERS) * episode_frames
        r = run_build(args, frames, secs)
        print_build(name, r, args.workers, limit_fps, m["bare_cpu_ms"])
    main_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\nmain process peak {main_mb:.0f} MB; load average {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    main()
