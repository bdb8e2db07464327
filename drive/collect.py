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

`--noise P` perturbs whoever drives, as DART does (Laskey et al., CoRL 2017: noise injected
into the supervisor while it drives, its corrections recorded): at each 2 Hz plan a
perturbation starts with probability P (none while one runs), either a drift (`Noise`: the
driven plan is moved sideways, up to `drift_m`, in and out over `drift_s`) or a hesitation (the
car is held standing for 1-`hold_s` s, wherever it is). The labels stay the expert's plan from
each state, so the frames show the way back to the lane's centre and the start from standstill
on a clear road, which the expert's own data never does (it never stands without a reason).

An episode ends when its frames are done, when SUMO takes the ego out, or when the ego has been
off the road network (no expert plan) for OFF_NETWORK_S; frames off the network get no row.
Episodes, seeds, towns and weathers come from the build's planner (datagen/dataset/plan.py),
so `--seed`, `--towns`, `--frames`, resuming and `--workers` work as in `datagen build`.
"""

from __future__ import annotations

import functools
import hashlib
import math
from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from datagen.errors import UserError

OFF_NETWORK_S = 5.0  # off the network this long (no expert plan, no row): the episode ends
PLAN_PERIOD_S = 0.5  # the policy plans at the data's 2 Hz
STEP_S = 0.1  # the world's step: the controller runs every step
_MODELS: dict = {}  # (checkpoint, device) -> drive.policy.ModelPolicy of this process


@dataclass(frozen=True)
class Noise:
    """DART-style perturbations of the driver (module docstring).

    Attributes:
        rate: probability that a perturbation starts at a 2 Hz plan (0: none).
        drift_m: largest sideways shift of a drift, m (uniform in +-[drift_m / 3, drift_m]).
        drift_s: a drift's length, s (in over the first half, out over the second).
        hold_s: a hesitation holds the car standing for uniform [1, hold_s] s.
        hold_share: the share of perturbations that are hesitations.
    """

    rate: float = 0.0
    drift_m: float = 1.5
    drift_s: float = 4.0
    hold_s: float = 4.0
    hold_share: float = 0.5


class Perturbation:
    """The driver's perturbation over time (stateful, one per episode, its own stream)."""

    def __init__(self, noise: Noise, rng: np.random.Generator):
        self.noise, self.rng = noise, rng
        self.kind, self.left_s, self.length_s, self.offset_m = "", 0.0, 0.0, 0.0

    def plan(self, waypoints: np.ndarray) -> np.ndarray:
        """The driven (4, 2) waypoints (ego frame) at this 2 Hz plan instead of `waypoints`."""
        n = self.noise
        if self.left_s <= 0.0 and n.rate > 0.0 and self.rng.random() < n.rate:
            if self.rng.random() < n.hold_share:
                self.kind, self.length_s = "hold", float(self.rng.uniform(1.0, n.hold_s))
            else:
                size = self.rng.uniform(n.drift_m / 3.0, n.drift_m) * self.rng.choice([-1, 1])
                self.kind, self.length_s, self.offset_m = "drift", n.drift_s, float(size)
            self.left_s = self.length_s
        if self.left_s <= 0.0:
            return waypoints
        self.left_s -= PLAN_PERIOD_S
        if self.kind == "hold":
            return np.zeros_like(waypoints)
        done = 1.0 - self.left_s / self.length_s  # 0 .. 1 over the drift
        out = np.array(waypoints, dtype=np.float64)
        out[:, 1] += self.offset_m * math.sin(math.pi * min(done, 1.0))
        return out


def driver_name(spec, beta: float, noise: Noise) -> str:
    """What the shards' `driver` says: the policy (a checkpoint by its file's sha256), beta and
    the noise."""
    name = spec.kind
    if spec.kind == "ckpt":
        digest = hashlib.sha256(Path(spec.path).read_bytes()).hexdigest()[:16]
        name = f"ckpt:{Path(spec.path).name}@{digest}"
    return f"{name} beta={beta:g}" + (f" noise={noise.rate:g}" if noise.rate > 0 else "")


