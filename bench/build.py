"""Benchmark `datagen build` end to end on a fixed small dataset; prints figures, asserts nothing.

    .venv/bin/python bench/build.py                      # 2 towns, 600 frames, --workers 2
    .venv/bin/python bench/build.py --frames 2000 --towns 4 --workers 2 --executor ray

Prints frames/s end to end (town preparation excluded: towns are cached after the first build),
the stage breakdown summed over the workers' episodes, peak memory per worker process and bytes
per frame on disk, against the issue's targets for this 2-core machine: >= 30 frames/s with
--workers 2 (146k frames in under 90 minutes), < 1.5 GB per worker, <= 60 KB per frame.
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

from datagen import build  # noqa: E402

TARGET_FPS = 30.0
TARGET_RSS_MB = 1536.0
TARGET_BYTES_PER_FRAME = 60_000


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--towns", type=int, default=2)
    p.add_argument("--frames", type=int, default=600)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episode-seconds", type=float, default=60.0)
    p.add_argument("--executor", choices=("process", "ray"), default="process")
    p.add_argument("--out", type=Path, default=None, help="keep the dataset here")
    args = p.parse_args()

    ns = argparse.Namespace(
        towns=args.towns,
        town=[],
        net=[],
        frames=args.frames,
        seed=args.seed,
        episode_seconds=args.episode_seconds,
        weather_mix=None,
        sensor=[],
        workers=args.workers,
    )
    t0 = time.perf_counter()
    cfg = build.config_from_args(ns)  # builds and caches the towns
    prep_s = time.perf_counter() - t0
    out = args.out or Path(tempfile.mkdtemp(prefix="iidsu-bench-")) / "data"
    try:
        t0 = time.perf_counter()
        report = build.build(
            cfg, out, workers=args.workers, force=True, executor=args.executor, progress_bar=False
        )
        wall_s = time.perf_counter() - t0
    finally:
        if args.out is None:
            shutil.rmtree(out.parent, ignore_errors=True)

    stats = report.manifest["statistics"]
    frames = stats["frames"]
    fps = frames / wall_s
    per_frame = stats["bytes"] / frames
    peak = max(report.peak_rss_mb.values())
    print(
        f"datagen build: {len(cfg.towns)} towns, {frames} frames, {stats['episodes']} episodes, "
        f"--workers {args.workers} --executor {args.executor}, {os.cpu_count()} cores"
    )
    print(f"town preparation (cached after the first run): {prep_s:.1f} s")
    print(f"end to end: {wall_s:.1f} s, {fps:.1f} frames/s  (target >= {TARGET_FPS:g})")
    print(
        f"paper scale (146k frames) at this rate: {build.PAPER_FRAMES / fps / 60:.0f} min "
        "(target < 90 min)"
    )

    stage = dict(report.stage_s)
    busy = stage.get("episode_s", 0.0) + stage.get("write_s", 0.0)
    print("\nstage breakdown, worker-seconds summed over episodes (per frame in ms):")
    cpu_s = stage.pop("cpu_s", 0.0)
    inner = {k: v for k, v in stage.items() if k not in ("episode_s", "write_s")}
    rows = [("run_episode (all stages below)", stage.get("episode_s", 0.0))]
    rows += [
        (f"  {k.removesuffix('_s')}", v) for k, v in sorted(inner.items(), key=lambda x: -x[1])
    ]
    rows += [("shard write (fsync, rename)", stage.get("write_s", 0.0))]
    rows += [("idle / process start / scheduling", max(0.0, args.workers * wall_s - busy))]
    for name, s in rows:
        print(f"  {name:<36} {s:8.1f} s  {1000 * s / frames:7.1f} ms/frame")
    print(
        f"  {'CPU time in run_episode':<36} {cpu_s:8.1f} s  {1000 * cpu_s / frames:7.1f} ms/frame"
        f"  -> {args.workers} idle cores: {args.workers * frames / max(cpu_s, 1e-9):.1f} frames/s"
    )
    if stage.get("episode_s", 0.0) > 1.2 * cpu_s:
        print(
            f"  (episodes took {stage['episode_s'] / max(cpu_s, 1e-9):.1f}x their CPU time: the "
            "machine was shared, wall times include waiting for a core)"
        )

    print("\npeak memory per worker process (ru_maxrss):")
    for key, mb in sorted(report.peak_rss_mb.items()):
        print(f"  {key:<28} {mb:7.0f} MB")
    main_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"  {'main process':<28} {main_mb:7.0f} MB   (target < {TARGET_RSS_MB:.0f} MB a worker)")
    print(
        f"\noutput: {stats['bytes'] / 1e6:.1f} MB, {per_frame / 1e3:.1f} KB/frame "
        f"(target <= {TARGET_BYTES_PER_FRAME / 1e3:g})"
    )
    ok = fps >= TARGET_FPS, peak < TARGET_RSS_MB, per_frame <= TARGET_BYTES_PER_FRAME
    print(
        "targets: "
        + ", ".join(
            f"{n} {'met' if k else 'MISSED'}" for n, k in zip(("speed", "memory", "size"), ok)
        )
    )


if __name__ == "__main__":
    main()
