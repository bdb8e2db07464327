"""Benchmark one recorded frame at the default sensor settings; prints figures, asserts nothing.

    .venv/bin/python bench/frame.py                      # grid_small, 40 frames, sunny
    .venv/bin/python bench/frame.py --town downtown --weather rainy --frames 60

Drives the expert in a built-in town and, for every recorded frame (2 Hz), times each stage the
way `datagen.episode.run_episode` runs it: sim (SUMO steps to the next frame), scene (actor
boxes + Embree commit; the town's static scene is committed once per process), lidar (sweep +
3-sweep BEV counts), camera, labels (BEV semantic raster, boxes, waypoints), encode (JPEG +
PNGs). Prints the median ms per stage (wall and CPU time: the machine is shared, CPU time is the
steadier figure), the rays per second achieved by the two sensor stages, and the limit: the very
same rays (LiDAR, camera, shadow rays; logged per frame) cast again by bare Embree queries
(datagen/sensors/embree.py) on the same committed scene, and the ratio of the two in the same run
(issue 12: sensors within 1.3x of bare Embree). `measure()` is also what bench/build.py calls for its limit.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from datagen import episode, labels  # noqa: E402
from datagen.sensors import config, lidar  # noqa: E402
from datagen.sensors.scene import load_static_scene  # noqa: E402
from datagen.world import World, WorldConfig  # noqa: E402
from datagen.world.towns import town_net_path  # noqa: E402
from schemas import FRAME_PERIOD_S, codecs  # noqa: E402

TARGET_SENSOR_OVER_BARE = 1.3


def measure(
    town: str = "grid_small",
    weather: str = "sunny",
    behaviour: str = "normal",
    frames: int = 40,
    seed: int = 1,
    skip: int = 4,
) -> dict:
    """Drive `frames` recorded frames (after `skip`) and return per-frame medians in ms:
    {"wall": {stage: ms}, "cpu": {stage: ms}, "sensor_ms", "bare_ms", "sensor_cpu_ms",
    "bare_cpu_ms", "rays", "triangles", "static_s", "n", "rebuilds", "mean_total_ms"}."""
    net = town_net_path(town)
    t0 = time.perf_counter()
    static = load_static_scene(net)
    t_static = time.perf_counter() - t0
    cfg = config.SensorConfig()
    sense = episode.Sensors(static, cfg, weather, episode.episode_rng(seed))
    wcfg = WorldConfig(net_path=net, seed=seed, weather=weather, behaviour=behaviour)
    stages = {k: [] for k in (*episode.STAGES, "total")}
    cpu = {k: [] for k in (*episode.STAGES, "total")}
    sensor_s, bare_s, rays, tris = [], [], [], []
    sensor_cpu, bare_cpu = [], []
    with World(wcfg) as world:
        states, sweeps = [], []
        for k in range(skip + frames + labels.FUTURE_FRAMES):
            t, c = time.perf_counter(), time.process_time()
            if k:
                world.advance(FRAME_PERIOD_S)
            if world.ended:
                print(f"world ended early: {world.ended}")
                break
            states.append(world.state())
            sim, sim_cpu = time.perf_counter() - t, time.process_time() - c
            if k < labels.FUTURE_FRAMES:
                continue
            frame = states[k - labels.FUTURE_FRAMES]
            future = states[k - labels.FUTURE_FRAMES + 1 :]
            c1, t1 = time.process_time(), time.perf_counter()
            scene = sense.scene(frame)
            scene.ray_log = []
            c2, t2 = time.process_time(), time.perf_counter()
            sweep = sense.sweep(scene, frame)
            sweeps = [sweep, *sweeps][: config.HISTORY + 1]
            counts = sense.lidar_counts(sweeps)
            bev, ground_t = lidar.lidar_bev_channels(counts), lidar.ground_channel(counts)
            c3, t3 = time.process_time(), time.perf_counter()
            image = sense.image(scene, frame)
            c4, t4 = time.process_time(), time.perf_counter()
            row = labels.frame_labels(frame, future, sweep.actor_hits).row()
            semantic = labels.bev_semantic(static.label_map, frame.ego.pose)
            c5, t5 = time.process_time(), time.perf_counter()
            codecs.encode_image(image, cfg.jpeg_quality)
            codecs.encode_lidar_bev(bev)
            codecs.encode_lidar_ground(ground_t)
            codecs.encode_bev_semantic(semantic)
            c6, t6 = time.process_time(), time.perf_counter()
            if k - labels.FUTURE_FRAMES < skip:
                continue
            for name, v, c in zip(
                episode.STAGES,
                (sim, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t6 - t5),
                (sim_cpu, c2 - c1, c3 - c2, c4 - c3, c5 - c4, c6 - c5),
            ):
                stages[name].append(v)
                cpu[name].append(c)
            stages["total"].append(sim + t6 - t1)
            cpu["total"].append(sim_cpu + c6 - c1)
            # The same rays, bare: one Embree query per logged cast (datagen/sensors/embree.py).
            tb, cb = time.perf_counter(), time.process_time()
            for query, emb, o, d, tfar in scene.ray_log:
                getattr(scene.backend, query)(emb, o, d, tfar)
            bare_s.append(time.perf_counter() - tb)
            bare_cpu.append(time.process_time() - cb)
            sensor_s.append(t4 - t2)
            sensor_cpu.append(c4 - c2)
            # sensor rays: the static-scene calls (the actor scene re-casts a subset of them)
            rays.append(sum(len(o) for _, e, o, _, _ in scene.ray_log if e is scene.static_embree))
            tris.append(scene.n_static + len(scene.actors.triangles_m))
            del row

    def ms(v):
        return 1e3 * float(np.median(v))

    return {
        "wall": {k: ms(v) for k, v in stages.items() if v},
        "cpu": {k: ms(v) for k, v in cpu.items() if v},
        "mean_total_ms": 1e3 * float(np.mean(stages["total"])),
        "sensor_ms": ms(sensor_s),
        "bare_ms": ms(bare_s),
        "sensor_cpu_ms": ms(sensor_cpu),
        "bare_cpu_ms": ms(bare_cpu),
        "rays": float(np.median(rays)),
        "triangles": float(np.median(tris)),
        "static_s": t_static,
        "n": len(stages["total"]),
        "rebuilds": sense.builder.rebuilds,
        "lidar_rays": sense.lidar.n_rays,
        "camera_rays": sense.camera.n_rays,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--town", default="grid_small")
    p.add_argument("--weather", default="sunny")
    p.add_argument("--behaviour", default="normal")
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--skip", type=int, default=4, help="frames driven before timing starts")
    args = p.parse_args()
    m = measure(args.town, args.weather, args.behaviour, args.frames, args.seed, args.skip)
    print(
        f"town {args.town}, weather {args.weather}, {m['n']} frames timed (medians), "
        f"pid {os.getpid()}, static scene loaded/built in {m['static_s']:.2f} s"
    )
    print(
        f"scene per frame: {m['triangles']:.0f} triangles; rays per frame {m['rays']:.0f} "
        f"(LiDAR {m['lidar_rays']}, camera {m['camera_rays']}, rest shadow rays)"
    )
    print(f"  {'stage':8s} {'wall':>8s} {'cpu':>8s}  (ms per frame, medians)")
    for k in (*episode.STAGES, "total"):
        print(f"  {k:8s} {m['wall'][k]:8.2f} {m['cpu'][k]:8.2f}")
    r = m["rays"]
    print(f"LiDAR + camera: {m['sensor_ms']:.2f} ms = {r / m['sensor_ms'] / 1e3:.2f} Mrays/s")
    print(
        f"bare Embree, same rays and scene: {m['bare_ms']:.2f} ms = "
        f"{r / m['bare_ms'] / 1e3:.2f} Mrays/s (limit); sensors / bare = "
        f"{m['sensor_ms'] / m['bare_ms']:.2f}x wall, "
        f"{m['sensor_cpu_ms'] / m['bare_cpu_ms']:.2f}x CPU "
        f"({m['sensor_cpu_ms']:.2f} vs {m['bare_cpu_ms']:.2f} ms; target <= "
        f"{TARGET_SENSOR_OVER_BARE}x)"
    )
    print(
        f"whole frame: {m['wall']['total']:.1f} ms median wall, {m['cpu']['total']:.1f} ms CPU "
        f"-> {1e3 / m['cpu']['total']:.1f} frames/s per idle core; culled static rebuilds: "
        f"{m['rebuilds']}; load average {os.getloadavg()[0]:.2f}"
    )


if __name__ == "__main__":
    main()