def policy_episode(
    episode, sensors, progress, *, policy, beta: float, nets: dict[str, str], noise: Noise = Noise()
):
    """Drive one planned episode (datagen.dataset.plan.Episode) with `policy` and return its
    datagen.episode.EpisodeResult (the build's runner: datagen.dataset.build.episode_task)."""

    from datagen import labels
    from datagen.episode import EpisodeResult, Sensors, episode_rng, episode_table
    from datagen.sensors.scene import load_static_scene
    from datagen.world import EgoCommand, World, WorldConfig
    from datagen.world.towns import network_sha256
    from drive.controller import Controller, Plan, VehicleState, bicycle_step
    from drive.policy import ModelPolicy
    from drive.sim import SensorStream

    net = Path(nets[episode.town])
    static = load_static_scene(net)
    sense = Sensors(static, sensors, episode.weather, episode_rng(episode.seed))
    stream = SensorStream(sense, sensors.jpeg_quality)
    mix = np.random.default_rng(np.random.SeedSequence([episode.seed, 0xDA6]))
    perturb = Perturbation(
        noise, np.random.default_rng(np.random.SeedSequence([episode.seed, 0xDA7]))
    )
    model = None
    if policy.kind == "ckpt":
        key = (policy.path, policy.device)
        if key not in _MODELS:
            _MODELS.clear()
            _MODELS[key] = ModelPolicy(policy, sensors.to_dict())
        model = _MODELS[key]
        model.reset()
    config = WorldConfig(
        net_path=net,
        seed=episode.seed,
        weather=episode.weather,
        behaviour=episode.behaviour,
        target_point=sensors.target_point,
        ego_driver="external",
    )
    steps_per_plan = round(PLAN_PERIOD_S / STEP_S)
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
                image, lidar_bev, ground_t = stream.encode(frame)
                encoded = {"image": image, "lidar_bev": lidar_bev, "lidar_ground_t": ground_t}
                expert = world.expert_plan()
                label = None if expert is None else frame.ego.pose.ego_from_world(expert[0])
                off_network = 0 if label is not None else off_network + 1
                if off_network * PLAN_PERIOD_S >= OFF_NETWORK_S:
                    break
                waypoints = label
                if model is not None and not (label is not None and mix.random() < beta):
                    waypoints = (
                        model.plan(frame, image, lidar_bev, ground_t)
                        if model.needs_sensors
                        else model.plan_privileged(frame, static.label_map)
                    )
                else:
                    expert_plans += label is not None
                    if model is not None:
                        model.observe(frame)  # the stand clock runs whoever plans
                if waypoints is not None:
                    waypoints = perturb.plan(waypoints)
                    plan = Plan.from_ego(frame.time_s, frame.ego.pose, waypoints)
                reason = expert[1].reason if expert is not None else "none"
                hits = stream.last_sweep.actor_hits
                held.append((frame, encoded, label, reason, hits, stream.full))
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
    stats.update(plans=k // steps_per_plan + 1, expert_plans=int(expert_plans))
    rows = rows[: episode.n_frames]
    table = episode_table(rows, sensors, network_sha256(net), episode.seed, episode.episode_id)
    return EpisodeResult(table=table, end_reason=end_reason, stats=stats)


def _row(held, future, episode, sense, labels) -> list[dict]:
    """The row of one held frame ([] off the network or before the LiDAR history is full)."""
    from schemas import codecs

    frame, encoded, label, reason, hits, full = held
    if label is None or not full:
        return []
    labelled = labels.frame_labels(frame, future, hits, waypoints_ego=np.asarray(label).ravel())
    # the rule binding the expert's plan from here
    row = replace(labelled, expert_reason=reason).row()
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
    p.add_argument(
        "--noise",
        type=float,
        default=0.0,
        metavar="P",
        help="DART-style perturbations of the driver: probability per 2 Hz plan that a drift "
        "beside the lane or a hesitation (standing) starts (default: %(default)s, none)",
    )
    p.add_argument(
        "--device",
        default="auto",
        choices=("auto", "cpu", "cuda"),
        help="where a ckpt: policy runs (default: auto, CUDA if present)",
    )
    build.add_arguments(p)
    # not a build's: a few thousand frames beside one (give it a seed other than the build's:
    # episode ids are <town>-<seed>-<n>, and train fit refuses the same episode twice)
    p.set_defaults(frames=4000, out=Path("data/on-policy"))


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
    if not 0.0 <= args.noise <= 1.0:
        raise UserError(f"--noise must be in [0, 1], got {args.noise}")
    noise = Noise(rate=args.noise)
    cfg = build.config_from_args(args)
    sensors = cfg.sensors
    if sensors.driver != "expert":
        raise UserError("--sensor driver=...: drive collect sets the driver itself")
    if spec.kind == "ckpt":
        from drive.policy import check_sensor_config
        from training.checkpoint import load_checkpoint

        check_sensor_config(load_checkpoint(spec.path), sensors.to_dict(), spec.path)
    cfg = dataclasses.replace(
        cfg, sensors=dataclasses.replace(sensors, driver=driver_name(spec, args.beta, noise))
    )
    nets = {t.name: t.net_path for t in cfg.towns}
    runner = functools.partial(policy_episode, policy=spec, beta=args.beta, nets=nets, noise=noise)
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
