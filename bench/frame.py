"""Benchmark one recorded frame at the default sensor settings; prints figures, asserts nothing.

    .venv/bin/python bench/frame.py                      # grid_small, 40 frames, sunny
    .venv/bin/python bench/frame.py --town downtown --weather rainy --frames 60

Drives the expert in a built-in town and, for every recorded frame (2 Hz), times each stage the
way `datagen.episode.run_episode` runs it: sim (SUMO steps to the next frame), scene (cull +
actor boxes + Embree commit), lidar (sweep + 3-sweep BEV histogram), camera, labels (BEV
semantic raster, boxes, waypoints), encode (JPEG + PNGs). Prints the median ms per stage, the
rays per second achieved by the two sensor stages, and the limit: the very same rays (LiDAR,
camera, shadow rays; logged per frame) cast again by bare embreex `scene.run` calls on the same
committed scene. Targets (issue 5): LiDAR + camera within 1.5x of the bare-Embree time, a whole
frame under 50 ms on one core.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from datagen import episode, labels, lidar  # noqa: E402
from datagen.scene import load_static_scene  # noqa: E402
from datagen.towns import town_net_path  # noqa: E402
from datagen.world import World, WorldConfig  # noqa: E402
from schemas import codecs  # noqa: E402

TARGET_FRAME_MS = 50.0
TARGET_SENSOR_OVER_BARE = 1.5


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--town", default="grid_small")
    p.add_argument("--weather", default="sunny")
    p.add_argument("--behaviour", default="normal")
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--skip", type=int, default=4, help="frames driven before timing starts")
    args = p.parse_args()

    net = town_net_path(args.town)
    t0 = time.perf_counter()
    static = load_static_scene(net)
    t_static = time.perf_counter() - t0
    cfg = episode.SensorConfig()
    sense = episode.Sensors(static, cfg, args.weather, episode.episode_rng(args.seed))
    wcfg = WorldConfig(net_path=net, seed=args.seed, weather=args.weather, behaviour=args.behaviour)
    stages = {k: [] for k in (*episode.STAGES, "total")}
    cpu = {k: [] for k in (*episode.STAGES, "total")}
    sensor_s, bare_s, rays, tris = [], [], [], []
    sensor_cpu, bare_cpu = [], []
    with World(wcfg) as world:
        states, sweeps = [], []
        for k in range(args.skip + args.frames + labels.FUTURE_FRAMES):
            t, c = time.perf_counter(), time.process_time()
            if k:
                world.advance(0.5)
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
            sweeps = [sweep, *sweeps][: episode.HISTORY + 1]
            counts = sense.lidar_counts(sweeps)
            bev, ground_t = lidar.lidar_bev_channels(counts), lidar.ground_channel(counts)
            c3, t3 = time.process_time(), time.perf_counter()
            image = sense.image(scene, frame)
            c4, t4 = time.process_time(), time.perf_counter()
            row = labels.frame_labels(frame, future, sweep.actor_hits)
            semantic = labels.bev_semantic(static.label_map, frame.ego.pose)
            c5, t5 = time.process_time(), time.perf_counter()
            codecs.encode_image(image, cfg.jpeg_quality)
            codecs.encode_lidar_bev(bev)
            codecs.encode_lidar_ground(ground_t)
            codecs.encode_bev_semantic(semantic)
            c6, t6 = time.process_time(), time.perf_counter()
            if k - labels.FUTURE_FRAMES < args.skip:
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
            # The same rays, bare: one embreex call per logged cast, primary ids only.
            tb, cb = time.perf_counter(), time.process_time()
            for emb, query, o, d, dists in scene.ray_log:
                emb.run(o, d, dists=dists, query=query)
            bare_s.append(time.perf_counter() - tb)
            bare_cpu.append(time.process_time() - cb)
            sensor_s.append(t4 - t2)
            sensor_cpu.append(c4 - c2)
            # sensor rays: the static-scene calls (the actor scene re-casts a subset of them)
            rays.append(sum(len(o) for e, _, o, _, _ in scene.ray_log if e is scene.static_embree))
            tris.append(scene.n_static + len(scene.actors.triangles_m))
            del row

    med = {k: 1e3 * float(np.median(v)) for k, v in stages.items() if v}
    mean = {k: 1e3 * float(np.mean(v)) for k, v in stages.items() if v}
    med_cpu = {k: 1e3 * float(np.median(v)) for k, v in cpu.items() if v}
    n = len(stages["total"])
    print(
        f"town {args.town}, weather {args.weather}, {n} frames timed (medians), "
        f"pid {os.getpid()}, static scene {static.n_triangles} triangles "
        f"(loaded/built in {t_static:.2f} s)"
    )
    print(
        f"scene per frame: {np.median(tris):.0f} triangles; rays per frame {np.median(rays):.0f} "
        f"(LiDAR {sense.lidar.n_rays}, camera {sense.camera.n_rays}, rest shadow rays)"
    )
    print(
        f"  {'stage':8s} {'median':>8s} {'mean':>8s} {'cpu':>8s}  (ms; cpu = median process time)"
    )
    for k in (*episode.STAGES, "total"):
        print(f"  {k:8s} {med[k]:8.2f} {mean[k]:8.2f} {med_cpu[k]:8.2f}")
    sensor_ms = 1e3 * float(np.median(sensor_s))
    bare_ms = 1e3 * float(np.median(bare_s))
    r = float(np.median(rays))
    print(f"LiDAR + camera: {sensor_ms:.2f} ms = {r / sensor_ms / 1e3:.2f} Mrays/s achieved")
    print(
        f"bare Embree, same rays and scene: {bare_ms:.2f} ms = {r / bare_ms / 1e3:.2f} Mrays/s "
        f"(limit); sensors / bare = {sensor_ms / bare_ms:.2f}x (target <= {TARGET_SENSOR_OVER_BARE}x)"
    )
    s_cpu, b_cpu = 1e3 * float(np.median(sensor_cpu)), 1e3 * float(np.median(bare_cpu))
    print(
        f"  in CPU time: sensors {s_cpu:.2f} ms, bare Embree {b_cpu:.2f} ms = {s_cpu / b_cpu:.2f}x"
    )
    print(
        f"whole frame: {med['total']:.1f} ms median, {mean['total']:.1f} ms mean, "
        f"{med_cpu['total']:.1f} ms CPU (target < {TARGET_FRAME_MS:.0f} ms) -> "
        f"{1e3 / mean['total']:.1f} frames/s per core; static scene rebuilds: "
        f"{sense.builder.rebuilds}; load average {os.getloadavg()[0]:.2f}"
    )


if __name__ == "__main__":
    main()
