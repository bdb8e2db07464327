"""Soak `datagen build`: many short real-SUMO episodes per worker; prints figures, asserts nothing.

    .venv/bin/python bench/soak.py                                # 220 episodes, --workers 2
    .venv/bin/python bench/soak.py --episodes 400 --recycle 0     # never replace a worker
    .venv/bin/python bench/soak.py --executor ray

What it answers (issue 11): does a long build finish (the episode count), does it slow down
(frames/s of the first vs the last quarter of the episodes, by finishing order), and does a worker
leak (peak resident memory of each worker process after its first episode and at its last, and
the growth per 100 episodes). `--recycle 0` keeps every worker for the whole build, so the growth
is what recycling (executors.MAX_TASKS_PER_WORKER) would bound.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from datagen.dataset import build, executors  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=220, help="episodes planned (default 220)")
    p.add_argument("--episode-seconds", type=float, default=2.5, help="5 frames an episode")
    p.add_argument("--towns", type=int, default=2)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--recycle",
        type=int,
        default=executors.MAX_TASKS_PER_WORKER,
        help="episodes before a worker is replaced; 0 = never (default: %(default)s)",
    )
    p.add_argument("--executor", choices=("process", "ray"), default="process")
    args = p.parse_args()

    frames_per_episode = max(1, round(args.episode_seconds * 2))
    ns = argparse.Namespace(
        towns=args.towns,
        town=[],
        net=[],
        frames=args.episodes * frames_per_episode,
        seed=args.seed,
        episode_seconds=args.episode_seconds,
        weather_mix=None,
        sensor=[],
        workers=args.workers,
    )
    cfg = build.config_from_args(ns)  # builds and caches the towns
    options = build.RunOptions(
        workers=args.workers,
        executor=args.executor,
        max_episodes_per_worker=args.recycle or None,
    )
    out = Path(tempfile.mkdtemp(prefix="iidsu-soak-")) / "data"
    try:
        t0 = time.perf_counter()
        report = build.build(cfg, out, force=True, progress_bar=False, options=options)
        wall_s = time.perf_counter() - t0
    finally:
        shutil.rmtree(out.parent, ignore_errors=True)

    log = report.episode_log  # (t_s, episode_id, rows, worker, peak_rss_mb), finishing order
    stats = report.manifest["statistics"]
    print(
        f"soak: {len(log)} episodes of <= {frames_per_episode} frames, {stats['frames']} frames, "
        f"{len(cfg.towns)} towns, --workers {args.workers} --executor {args.executor}, "
        f"recycle after {args.recycle or 'never'}; {os.cpu_count()} cores, load average "
        f"{os.getloadavg()[0]:.1f} at the end (a shared machine: timings are noisy)"
    )
    print(f"status: {report.manifest['status']}; wall {wall_s:.0f} s")
    # The plan runs the towns one after the other, and towns differ in cost: compare the first
    # and last quarter of each town's episodes, as well as of the whole build.
    town_of = {e["episode_id"]: e["town"] for e in report.manifest["episodes"]}
    groups = {"all": log}
    for t in cfg.towns:
        groups[t.name] = [x for x in log if town_of[x[1]] == t.name]
    for name, entries in groups.items():
        if len(entries) < 8:
            continue
        first, last = _rate(entries, 0, log), _rate(entries, 3, log)
        print(
            f"frames/s {name:<12} first quarter {first:6.2f}, last quarter {last:6.2f}, "
            f"ratio last/first {last / first:.2f}  ({len(entries) // 4} episodes a quarter)"
        )
    by_worker = defaultdict(list)
    for t, _, _, worker, rss in log:
        by_worker[worker].append((t, rss))
    print("worker                        episodes  RSS after 1st (MB)  peak (MB)  growth/100 ep")
    for worker, series in sorted(by_worker.items(), key=lambda kv: kv[1][0][0]):
        n = len(series)
        growth = (series[-1][1] - series[0][1]) / max(n - 1, 1) * 100
        print(f"{worker:<30} {n:8d}  {series[0][1]:18.0f}  {series[-1][1]:9.0f}  {growth:10.1f}")
    peak = max(rss for *_, rss in log)
    print(f"peak RSS of any worker: {peak:.0f} MB")


def _rate(entries: list, quarter: int, log: list) -> float:
    """Frames per second over the `quarter`-th quarter (0..3) of `entries` (a part of `log`, in
    finishing order): its rows over the time from the finish of the episode before it in the
    whole log (0 for the very first) to the finish of its last one."""
    q = len(entries) // 4
    part = entries[quarter * q : (quarter + 1) * q]
    before = [x[0] for x in log if x[0] < part[0][0]]
    t0 = before[-1] if before else 0.0
    return sum(x[2] for x in part) / max(part[-1][0] - t0, 1e-9)


if __name__ == "__main__":
    main()
