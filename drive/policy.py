"""Who drives the ego: `expert` (the privileged rule-based driver of the data, the ceiling),
`expert-plan` (the same expert's plan from the ego's state, as the 4 waypoints a model outputs,
driven through the model's controllers: the ceiling of the waypoint representation and the
controller), `constant` (straight ahead at a fixed speed, the floor) or `ckpt:PATH` (a trained
II-DSU, or the privileged planner).

A non-privileged policy returns 4 waypoints (ego frame, m, +0.5 .. +2.0 s) from one recorded
instant; drive/controller.py turns them into the ego's motion. The checkpoint policy sees what
the model was trained on (paper Sec. III-A): the camera and the 2 Hz LiDAR BEV history from the
sensors the data was recorded with (datagen.episode.Sensors), encoded as in the shards and
decoded by the trainer's own `training.decode.model_inputs`, the ego's speed and the route's
target point in the ego frame (the model reads no command). A checkpoint of `train fit --arch
privileged` (training/privileged.py) reads no sensor: it plans from the world's ground truth
rasterised as the shards' labels are (`privileged_inputs`), and its 4 waypoints go through the
same controller.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from datagen.errors import UserError
from datagen.state import FrameState
from schemas import WAYPOINT_TIMES_S

CONSTANT_SPEED_MPS = 6.0  # `constant`: about 22 km/h, straight ahead


@dataclass(frozen=True)
class PolicySpec:
    """A parsed --policy: kind ("expert", "constant", "ckpt"), checkpoint path, device."""

    kind: str
    path: str | None = None
    device: str = "auto"

    @property
    def name(self) -> str:
        return f"ckpt:{Path(self.path).name}" if self.kind == "ckpt" else self.kind

    @property
    def privileged(self) -> bool:
        """The expert drives the ego inside the world (no controller, no bicycle model)."""
        return self.kind == "expert"


def parse_policy(text: str, device: str = "auto") -> PolicySpec:
    """'expert' | 'expert-plan' | 'constant' | 'ckpt:PATH' -> PolicySpec; UserError for
    anything else (the checkpoint is checked to exist and load here, before any route
    starts)."""
    if text in ("expert", "expert-plan", "constant"):
        return PolicySpec(text, device=device)
    if text.startswith("ckpt:"):
        path = text[len("ckpt:") :]
        from training.checkpoint import load_checkpoint
        from training.errors import UserError as TrainError

        try:
            load_checkpoint(path)
        except TrainError as e:
            reason = str(e).removeprefix(f"{path}: ")  # its path is in the flag already
            raise UserError(f"--policy {text}: {reason}") from None
        return PolicySpec("ckpt", path, device)
    raise UserError(f"--policy {text!r}: expected expert, expert-plan, constant or ckpt:PATH")


def constant_waypoints(speed_mps: float = CONSTANT_SPEED_MPS) -> np.ndarray:
    """(4, 2) straight ahead at `speed_mps`, ego frame."""
    return np.array([[speed_mps * t, 0.0] for t in WAYPOINT_TIMES_S])


def check_sensor_config(checkpoint: dict, world_config: dict, where: str) -> None:
    """UserError naming the differing fields if the checkpoint's data was recorded with other
    sensors than the world's (training.checkpoint.check_sensors)."""
    from training.checkpoint import check_sensors
    from training.privileged import is_privileged

    if is_privileged(checkpoint):  # it reads the world's ground truth, never the sensors
        return
    check_sensors(checkpoint, world_config, "this world's", where)


