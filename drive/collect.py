"""`drive collect`: on-policy data, labelled by the privileged expert (DAgger).

    drive collect --policy ckpt:runs/m0/last.pt --towns 8 --frames 4000 --seed 1 --out runs/dagger1
    train fit --shards runs/d41 --shards runs/dagger1 ...        # the union (training/data.py)

Imitation learns the expert's states, not the states its own mistakes lead to: off the lane's
centre, askew, standing where the expert would have gone. DAgger (Ross et al., AISTATS 2011;
in CARLA: Prakash et al., CVPR 2020, DA-RB) lets the learner drive and asks the expert what to
do from where it got to. Here the expert is cheap and privileged: at every 2 Hz frame of an
episode driven by the policy, `World.expert_plan` gives the expert's plan from that very state
(its rollout along the route's lanes, back to the lane's centre, lane changes included), and
that plan is the frame's `waypoints` label. Every other column is made as in a build
(datagen/episode.py: the same sensors, encoder and labels), so the shards are ordinary shards
of schema 1.2 whose `iidsu.config_json` says who drove (`driver`).

Who drives: at each 2 Hz plan the policy's waypoints, or with probability `--beta` the
expert's plan (DAgger's mixture policy pi_i = beta pi* + (1 - beta) pi_hat), through the same
controller and bicycle as `drive eval` (drive/controller.py). The mixture keeps a policy that
stands or wanders moving along the route, so the frames cover its mistakes without repeating
one for a whole episode. `--policy expert-plan` with `--beta 0` collects the expert's plan
driven through the controller (the controller's own state distribution).

An episode ends when its frames are done, when SUMO takes the ego out, or when the ego has been
off the road network (no expert plan) for OFF_NETWORK_S; frames off the network get no row.
Episodes, seeds, towns and weathers come from the build's planner (datagen/dataset/plan.py),
so `--seed`, `--towns`, `--frames`, resuming and `--workers` work as in `datagen build`.
"""

from __future__ import annotations

import functools
import hashlib
from collections import deque
from pathlib import Path

import numpy as np

from datagen.errors import UserError

OFF_NETWORK_S = 5.0  # off the network this long (no expert plan, no row): the episode ends
PLAN_PERIOD_S = 0.5  # the policy plans at the data's 2 Hz
STEP_S = 0.1  # the world's step: the controller runs every step
_MODELS: dict = {}  # (checkpoint, device) -> drive.policy.ModelPolicy of this process


def driver_name(spec, beta: float) -> str:
    """What the shards' `driver` says: the policy (a checkpoint by its file's sha256) and beta."""
    name = spec.kind
    if spec.kind == "ckpt":
        digest = hashlib.sha256(Path(spec.path).read_bytes()).hexdigest()[:16]
        name = f"ckpt:{Path(spec.path).name}@{digest}"
    return f"{name} beta={beta:g}"


