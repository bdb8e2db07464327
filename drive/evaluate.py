"""`drive eval`: drive every route of a route file with one policy and score it.

    drive eval --policy ckpt:runs/demo/last.pt --routes drive/routes/heldout_short.json --out runs/eval
    drive eval --policy expert --routes drive/routes/heldout_short.json --workers 2 --out runs/expert

Per route (one SUMO world each, seeded by the route): the world's traffic runs around the ego;
every 0.1 s step the infraction tracker (drive/infractions.py) judges the ground truth. The
expert drives inside the world as when recording data; any other policy plans 4 waypoints at
2 Hz (the data's rate) and the controller (drive/controller.py) moves the ego every step,
placed in SUMO anywhere (off its lane or the road too) with its speed, so others react to it.
A policy that has stood still 55 s creeps forward unless its LiDAR sees something just ahead
(TransFuser's creep, `drive.controller.Creep`; `--no-creep` turns it off); each route's result
counts its creeps.
The route ends when it is complete, on a route deviation, a blocked agent or a timeout; a
collision ends nothing (the expert's world drives on after one, as the leaderboard does).

`--repetitions N` drives every route N times (the leaderboard's `--repetitions`): repetition 0
with the route's own seed, repetition r with a seed drawn from (route seed, r) for the traffic
and the sensors' noise (repetition_seed); the summary averages a route's repetitions before
taking means and intervals over routes (drive/score.py).

Writes OUT/routes/<route_id>.json (repetition 0; <route_id>_rep<r>.json for the others: scores,
every infraction with time and position, the extra measures, timing apart under "timing"),
OUT/summary.json and OUT/summary.txt (the table of the paper's Table III), and with --record N,
OUT/videos/<route_id>.mp4 for the first N routes. A route whose drive fails (the simulation
raised) is recorded as failed with its reason under "failure" (scored DS 0, as the leaderboard
scores a crashed route) and the others go on. Rerunning the same command resumes: finished
routes are kept, failed and missing ones are driven; results of another policy or setting in
OUT are refused. The same route file, policy and checkpoint give the same numbers (timing
aside).
"""

from __future__ import annotations

import json
import os
import time
import traceback
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from datagen.errors import UserError
from datagen.world import TELEPORT_S
from drive import score
from drive.controller import (
    Controller,
    ControllerConfig,
    Creep,
    Plan,
    VehicleState,
    bicycle_step,
    safety_box_clear,
)
from drive.policy import PolicySpec, constant_waypoints
from drive.routes import Route, resolve_net
from drive.summary import format_summary, result_key, result_name, summary_doc
from schemas import FRAME_PERIOD_S, outputs

PLAN_PERIOD_S = FRAME_PERIOD_S  # the policy plans at the data's rate (2 Hz)
STUCK_MPS = 0.1  # slower than this, a policy stands (counted at every plan, 2 Hz)
STEP_S = 0.1  # SUMO step: the controller and the infraction tracker run every step
# The expert's world gives up on an ego that stands 80 s or that SUMO teleports out of a jam:
# for the score that is the agent blocked.
WORLD_BLOCKED = ("blocked", "teleported")
_LAYOUTS: dict = {}  # network sha256 -> drive.layout.Layout of this process
_MODELS: dict = {}  # (checkpoint, device) -> drive.policy.ModelPolicy of this process


@dataclass(frozen=True)
class Task:
    """One route to drive: the route, the policy, where to write, whether to record a video."""

    route: Route
    policy: PolicySpec
    out_dir: str
    record: bool
    net_override: str | None = None
    max_sim_s: float | None = None  # stop after this much simulated time (smoke runs)
    creep: bool = True  # a policy that stands still creeps (drive.controller.Creep)
    repetition: int = 0  # which repetition of the route (repetition_seed)
    lateral: str = "pursuit"  # the controller's steering (drive.controller.ControllerConfig)
    run: dict = field(default_factory=dict)  # what a result must match to be resumed (run_key)


def repetition_seed(route_seed: int, repetition: int) -> int:
    """The world's and the sensors' seed of a route's repetition: the route's own for
    repetition 0, else one drawn from (route seed, repetition)."""
    if repetition == 0:
        return int(route_seed)
    state = np.random.SeedSequence([int(route_seed), int(repetition)]).generate_state(1)
    return int(state[0] % (2**31 - 1))


def _write_json(path: Path, doc: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, path)


