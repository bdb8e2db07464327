"""Benchmark the driving world: simulation speed, ego behaviour per profile, safety.

    python bench/sim.py                    # 24 episodes of 120 s over the 8 towns
    python bench/sim.py --episodes 420 --seconds 180 --workers 2 --quiet   # paper scale

Prints per episode and in total: simulated seconds per wall second (the World's own stepping,
expert included, recorded at 2 Hz), wall milliseconds per recorded frame, mean ego speed and
median time gap while following per behaviour profile, how episodes ended, and the safety
figures per 100 episodes: ego collisions, red-light runs, teleports (all vehicles, and of the
ego), hard brakes (steps where SUMO's safety model braked harder than any command), with the
town, seed and detail of every episode that ended in an ego collision (each is a regression
case: `WorldConfig(town_net_path(town), seed, weather, behaviour)`). Conditions are drawn as
`datagen build` draws them (behaviour.draw_condition); episode i drives town i mod len(towns).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections import Counter, defaultdict
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from datagen.world import World, WorldConfig, record  # noqa: E402
from datagen.world.behaviour import draw_condition  # noqa: E402
from datagen.world.towns import TOWN_NAMES, town_net_path  # noqa: E402
from schemas import FRAME_RATE_HZ  # noqa: E402


def run_episode(job: tuple[str, int, float]) -> dict:
    """One episode of `seconds` simulated seconds recorded at 2 Hz; its stats and timings."""
    town, seed, seconds = job
    weather, behaviour = draw_condition(np.random.default_rng(seed))
    cfg = WorldConfig(net_path=town_net_path(town), seed=seed, weather=weather, behaviour=behaviour)
    t0 = time.perf_counter()
    with World(cfg) as world:
        t1 = time.perf_counter()
        frames = sum(1 for _ in record(world, int(seconds * FRAME_RATE_HZ) + 1))
        t2 = time.perf_counter()
        st = world.stats
    return dict(
        town=town,
        seed=seed,
        weather=weather,
        behaviour=behaviour,
        frames=frames,
        init_s=t1 - t0,
        sim_per_wall=st["sim_s"] / max(t2 - t1, 1e-9),
        ms_per_frame=1000 * (t2 - t1) / max(frames, 1),
        **st,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--episodes", type=int, default=24)
    ap.add_argument("--seconds", type=float, default=120.0, help="simulated seconds per episode")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--towns", default=",".join(TOWN_NAMES))
    ap.add_argument("--workers", type=int, default=1, help="episodes in parallel processes")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    towns = args.towns.split(",")
    for t in towns:
        town_net_path(t)  # build the cached networks once, before the workers race for them
    jobs = [
        (towns[i % len(towns)], args.seed * 100_000 + i, args.seconds) for i in range(args.episodes)
    ]
    rows = []
    t_all = time.perf_counter()
    workers = max(1, min(args.workers, os.cpu_count() or 1))
    with ProcessPoolExecutor(workers) if workers > 1 else _Serial() as pool:
        for i, row in enumerate(pool.map(run_episode, jobs)):
            rows.append(row)
            st = row
            if not args.quiet:
                print(
                    f"{i:3d} {row['town']:12s} {row['behaviour']:10s} frames={row['frames']:4d} "
                    f"sim/wall={row['sim_per_wall']:6.1f} ms/frame={row['ms_per_frame']:5.2f} "
                    f"v={st['mean_speed_mps']:5.2f} "
                    f"gap={st['median_time_gap_s'] or float('nan'):5.2f} "
                    f"coll={st['collisions']} rlv={st['red_light_violations']} "
                    f"tele={st['teleports']} end={st['ended']} {st['end_detail']}",
                    flush=True,
                )
    wall = time.perf_counter() - t_all
    sim = sum(r["sim_s"] for r in rows)
    step_wall = sum(r["sim_s"] / r["sim_per_wall"] for r in rows)
    print(f"\nepisodes {len(rows)}, simulated {sim:.0f} s in {wall:.1f} s wall (init included)")
    print(
        f"stepping: {sim / step_wall:.1f} simulated s per wall s; "
        f"median {statistics.median(r['ms_per_frame'] for r in rows):.2f} ms per recorded frame "
        f"(5 steps of 0.1 s); init median {statistics.median(r['init_s'] for r in rows):.2f} s"
    )
    by = defaultdict(list)
    for r in rows:
        by[r["behaviour"]].append(r)
    for b, rs in sorted(by.items()):
        # per-episode medians weighted by how long each episode followed a lead
        gaps = [(r["median_time_gap_s"], r["following_s"]) for r in rs if r["following_s"] > 0]
        gap = sum(g * w for g, w in gaps) / sum(w for _, w in gaps) if gaps else float("nan")
        print(
            f"  {b:10s} episodes {len(rs):3d}  mean ego speed "
            f"{statistics.mean(r['mean_speed_mps'] for r in rs):5.2f} m/s  median time gap "
            f"{gap:5.2f} s (following {sum(w for _, w in gaps):.0f} s)"
        )
    n = len(rows)
    per100 = 100.0 / max(n, 1)
    ego_tele = sum(r["ended"] == "teleported" for r in rows)
    totals = {
        "ego collisions": sum(r["collisions"] for r in rows),
        "red-light runs": sum(r["red_light_violations"] for r in rows),
        "teleports (all vehicles)": sum(r["teleports"] for r in rows),
        "ego teleports": ego_tele,
        "hard brakes": sum(r["hard_brakes"] for r in rows),
        "background collisions": sum(r["other_collisions"] for r in rows),
    }
    print(f"per 100 episodes ({n} episodes of {args.seconds:.0f} s):")
    for k, v in totals.items():
        print(f"  {k:26s} {v * per100:8.2f}   (total {v})")
    for r in rows:
        if r["collisions"]:
            print(
                f"  collision: town={r['town']} seed={r['seed']} weather={r['weather']} "
                f"behaviour={r['behaviour']} at {r['sim_s']:.1f} s: {r['end_detail']}"
            )
    print(f"episode ends: {dict(Counter(r['ended'] or 'ran full length' for r in rows))}")
    reasons = Counter()
    for r in rows:
        reasons.update(r["reasons"])
    total = sum(reasons.values())
    print(
        "expert reasons (share of steps): "
        + ", ".join(f"{k} {v / total:.1%}" for k, v in reasons.most_common())
    )
    return 0


class _Serial:
    """map() in this process (one worker: no pool, easier to profile)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None

    def map(self, fn, jobs):
        return map(fn, jobs)


if __name__ == "__main__":
    sys.exit(main())
