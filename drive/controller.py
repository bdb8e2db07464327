"""From planned waypoints to the ego's next pose: two PID controllers and a kinematic bicycle.

The controllers are TransFuser's (Prakash et al. 2021, `team_code/planner.py` and the agent's
`control_pid`, the paper's Sec. III-B "two PID controllers"): the lateral one steers towards
the mean of the first two waypoints, the longitudinal one tracks the speed the first two
waypoints imply (their distance / 0.5 s). Each PID keeps a window of its last N errors; I is
their mean and D the last difference, as in TransFuser.

Plans come at 2 Hz (the data's rate; the LiDAR history is 2 Hz) and the controllers run every
0.1 s SUMO step. Between plans the waypoints are held in the world frame as a trajectory timed
from the plan (0 s: the ego's pose when planned; +0.5 .. +2.0 s: the waypoints), and at
`elapsed` seconds after the plan the controllers see the trajectory's points at
`elapsed + 0.5 s` and `elapsed + 1.0 s` in the current ego frame -- exactly TransFuser's two
waypoints when `elapsed` is 0.

TransFuser's lateral PID was tuned for CARLA's cars, whose steering reaches about twice the
wheel angle of the bicycle here, and its aim point (0.5-1.0 s ahead) is a few metres away at
turning speeds, so at a tight turn it steers far too little (`expert-plan`, the expert's own
plan driven through it, left its route on dev routes). `ControllerConfig.lateral="pursuit"`
(the default) steers by pure pursuit instead (Coulter, CMU-RI-TR-92-01, 1992), which is exact
for this kinematic bicycle: the aim point is where the planned trajectory crosses the circle of
radius L_d (speed-dependent) around the rear axle, at angle alpha, and the wheel angle is
delta = atan(2 L sin(alpha) / L_d). docs/closed-loop.md has the measured comparison.

The vehicle is a kinematic bicycle about the box centre (Rajamani, "Vehicle Dynamics and
Control", Sec. 2.2): slip angle beta = atan(l_r / L tan delta), x' = v cos(yaw + beta),
y' = v sin(yaw + beta), yaw' = v / l_r sin beta, v' = a. Steering is positive to the left
(yaw counter-clockwise), unlike CARLA's.

`Creep` is TransFuser's stuck detector (Chitta et al., TPAMI 2022, the evaluation agent and its
config: `stuck_threshold`, `creep_duration`, `creep_throttle`, the LiDAR `safety_box`): a model
that has stood still for 55 s is pushed forward for 1.5 s at throttle 0.4, unless its own LiDAR
sees something in a small box just ahead of the car. Imitation models learn from their speed
input that a standing car stays standing (the "inertia" of Codevilla et al. 2019); the creep
gets them rolling again, as in the baselines the paper compares with.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from datagen.state import Pose
from schemas import WAYPOINT_TIMES_S

LATERAL = ("pursuit", "pid")


@dataclass(frozen=True)
class ControllerConfig:
    """Gains and limits (TransFuser's config.py values unless noted).

    Attributes:
        turn_kp, turn_ki, turn_kd, turn_n: lateral PID on the heading error / 90 degrees.
        speed_kp, speed_ki, speed_kd, speed_n: longitudinal PID on the speed error, m/s.
        brake_speed_mps: brake when the planned speed is below this.
        brake_ratio: ... or when speed / planned speed exceeds this.
        clip_delta_mps: the speed error the longitudinal PID sees is clipped to [0, this].
        max_throttle: throttle limit, 0..1.
        lateral: "pursuit" (ours, the default: pure pursuit on the planned trajectory) or
            "pid" (TransFuser's PID on the heading to the first two waypoints' mean).
        lookahead_s, min_lookahead_m, max_lookahead_m: pure pursuit's L_d, from the rear
            axle: speed x lookahead_s, clipped to [min, max] m.
    """

    turn_kp: float = 1.25
    turn_ki: float = 0.75
    turn_kd: float = 0.3
    turn_n: int = 40
    speed_kp: float = 5.0
    speed_ki: float = 0.5
    speed_kd: float = 1.0
    speed_n: int = 40
    brake_speed_mps: float = 0.4
    brake_ratio: float = 1.1
    clip_delta_mps: float = 0.25
    max_throttle: float = 0.75
    lateral: str = "pursuit"
    # Chosen on the dev routes with the expert's own plan (docs/closed-loop.md, 2026-12-06):
    # 0.6 s / 3 m cut the junctions' corners, a wheel on the kerb on 13 of 16 routes.
    lookahead_s: float = 0.3
    min_lookahead_m: float = 1.0
    max_lookahead_m: float = 12.0

    def __post_init__(self) -> None:
        if self.lateral not in LATERAL:
            raise ValueError(f"lateral must be one of {LATERAL}, got {self.lateral!r}")


@dataclass(frozen=True)
class VehicleConfig:
    """Kinematic bicycle of the ego (a mid-size sedan, as datagen.world's ego box).

    Attributes:
        wheelbase_m: L; rear_to_centre_m: l_r, rear axle to the box centre.
        max_steer_rad: front-wheel angle at steer = 1 (35 degrees, a passenger car's lock).
        max_accel_mps2: acceleration at throttle 1.
        brake_decel_mps2: deceleration when braking.
        coast_decel_mps2: rolling resistance and drag without throttle or brake.
    """

    wheelbase_m: float = 2.85
    rear_to_centre_m: float = 1.425
    max_steer_rad: float = math.radians(35.0)
    max_accel_mps2: float = 4.0
    brake_decel_mps2: float = 6.0
    coast_decel_mps2: float = 0.3


@dataclass(frozen=True)
class Control:
    """One step's command: steer in [-1, 1] (positive left), throttle in [0, 1], brake."""

    steer: float
    throttle: float
    brake: bool


@dataclass(frozen=True)
class VehicleState:
    """The ego's kinematic state: box-centre pose (world frame) and speed, m/s (>= 0)."""

    pose: Pose
    speed_mps: float


class PID:
    """PID over a window of the last `n` errors (TransFuser's PIDController)."""

    def __init__(self, kp: float, ki: float, kd: float, n: int):
        self.kp, self.ki, self.kd = kp, ki, kd
        self.window: deque[float] = deque([0.0] * n, maxlen=n)

    def step(self, error: float) -> float:
        self.window.append(float(error))
        integral = float(np.mean(self.window))
        derivative = self.window[-1] - self.window[-2] if len(self.window) >= 2 else 0.0
        return self.kp * error + self.ki * integral + self.kd * derivative


@dataclass
class Controller:
    """Lateral and longitudinal PID (stateful: their error windows)."""

    config: ControllerConfig = field(default_factory=ControllerConfig)

    def __post_init__(self) -> None:
        c = self.config
        self.turn = PID(c.turn_kp, c.turn_ki, c.turn_kd, c.turn_n)
        self.speed = PID(c.speed_kp, c.speed_ki, c.speed_kd, c.speed_n)

    def control(
        self,
        waypoints_ego: np.ndarray,
        speed_mps: float,
        creep_throttle: float = 0.0,
        path_ego: np.ndarray | None = None,
    ) -> Control:
        """waypoints_ego: (>=2, 2) float, m, ego frame, 0.5 s apart -> this step's Control.
        `path_ego`: (K, 2) the planned trajectory ahead, ego frame (Plan.ahead), which pure
        pursuit steers along (without it, or with lateral "pid", the PID steers).
        `creep_throttle` > 0 (Creep): no brake and at least that throttle."""
        c = self.config
        w = np.asarray(waypoints_ego, dtype=np.float64)
        desired = float(np.linalg.norm(w[1] - w[0])) / (WAYPOINT_TIMES_S[1] - WAYPOINT_TIMES_S[0])
        brake = desired < c.brake_speed_mps or speed_mps / max(desired, 1e-6) > c.brake_ratio
        aim = 0.5 * (w[0] + w[1])
        angle = math.degrees(math.atan2(aim[1], aim[0])) / 90.0  # heading error, + = left
        if speed_mps < 0.01:  # TransFuser: no steering at standstill
            angle = 0.0
        steer = float(np.clip(self.turn.step(angle), -1.0, 1.0))
        if c.lateral == "pursuit" and path_ego is not None:
            steer = 0.0 if speed_mps < 0.01 else pursuit_steer(path_ego, speed_mps, c)
        delta = float(np.clip(desired - speed_mps, 0.0, c.clip_delta_mps))
        throttle = float(np.clip(self.speed.step(delta), 0.0, c.max_throttle))
        if creep_throttle > 0.0:
            return Control(steer=steer, throttle=max(throttle, creep_throttle), brake=False)
        return Control(steer=steer, throttle=0.0 if brake else throttle, brake=bool(brake))


def pursuit_steer(
    path_ego: np.ndarray,
    speed_mps: float,
    config: ControllerConfig,
    vehicle: VehicleConfig = VehicleConfig(),
) -> float:
    """Pure pursuit's steer in [-1, 1] along `path_ego` ((K, 2), m, ego frame of the box
    centre): the aim point is the last crossing of the path with the circle of radius L_d
    around the rear axle (the path's end, straight on along its last segment, if it ends
    inside the circle), and the wheel angle delta = atan(2 L sin(alpha) / L_d)."""
    rear = np.array([-vehicle.rear_to_centre_m, 0.0])
    look = float(
        np.clip(speed_mps * config.lookahead_s, config.min_lookahead_m, config.max_lookahead_m)
    )
    p = np.asarray(path_ego, dtype=np.float64).reshape(-1, 2) - rear
    p = p[np.concatenate([[True], np.hypot(*np.diff(p, axis=0).T) > 1e-3])]
    r = np.hypot(p[:, 0], p[:, 1])
    aim = None
    for k in range(len(p) - 1, 0, -1):  # the last segment that leaves the circle
        if r[k] >= look > r[k - 1] or (r[k] >= look and k == 1):
            a, d = p[k - 1], p[k] - p[k - 1]
            # |a + t d| = look, the larger root in [0, 1]
            qa, qb, qc = d @ d, 2.0 * (a @ d), a @ a - look * look
            t = (-qb + math.sqrt(max(qb * qb - 4.0 * qa * qc, 0.0))) / (2.0 * qa)
            aim = a + min(max(t, 0.0), 1.0) * d
            break
    if aim is None:  # the whole path is inside the circle (slow): aim along its end
        if len(p) >= 2:
            d = p[-1] - p[-2]
            aim = p[-1] + d / max(float(np.hypot(*d)), 1e-9) * max(look - r[-1], 0.0)
        else:
            return 0.0
    alpha = math.atan2(aim[1], aim[0])
    dist = max(float(np.hypot(*aim)), 1e-6)
    delta = math.atan(2.0 * vehicle.wheelbase_m * math.sin(alpha) / dist)
    return float(np.clip(delta / vehicle.max_steer_rad, -1.0, 1.0))


@dataclass(frozen=True)
class CreepConfig:
    """TransFuser's creep (module docstring; its values, converted from 20 Hz frames to s).

    Attributes:
        stuck_s: standing this long (slower than stuck_speed_mps) starts a creep.
        duration_s: how long a creep lasts; throttle: its least throttle, 0..1.
        box_ahead_m: the safety box reaches this far ahead of the front bumper ...
        box_side_m: ... is this much wider than the car on each side ...
        box_low_m, box_high_m: ... and holds LiDAR returns between these heights above the
            ground (the ground itself and overhead signs do not count).
    """

    stuck_s: float = 55.0
    stuck_speed_mps: float = 0.1
    duration_s: float = 1.5
    throttle: float = 0.4
    box_ahead_m: float = 4.0
    box_side_m: float = 0.2
    box_low_m: float = 0.5
    box_high_m: float = 2.0


def safety_box_clear(
    points_world: np.ndarray, pose: Pose, length_m: float, width_m: float, config: CreepConfig
) -> bool:
    """True if none of the LiDAR returns `points_world` ((N, 3), world frame, z above the
    ground, m) lies in the safety box ahead of a car of `length_m` x `width_m` (m) whose box
    centre is at `pose`."""
    p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    z = p[:, 2]
    p = p[(z >= config.box_low_m) & (z <= config.box_high_m)]
    if not len(p):
        return True
    local = pose.ego_from_world(p[:, :2])
    front = 0.5 * length_m
    inside = (
        (local[:, 0] >= front)
        & (local[:, 0] <= front + config.box_ahead_m)
        & (np.abs(local[:, 1]) <= 0.5 * width_m + config.box_side_m)
    )
    return not bool(inside.any())


@dataclass
class Creep:
    """The stuck detector (stateful): `step(speed, clear_ahead)` once per control step returns
    the creep throttle for this step (0.0: none). A creep starts once the car has stood
    `stuck_s` and the safety box is clear, and stops early if the box fills. Time is counted
    in whole steps of `step_s`."""

    config: CreepConfig = field(default_factory=CreepConfig)
    step_s: float = 0.1
    stood_steps: int = 0
    creep_steps_left: int = 0
    creeps: int = 0  # how many creeps started

    @property
    def _stuck_steps(self) -> int:
        return round(self.config.stuck_s / self.step_s)

    @property
    def due(self) -> bool:
        """Whether the caller should look at the safety box (a creep may start or is on)."""
        return self.creep_steps_left > 0 or self.stood_steps + 1 >= self._stuck_steps

    def step(self, speed_mps: float, clear_ahead: bool) -> float:
        c = self.config
        self.stood_steps = self.stood_steps + 1 if speed_mps < c.stuck_speed_mps else 0
        if self.creep_steps_left <= 0 and self.stood_steps >= self._stuck_steps and clear_ahead:
            self.creep_steps_left = round(c.duration_s / self.step_s)
            self.creeps += 1
        if self.creep_steps_left > 0:
            if not clear_ahead:
                self.creep_steps_left = 0
                return 0.0
            self.creep_steps_left -= 1
            self.stood_steps = 0
            return c.throttle
        return 0.0


def bicycle_step(
    state: VehicleState, control: Control, dt_s: float, vehicle: VehicleConfig = VehicleConfig()
) -> VehicleState:
    """Advance the kinematic bicycle by dt_s (module docstring); speed never goes negative."""
    v = state.speed_mps
    if control.brake:
        a = -vehicle.brake_decel_mps2
    elif control.throttle > 0.0:
        a = control.throttle * vehicle.max_accel_mps2
    else:
        a = -vehicle.coast_decel_mps2
    delta = control.steer * vehicle.max_steer_rad
    beta = math.atan(vehicle.rear_to_centre_m / vehicle.wheelbase_m * math.tan(delta))
    p = state.pose
    # integrate the pose with the step's mean speed (exact for constant acceleration on a line)
    v1 = max(0.0, v + a * dt_s)
    v_mid = 0.5 * (v + v1)
    yaw = p.yaw_rad + v_mid / vehicle.rear_to_centre_m * math.sin(beta) * dt_s
    mid_yaw = 0.5 * (p.yaw_rad + yaw)
    x = p.x_m + v_mid * math.cos(mid_yaw + beta) * dt_s
    y = p.y_m + v_mid * math.sin(mid_yaw + beta) * dt_s
    yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
    return VehicleState(Pose(x, y, yaw), v1)


@dataclass(frozen=True)
class Plan:
    """A plan held in the world frame: the ego's pose when planned and its waypoints.

    Attributes:
        time_s: simulation time of the plan, s.
        points_xy_m: (1 + n, 2) float64 world frame: the ego's box centre at the plan's time,
            then the waypoints at WAYPOINT_TIMES_S after it.
    """

    time_s: float
    points_xy_m: np.ndarray

    @staticmethod
    def from_ego(time_s: float, pose: Pose, waypoints_ego: np.ndarray) -> Plan:
        """waypoints_ego: (n, 2) m, ego frame at `pose` (the model's output)."""
        world = pose.world_from_ego(np.asarray(waypoints_ego, dtype=np.float64))
        return Plan(time_s, np.vstack([[pose.x_m, pose.y_m], world]))

    def ahead(self, time_s: float, pose: Pose) -> np.ndarray:
        """(K, 2) the trajectory from its point at `time_s` to its last waypoint, in the
        frame of `pose` (what pure pursuit steers along)."""
        times = np.concatenate([[0.0], WAYPOINT_TIMES_S[: len(self.points_xy_m) - 1]])
        pts = self.points_xy_m
        elapsed = min(max(time_s - self.time_s, 0.0), float(times[-1]))
        k = int(np.clip(np.searchsorted(times, elapsed, side="right") - 1, 0, len(times) - 2))
        f = (elapsed - times[k]) / (times[k + 1] - times[k])
        now = pts[k] + f * (pts[k + 1] - pts[k])
        return pose.ego_from_world(np.vstack([now, pts[k + 1 :]]))

    def at(self, time_s: float, pose: Pose) -> np.ndarray:
        """(2, 2) the trajectory at +0.5 s and +1.0 s from `time_s`, in the frame of `pose`
        (linear in time between points, extrapolated past the last one)."""
        times = np.concatenate([[0.0], WAYPOINT_TIMES_S[: len(self.points_xy_m) - 1]])
        pts = self.points_xy_m
        elapsed = time_s - self.time_s
        out = []
        for t in (elapsed + WAYPOINT_TIMES_S[0], elapsed + WAYPOINT_TIMES_S[1]):
            k = int(np.clip(np.searchsorted(times, t) - 1, 0, len(times) - 2))
            f = (t - times[k]) / (times[k + 1] - times[k])
            out.append(pts[k] + f * (pts[k + 1] - pts[k]))
        return pose.ego_from_world(np.array(out))