def drive_route(
    task: Task,
    planner: Callable[[object], np.ndarray] | None = None,
    on_start: Callable[[], None] | None = None,
    world_options: dict | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict:
    """Drive one route; returns (and writes) its result document.

    For scripted tests: `planner(frame) -> (4, 2)` ego-frame waypoints replaces the policy,
    `on_start()` runs once the world has started (e.g. to park a car with libsumo), and
    `world_options` overrides WorldConfig fields (n_vehicles, n_pedestrians, warmup_s).
    `task.max_sim_s` stops the route after that much simulated time (bench/drive.py, smoke
    runs); it is scored as far as it got and ends "max_sim_s".
    """
    from datagen.episode import Sensors, episode_rng
    from datagen.sensors.config import SensorConfig
    from datagen.sensors.scene import load_static_scene
    from drive.geometry import route_geometry
    from drive.infractions import InfractionTracker
    from drive.layout import Layout
    from drive.policy import ModelPolicy
    from drive.sim import DrivenWorld, SensorStream

    t0 = time.perf_counter()
    spec = task.policy
    route = replace(task.route, seed=repetition_seed(task.route.seed, task.repetition))
    name = result_name(route.route_id, task.repetition)
    net = resolve_net(route, Path(task.net_override) if task.net_override else None)
    geom = route_geometry(net, route.edges)
    static = load_static_scene(net)
    layout = _LAYOUTS.get(static.network_sha256)
    if layout is None:  # one town per worker at a time, as the static scene's cache
        _LAYOUTS.clear()
        layout = _LAYOUTS[static.network_sha256] = Layout.from_static(static)
    sensor_cfg = SensorConfig()
    model = None
    if spec.kind == "ckpt":  # loaded once per worker process
        key = (spec.path, spec.device)
        if key not in _MODELS:
            _MODELS.clear()
            _MODELS[key] = ModelPolicy(spec, sensor_cfg.to_dict())
        model = _MODELS[key]
        model.reset()

    def sensor_stream() -> SensorStream:
        sense = Sensors(static, sensor_cfg, route.weather, episode_rng(route.seed))
        return SensorStream(sense, sensor_cfg.jpeg_quality)

    # encoded at every plan for a model or a video; else started only when the creep needs them
    encode = (model is not None and model.needs_sensors) or task.record
    sensors = sensor_stream() if encode else None
    recorder = None
    if task.record:
        from drive.video import Recorder

        recorder = Recorder(Path(task.out_dir) / "videos" / f"{name}.mp4")
    tracker = InfractionTracker(geom, layout)
    timing = {"setup": time.perf_counter() - t0, "sim": 0.0, "sensors": 0.0, "policy": 0.0}
    timing.update(judge=0.0)
    external = planner is not None or not spec.privileged
    creep = Creep(step_s=STEP_S) if task.creep and external else None
    clear_ahead = False  # the creep's safety box at the last plan, looked at only when due
    # a collision ends no route (the leaderboard drives on): the same judge scores every policy
    options = {"end_on_collision": False, **(world_options or {})}
    with DrivenWorld(net, route, external=external, **options) as world:
        if on_start is not None:
            on_start()
        frame = world.state()
        timing["setup"] = time.perf_counter() - t0  # the world's start-up (warm-up) included
        vehicle = VehicleState(frame.ego.pose, frame.ego.speed_mps)
        controller = Controller(ControllerConfig(lateral=task.lateral))
        plan: Plan | None = None
        waypoints = None
        steps_per_plan = round(PLAN_PERIOD_S / STEP_S)
        max_sim_s = task.max_sim_s
        k = 0
        standing_s = stuck_s = 0.0  # standing, and standing where the expert would drive on
        while True:
            t = time.perf_counter()
            tracker.step(frame, STEP_S)
            timing["judge"] += time.perf_counter() - t
            if tracker.ended is not None or world.ended is not None:
                break
            if max_sim_s is not None and frame.time_s - tracker.start_time_s >= max_sim_s:
                break
            if k % steps_per_plan == 0:
                if progress is not None:
                    progress(0)
                if external and vehicle.speed_mps < STUCK_MPS:
                    standing_s += PLAN_PERIOD_S
                    stuck_s += PLAN_PERIOD_S if world.expert_would_go() else 0.0
                t = time.perf_counter()
                image_jpeg = lidar_png = ground_png = None
                if encode:
                    image_jpeg, lidar_png, ground_png = sensors.encode(frame)
                if creep is not None and creep.due:
                    if sensors is None:
                        sensors = sensor_stream()
                    sweep = sensors.last_sweep if encode else sensors.sweep(frame)
                    ego = frame.ego
                    clear_ahead = safety_box_clear(
                        sweep.points_m, ego.pose, ego.length_m, ego.width_m, creep.config
                    )
                else:
                    clear_ahead = False
                timing["sensors"] += time.perf_counter() - t
                t = time.perf_counter()
                if planner is not None:
                    waypoints = planner(frame)
                elif model is not None and not model.needs_sensors:
                    waypoints = model.plan_privileged(frame, static.label_map)
                elif model is not None:
                    waypoints = model.plan(frame, image_jpeg, lidar_png, ground_png)
                elif spec.kind == "constant":
                    waypoints = constant_waypoints()
                elif spec.kind == "expert-plan":  # None off the network: the last plan holds
                    waypoints = world.expert_waypoints(frame)
                if waypoints is not None:
                    plan = Plan.from_ego(frame.time_s, frame.ego.pose, waypoints)
                timing["policy"] += time.perf_counter() - t
                if recorder is not None:
                    recorder.add(frame, image_jpeg, lidar_png, plan, tracker)
            t = time.perf_counter()
            if plan is not None:
                push = creep.step(vehicle.speed_mps, clear_ahead) if creep is not None else 0.0
                aim = plan.at(frame.time_s, vehicle.pose)
                ahead = plan.ahead(frame.time_s, vehicle.pose)
                ctrl = controller.control(aim, vehicle.speed_mps, push, ahead)
                vehicle = bicycle_step(vehicle, ctrl, STEP_S)
                world.place_ego(vehicle.pose, vehicle.speed_mps)
            world.step()
            if world.ended is not None:  # SUMO may have taken the ego out: no state to read
                if plan is not None and tracker.ended is None:
                    # a placed ego is where the controller put it: judge that last step
                    tracker.step(_placed(frame, vehicle), STEP_S)
                timing["sim"] += time.perf_counter() - t
                break
            frame = world.state()
            if plan is None:  # the expert drives: follow its state
                vehicle = VehicleState(frame.ego.pose, frame.ego.speed_mps)
            timing["sim"] += time.perf_counter() - t
            k += 1
        world_end = world.ended
        world_detail = world.end_detail
        judge_world_end(tracker, frame, world_end, world_detail, external)
        sim_s = frame.time_s - (tracker.start_time_s or frame.time_s)
    if recorder is not None:
        recorder.close()
    result = score.score_route(
        tracker.route_completion_pct, tracker.counts(), tracker.off_route_share, geom.length_m
    )
    timing["total"] = time.perf_counter() - t0
    doc = {
        "route": task.route.to_dict(),
        "repetition": task.repetition,
        "seed": route.seed,
        "run": task.run,
        "policy": spec.name,
        "complete": tracker.complete,
        "rc": round(result.rc, 4),
        "is": round(result.infraction_score, 6),
        "ds": round(result.ds, 4),
        "counts": result.counts,
        "events": [e.to_dict() for e in tracker.events],
        "off_road_share": round(tracker.off_road_share, 6),
        "off_route_share": round(result.off_route_share, 6),
        "km_driven": round(result.km_driven, 6),
        "distance_m": round(tracker.distance_m, 3),
        "min_ttc_s": None if not np.isfinite(tracker.min_ttc_s) else round(tracker.min_ttc_s, 2),
        "traffic_delay_s": round(tracker.traffic_delay_s, 3),
        # per simulated second: comparable between drives of different length
        "traffic_delay_rate": round(tracker.traffic_delay_s / max(sim_s, 1e-6), 4),
        "sim_s": round(sim_s, 2),
        "ended": tracker.ended or (f"world_{world_end}" if world_end else "max_sim_s"),
        "creeps": creep.creeps if creep is not None else 0,
        "standing_s": round(standing_s, 1),
        "stuck_s": round(stuck_s, 1),
        "end_detail": world_detail if tracker.ended is None else "",
        "timing": {k: round(v, 4) for k, v in timing.items()},
    }
    _write_json(Path(task.out_dir) / "routes" / f"{name}.json", doc)
    return doc


def judge_world_end(tracker, frame, world_end: str | None, detail: str, external: bool) -> None:
    """Score a drive the world ended before the tracker did (`frame`: the last state).

    SUMO teleports a vehicle that has waited TELEPORT_S, a placed ego too (the world ends the
    drive then): standing that long is the agent blocked. SUMO taking a placed ego out away
    from its route's lanes (it had mapped the ego to another road) is a route deviation, however
    close to the route that was (the leaderboard's InRouteTest would have seen it leave)."""
    if tracker.ended is not None or world_end is None:
        return
    standing = tracker.standing_s >= TELEPORT_S - 1.0
    if world_end in WORLD_BLOCKED or standing:
        tracker.end("agent_blocked", frame, f"{world_end}: {detail}")
    elif world_end == "route_end" and external and not tracker.complete:
        p = frame.ego.pose
        if not tracker.geometry.in_lanes(p.x_m, p.y_m):
            off = tracker.route_distance_m(frame)
            tracker.end("route_deviation", frame, f"{detail}, {off:.1f} m from the route")


def _placed(frame, vehicle: VehicleState):
    """The frame after a last step whose state SUMO could not give: the ego where the
    controller placed it, no agents (their positions are unknown)."""
    ego = replace(frame.ego, pose=vehicle.pose, speed_mps=vehicle.speed_mps)
    return replace(frame, time_s=frame.time_s + STEP_S, ego=ego, agents=())


def failed_doc(task: Task, reason: str) -> dict:
    """The result document of a route whose drive failed (RC 0, IS 1, DS 0: score.py)."""
    s = score.failed_route(task.route.route_id)
    return {
        "route": task.route.to_dict(),
        "repetition": task.repetition,
        "seed": repetition_seed(task.route.seed, task.repetition),
        "run": task.run,
        "policy": task.policy.name,
        "complete": False,
        "failure": reason,
        "rc": s.rc,
        "is": s.infraction_score,
        "ds": s.ds,
        "counts": s.counts,
        "events": [],
        "off_road_share": 0.0,
        "off_route_share": 0.0,
        "km_driven": 0.0,
        "distance_m": 0.0,
        "min_ttc_s": None,
        "traffic_delay_s": 0.0,
        "traffic_delay_rate": 0.0,
        "sim_s": 0.0,
        "ended": "failed",
        "creeps": 0,
        "end_detail": reason,
        "timing": {"total": 0.0},
    }


def drive_or_fail(task: Task, progress: Callable[[int], None] | None = None) -> dict:
    """drive_route, or the failed route's document (also written) when the drive raises
    anything but a UserError (the leaderboard's crashed route: the others go on)."""
    try:
        return drive_route(task, progress=progress)
    except UserError:
        raise
    except Exception as e:  # noqa: BLE001 - any failure of one route is that route's result
        last = traceback.extract_tb(e.__traceback__)[-1]
        reason = f"{type(e).__name__}: {e} ({Path(last.filename).name}:{last.lineno})"
        doc = failed_doc(task, reason)
        name = result_name(task.route.route_id, task.repetition)
        _write_json(Path(task.out_dir) / "routes" / f"{name}.json", doc)
        return doc


def check_routes(
    routes: list[Route], net_override: Path | None = None, routes_file: Path | None = None
) -> dict:
    """UserError, before any driving, for a route whose network is not the one it was made for
    (sha256) or whose edges are not a drivable path in it; the networks resolved, by (town,
    net_name, sha256) (a user network's path travels with the tasks: workers have no route file
    to look beside)."""
    from drive.geometry import route_geometry

    nets: dict = {}
    for r in routes:
        key = (r.town, r.net_name, r.network_sha256)
        if key not in nets:
            nets[key] = resolve_net(r, net_override, routes_file)
        try:
            route_geometry(nets[key], r.edges)
        except ValueError as e:
            raise UserError(f"route {r.route_id}: {e}") from None
    return nets


def route_task(task: Task, progress: Callable[[int], None]) -> dict:
    """The executors' task function: one route; `progress(0)` at every plan (the watchdog's
    heartbeat), `progress(1)` when done."""
    doc = drive_or_fail(task, progress=progress)
    progress(1)
    return doc


def execute(
    tasks: list[Task], workers: int, executor: str = "process", ray_address: str | None = None
) -> Iterable[dict]:
    """Drive the tasks (datagen.dataset.executors: a supervised process pool or Ray, as every parallel
    command), serially in this process with one process worker; results as routes finish."""
    if workers <= 1 and executor == "process":
        for t in tasks:
            yield drive_or_fail(t)
        return
    from datagen.dataset import executors

    by_name = {result_name(t.route.route_id, t.repetition): t for t in tasks}

    def lost(name: str, message: str) -> dict:
        """A route whose worker died on every attempt (e.g. SUMO crashed): failed, written."""
        task = by_name[name]
        doc = failed_doc(task, message)
        _write_json(Path(task.out_dir) / "routes" / f"{name}.json", doc)
        return doc

    with (
        executors.stop_on_sigterm(),
        executors.make(
            executor,
            route_task,
            workers=workers,
            ray_address=ray_address,
            noun="route",
            on_lost=lost,
        ) as ex,
    ):
        for done in ex.map(by_name.items()):
            yield done.result


def run_key(spec: PolicySpec, args) -> dict:
    """What a result in OUT must have been driven with to be kept on a rerun: the policy (a
    checkpoint by its bytes' sha256), creep, the lateral controller and the smoke-run limit."""
    key = {"policy": spec.name, "creep": not args.no_creep, "max_sim_s": args.max_sim_s}
    key["lateral"] = getattr(args, "lateral", "pursuit")
    if spec.kind == "ckpt":
        from datagen.world.towns import network_sha256  # the sha256 of any file's bytes

        key["checkpoint_sha256"] = network_sha256(Path(spec.path))
    return key


def resumable(tasks: list[Task], out: Path) -> dict[str, dict]:
    """Results in OUT/routes that this run keeps (finished drives of the same route,
    repetition and run key), by result name; UserError if OUT holds another run's results."""
    kept = {}
    for t in tasks:
        name = result_name(t.route.route_id, t.repetition)
        path = out / "routes" / f"{name}.json"
        if not path.is_file():
            continue
        try:
            doc = json.loads(path.read_text())
            same = doc.get("run") == t.run and doc["route"] == t.route.to_dict()
        except (ValueError, KeyError, TypeError):
            same = False
        if not same:
            raise UserError(
                f"{out} holds a result of {name} driven by another policy, setting or route "
                f"file ({path}); give another --out"
            )
        if not doc.get("failure"):
            kept[name] = doc
    return kept


def run(args) -> int:
    from drive.policy import parse_policy
    from drive.routes import load_routes

    if args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    if args.record < 0:
        raise UserError(f"--record must be >= 0, got {args.record}")
    if args.repetitions < 1:
        raise UserError(f"--repetitions must be >= 1, got {args.repetitions}")
    max_sim = args.max_sim_s
    if max_sim is not None and max_sim <= 0:
        raise UserError(f"--max-sim-s must be > 0, got {max_sim}")
    if args.limit is not None and args.limit < 1:
        raise UserError(
            f"--limit must be >= 1 (leave it out to drive every route), got {args.limit}"
        )
    out = outputs.check_dir(args.out)  # before any driving
    spec = parse_policy(args.policy, args.device)
    name, routes = load_routes(args.routes)
    if args.limit is not None:
        routes = routes[: args.limit]
    nets = check_routes(routes, args.net, Path(args.routes))
    if spec.kind == "ckpt":  # a sensor mismatch fails before any driving, too
        from datagen.sensors.config import SensorConfig
        from drive.policy import check_sensor_config
        from training.checkpoint import load_checkpoint

        check_sensor_config(load_checkpoint(spec.path), SensorConfig().to_dict(), spec.path)
    baseline = None
    if args.baseline is not None:
        baseline = {}
        for f in sorted((Path(args.baseline) / "routes").glob("*.json")):
            d = json.loads(f.read_text())
            baseline[result_key(d)] = d
        if not baseline:
            raise UserError(f"--baseline {args.baseline}: no routes/*.json results in it")
    key = run_key(spec, args)
    tasks = [
        Task(
            r,
            spec,
            str(out),
            i < args.record and rep == 0,
            None if r.town and not args.net else str(nets[(r.town, r.net_name, r.network_sha256)]),
            max_sim,
            creep=not args.no_creep,
            repetition=rep,
            run=key,
            lateral=args.lateral,
        )
        for rep in range(args.repetitions)
        for i, r in enumerate(routes)
    ]
    kept = resumable(tasks, out)
    todo = [t for t in tasks if result_name(t.route.route_id, t.repetition) not in kept]
    if kept:
        print(f"{out}: keeping {len(kept)} finished route result(s), driving {len(todo)}")
    from tqdm import tqdm

    docs: list[dict] = list(kept.values())
    with tqdm(total=len(todo), desc=f"drive {spec.name}", unit="route") as bar:
        for doc in execute(todo, args.workers, args.executor, args.ray_address):
            docs.append(doc)
            bar.update()
            bar.set_postfix(ds=f"{doc['ds']:.1f}", last=doc["ended"])
    order = {result_name(t.route.route_id, t.repetition): i for i, t in enumerate(tasks)}
    docs.sort(
        key=lambda d: order[result_key(d)]
    )  # as the route file lists them, repetition by rep.
    summary = summary_doc(name, docs, baseline)
    _write_json(out / "summary.json", summary)
    text = format_summary(summary)
    outputs.write_text(out / "summary.txt", text + "\n")
    print(text)
    return 0