class ModelPolicy:
    """A trained II-DSU from a checkpoint, on CPU or CUDA (bf16 autocast there); or, for a
    checkpoint of `train fit --arch privileged`, the privileged planner (`needs_sensors`
    False: it plans from the world's ground truth, `plan_privileged`)."""

    def __init__(self, spec: PolicySpec, sensor_config: dict):
        import torch

        from training.checkpoint import load_checkpoint, model_from_checkpoint
        from training.device import choose_device
        from training.privileged import is_privileged, model_from_state

        state = load_checkpoint(spec.path)
        self.device = choose_device(spec.device)
        self.needs_sensors = not is_privileged(state)
        if self.needs_sensors:
            check_sensor_config(state, sensor_config, spec.path)
            self.model = model_from_checkpoint(state, self.device)
        else:  # reads labels only: any sensors will do
            self.model = model_from_state(state, self.device)
        self.torch = torch
        self.reset()

    def reset(self) -> None:
        """Forget the route driven so far (call at each route's start): the privileged
        planner's stand clock (training.ego_history.StandClock)."""
        from training.ego_history import StandClock

        self.clock = StandClock()

    def observe(self, frame: FrameState) -> float:
        """Tick the stand clock at a plan (plan_privileged does; call it at a plan someone
        else makes); the seconds the ego has stood."""
        return self.clock.tick(float(np.float32(frame.ego.speed_mps)))

    def plan_privileged(self, frame: FrameState, label_map) -> np.ndarray:
        """(4, 2) waypoints, ego frame, m, of the privileged planner from the world's ground
        truth at one instant (`label_map`: the town's, datagen.sensors.scene.StaticScene),
        one call per plan (its stand clock ticks at each)."""
        torch = self.torch
        x = privileged_inputs(frame, label_map)
        x["stood"] = np.float32(self.observe(frame))
        batch = {k: torch.from_numpy(np.asarray(v))[None].to(self.device) for k, v in x.items()}
        with torch.no_grad():
            waypoints = self.model.plan(batch)
        return waypoints[0].float().cpu().numpy().astype(np.float64)

    def plan(
        self, frame: FrameState, image_jpeg: bytes, lidar_png: bytes, ground_png: bytes
    ) -> np.ndarray:
        """(4, 2) waypoints, ego frame, m, from one instant's encoded sensors (`ground_png`, the
        current sweep's ground channel, is read by a single-frame LiDAR model only)."""
        from training.device import autocast
        from training.model import INPUTS

        torch = self.torch
        single = self.model.cfg.single_frame_lidar
        x = sensor_inputs(frame, image_jpeg, lidar_png, ground_png if single else None)
        batch = {k: torch.from_numpy(np.asarray(v))[None].to(self.device) for k, v in x.items()}
        with torch.no_grad(), autocast(self.device):
            waypoints = self.model.plan(*(batch[k] for k in INPUTS))  # (1, 4, 2)
        return waypoints[0].float().cpu().numpy().astype(np.float64)


def sensor_inputs(
    frame: FrameState, image_jpeg: bytes, lidar_png: bytes, ground_png: bytes | None = None
) -> dict[str, np.ndarray]:
    """What the sensor model reads at one instant, as the loader's sample holds it
    (training/data.py `_sample`): image (3, 256, 256) uint8 and lidar (4 or, given
    `ground_png`, 2, 256, 256) uint8 decoded by the trainer's own `model_inputs`; speed ()
    float32, m/s; target_point (2,) float32, m, the ego frame now."""
    from training.decode import model_inputs

    image, lidar = model_inputs(image_jpeg, lidar_png, ground_png)
    tp = frame.ego.pose.ego_from_world(np.array([frame.target_point_xy_m]))[0]
    return {
        "image": image,
        "lidar": lidar,
        "speed": np.float32(frame.ego.speed_mps),
        "target_point": tp.astype(np.float32),
    }


def privileged_inputs(frame: FrameState, label_map) -> dict[str, np.ndarray]:
    """What the privileged planner reads at one instant (training.privileged.inputs), made from
    the world's state as the build makes the shards' labels (datagen.labels: the BEV map of
    the town's `label_map` and the agents' boxes at t), so that a closed-loop input equals the
    one the planner was trained on from the same state (tests/test_drive_parity.py)."""
    from datagen import labels
    from training.privileged import WALKERS, AgentBoxes, Situation, inputs

    sem = labels.bev_semantic(label_map, frame.ego.pose)
    boxes = labels.boxes(frame, [], None)
    # through float32, as the shards store boxes, speed and target point
    agents = AgentBoxes(
        *(np.array([getattr(b, f) for b in boxes], np.float32).astype(np.float64).reshape(-1)
          for f in ("x_m", "y_m", "yaw_rad", "length_m", "width_m", "speed_mps")),
        np.array([b.cls in WALKERS for b in boxes], bool),
    )  # fmt: skip
    tp = frame.ego.pose.ego_from_world(np.array([frame.target_point_xy_m]))[0]
    situation = Situation(
        float(np.float32(frame.ego.speed_mps)), tp.astype(np.float32), frame.command,
        frame.traffic_light, _f32(frame.light_distance_m), bool(frame.stop_sign),
        _f32(frame.stop_distance_m),
    )  # fmt: skip
    return inputs(sem, agents, situation)


def _f32(v: float | None) -> float | None:
    return None if v is None else float(np.float32(v))