def policy_episode(episode, sensors, progress, *, policy, beta: float, nets: dict[str, str]):
    """Drive one planned episode (datagen.dataset.plan.Episode) with `policy` and return its
    datagen.episode.EpisodeResult (the build's runner: datagen.dataset.build.episode_task)."""
    import pyarrow as pa

    import schemas
    from datagen import labels
    from datagen.episode import EpisodeResult, Sensors, encode_sensors, episode_rng
    from datagen.sensors.config import HISTORY
    from datagen.sensors.scene import load_static_scene
    from datagen.world import EgoCommand, World, WorldConfig
    from datagen.world.towns import network_sha256
    from drive.controller import Controller, Plan, VehicleState, bicycle_step
    from drive.policy import ModelPolicy

    net = Path(nets[episode.town])
    static = load_static_scene(net)
    sense = Sensors(static, sensors, episode.weather, episode_rng(episode.seed))
    mix = np.random.default_rng(np.random.SeedSequence([episode.seed, 0xDA6]))
    model = None
    if policy.kind == "ckpt":
        key = (policy.path, policy.device)
        if key not in _MODELS:
            _MODELS.clear()
            _MODELS[key] = ModelPolicy(policy, sensors.to_dict())
        model = _MODELS[key]
    config = WorldConfig(
        net_path=net,
        seed=episode.seed,
        weather=episode.weather,
        behaviour=episode.behaviour,
        target_point=sensors.target_point,
        ego_driver="external",
    )
    steps_per_plan = round(PLAN_PERIOD_S / STEP_S)
    sweeps: deque = deque(maxlen=HISTORY + 1)
    held: deque = deque()  # frames waiting for the boxes' future (t+0.5 s, t+1.0 s)
    rows: list[dict] = []
    expert_plans = off_network = 0
    with World(config) as world:
        frame = world.state()
        vehicle = VehicleState(frame.ego.pose, frame.ego.speed_mps)
        controller = Controller()
        plan = None
        k = 0
        while len(rows) < episode.n_frames:
            if k % steps_per_plan == 0:
                scene = sense.scene(frame)
                sweeps.appendleft(sense.sweep(scene, frame))
                hist = list(sweeps) + [sweeps[-1]] * (sweeps.maxlen - len(sweeps))
                encoded = encode_sensors(sense, scene, frame, hist)
                expert = world.expert_plan()
                label = None if expert is None else frame.ego.pose.ego_from_world(expert[0])
                off_network = 0 if label is not None else off_network + 1
                if off_network * PLAN_PERIOD_S >= OFF_NETWORK_S:
                    break
                waypoints = label
                if model is not None and not (label is not None and mix.random() < beta):
                    waypoints = model.plan(
                        frame, encoded["image"], encoded["lidar_bev"], encoded["lidar_ground_t"]
                    )
                else:
                    expert_plans += label is not None
                if waypoints is not None:
                    plan = Plan.from_ego(frame.time_s, frame.ego.pose, waypoints)
                reason = expert[1].reason if expert is not None else "none"
                full = len(sweeps) > HISTORY
                held.append((frame, encoded, label, reason, sweeps[0].actor_hits, full))
                if len(held) > 2:  # its two future states are here: the boxes can be labelled
                    row = _row(held.popleft(), [h[0] for h in held], episode, sense, labels)
                    rows += row
                    if row and progress is not None:
                        progress(1)
            if plan is not None:
                aim = plan.at(frame.time_s, vehicle.pose)
                ctrl = controller.control(
                    aim, vehicle.speed_mps, 0.0, plan.ahead(frame.time_s, vehicle.pose)
                )
                vehicle = bicycle_step(vehicle, ctrl, STEP_S)
                world.step(EgoCommand(vehicle.pose, vehicle.speed_mps))
            else:
                world.step(EgoCommand(frame.ego.pose, 0.0))
            if world.ended is not None:
                break
            frame = world.state()
            k += 1
        end_reason = world.ended or ("off_network" if off_network else None)
        stats = dict(world.stats)
    rows = rows[: episode.n_frames]
    for i, row in enumerate(rows):
        row["frame"] = i
    stats.update(plans=k // steps_per_plan + 1, expert_plans=int(expert_plans))
    meta = schemas.file_metadata(
        generator_version=_generator_version(),
        config=sensors.to_dict(),
        network_sha256=network_sha256(net),
        seed=episode.seed,
    )
    table = pa.Table.from_pylist(rows, schema=schemas.schema(meta))
    schemas.validate(table, where=episode.episode_id)
    return EpisodeResult(table=table, end_reason=end_reason, stats=stats)


def _generator_version() -> str:
    from datagen.episode import generator_version

    return generator_version()


def _row(held, future, episode, sense, labels) -> list[dict]:
    """The row of one held frame ([] off the network or before the LiDAR history is full)."""
    from schemas import codecs

    frame, encoded, label, reason, hits, full = held
    if label is None or not full:
        return []
    row = labels.frame_labels(frame, future, hits, waypoints_ego=np.asarray(label).ravel())
    row["expert_reason"] = reason  # the rule binding the expert's plan from here
    semantic = labels.bev_semantic(sense.static.label_map, frame.ego.pose)
    row.update(
        episode_id=episode.episode_id,
        town=episode.town,
        weather=episode.weather,
        behaviour=episode.behaviour,
        **encoded,
        bev_semantic=codecs.encode_bev_semantic(semantic),
    )
    return [row]


def add_arguments(p) -> None:
    from datagen.dataset import build

    p.add_argument(
        "--policy",
        required=True,
        help="who drives: ckpt:PATH (a trained model) or expert-plan (the expert's plan through "
        "the controller)",
    )
    p.add_argument(
        "--beta",
        type=float,
        default=0.5,
        help="probability that a 2 Hz plan is the expert's instead of the policy's (DAgger's "
        "mixture; default: %(default)s)",
    )
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    build.add_arguments(p)


def run(args) -> int:
    import dataclasses
    import sys

    from datagen.dataset import build
    from drive.policy import parse_policy
    from schemas import outputs

    spec = parse_policy(args.policy, args.device)
    if spec.kind not in ("ckpt", "expert-plan"):
        raise UserError(f"--policy {args.policy}: drive collect takes ckpt:PATH or expert-plan")
    if not 0.0 <= args.beta <= 1.0:
        raise UserError(f"--beta must be in [0, 1], got {args.beta}")
    cfg = build.config_from_args(args)
    sensors = cfg.sensors
    if sensors.driver != "expert":
        raise UserError("--sensor driver=...: drive collect sets the driver itself")
    if spec.kind == "ckpt":
        from drive.policy import check_sensor_config
        from training.checkpoint import load_checkpoint

        check_sensor_config(load_checkpoint(spec.path), sensors.to_dict(), spec.path)
    cfg = dataclasses.replace(
        cfg, sensors=dataclasses.replace(sensors, driver=driver_name(spec, args.beta))
    )
    runner = functools.partial(
        policy_episode, policy=spec, beta=args.beta, nets={t.name: t.net_path for t in cfg.towns}
    )
    options = build.options_from_args(args)
    outputs.check_dir(args.out)
    report = build.build(
        cfg,
        args.out,
        force=args.force,
        progress_bar=not args.no_progress,
        options=options,
        runner=runner,
    )
    print(build.summary(report))
    if report.manifest["status"] != "complete":
        print("drive collect: the dataset is incomplete (see above)", file=sys.stderr)
        return 1
    return 0
