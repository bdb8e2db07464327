"""One episode: drive the world, record every frame's sensors and labels, return a v1 table.

    result = run_episode(EpisodeSpec("grid_small-7-0", "grid_small", str(net), seed=7,
                                     weather="rainy", behaviour="cautious", n_frames=40))
    result.table      # pa.Table, validated against schemas (file metadata filled)

The world is recorded at 2 Hz for HISTORY + n_frames + FUTURE states. The first HISTORY (2)
states only contribute their LiDAR sweeps (the t-1 and t-2 channels of the first row); the last
FUTURE (4) only their ground truth (waypoints reach +2.0 s, boxes +1.0 s). Each frame is
processed once its future is recorded, so the camera and labels are paid only for frames that
become rows. If the world ends early (route end, teleport, blocked ego) the frames without a
full future are dropped and the table holds fewer than n_frames rows.

Per frame (timed per stage in `stats["timing"]`): sim (SUMO steps to the next recorded state),
scene (the agents' boxes and their Embree scene; the culled static scene of the ego's cell,
committed once per process: datagen/sensors/raycast.py), lidar (sweep + BEV counts),
camera, labels (BEV semantic raster, boxes, waypoints), encode (JPEG, PNGs).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pyarrow as pa

import schemas
from datagen import labels
from datagen.sensors import camera, lidar
from datagen.sensors.config import HISTORY, SensorConfig
from datagen.sensors.raycast import SceneBuilder
from datagen.sensors.scene import SCENE_VERSION, StaticScene, load_static_scene
from datagen.state import FrameState
from schemas import codecs

FUTURE = labels.FUTURE_FRAMES  # 4 future states for +2.0 s waypoints
STAGES = ("sim", "scene", "lidar", "camera", "labels", "encode")

DATA_VERSION = 10
"""What the generator writes, beyond the scene (bump it with every change of shard bytes for the
same seed; tests/test_identical.py pins them; data/README.md lists the changes):
1 the first release; 2 PNG columns encoded with no/UP row filter + RLE (same decoded arrays);
3 the `lidar_ground_t` column (schema 1.1); 4 every signal head lit with its own light's real
state at any distance (was: only the heads showing the ego's governing light within 30 m);
5 the expert yields to people at crossings and keeps junctions clear, and an episode that ends
in an ego collision loses its last 5 s of frames (datagen/world/world.py `record`); 6 the expert
yields to people its body would sweep on a turn and waits out a green too short to clear the
junction (datagen/world/perception.py `swept_contact`, datagen/world/expert.py `light_rule`); 7 the
target point is the next point of the sparse route plan by default (SensorConfig.target_point);
the expert yields to a standing person at the kerb only where its body would cover them, and
after a stop sign waits at the line while a foe is inside the junction or due within 5 s; 8 the
expert brakes harder than its vType decel when that cannot stop it short of a car or person on
its path (`expert.emergency_brake_mps2`), and counts a car standing at a stop line across a
junction as a foe before beginning a turn that waits inside it; 9 a vehicle is on the expert's
path by the part of its box inside the corridor ahead (`perception.corridor_span`; a skewed bus
beside it no longer stops it), and a green that ends too soon is timed at the junction's curve
speed, read from the comfortable stopping distance out and stopped for at the vType decel;
10 the camera JPEG keeps full-resolution colour (4:4:4; schemas/codecs.py JPEG_SAMPLING)."""


def generator_version() -> str:
    """What made the data: the package version, the static scene's and the data's version."""
    try:
        from importlib.metadata import version

        v = version("iidsu")
    except Exception:  # noqa: BLE001  (a source checkout without installed metadata)
        v = "0+unknown"
    return f"iidsu {v}, scene v{SCENE_VERSION}, data v{DATA_VERSION}"


@dataclass(frozen=True)
class EpisodeSpec:
    """What to drive: town and network, seed (world and sensors), weather, behaviour, length."""

    episode_id: str
    town: str
    net_path: str
    seed: int
    weather: str
    behaviour: str
    n_frames: int


@dataclass
class EpisodeResult:
    """A finished episode.

    Attributes:
        table: the rows, validated v1, with file metadata (schemas.file_metadata).
        end_reason: why the world ended early (World.ended), None if it ran to n_frames.
        stats: the world's statistics plus "timing": seconds per stage (STAGES) and "frames".
    """

    table: pa.Table
    end_reason: str | None
    stats: dict


class Sensors:
    """Scene, LiDAR and camera of one episode in one town (static mesh, ray directions and
    random streams set up once)."""

    def __init__(
        self, static: StaticScene, config: SensorConfig, weather: str, rng: np.random.Generator
    ):
        self.static = static
        self.config = config
        self.weather = weather
        self.lidar = lidar.Lidar(config.lidar)
        self.camera = camera.Camera(config.camera)
        reach = max(
            config.lidar.range_m + abs(config.lidar.mount_x_m),
            config.camera.range_m + abs(config.camera.mount_x_m),
        )
        self.builder = SceneBuilder(static, reach_m=reach, raycaster=config.raycaster)
        lidar_rng, camera_rng, pose_rng, sun_rng = rng.spawn(4)
        self.lidar_rng, self.camera_rng, self.pose_rng = lidar_rng, camera_rng, pose_rng
        self.sun = camera.sun_direction(sun_rng)
        if weather not in lidar.LIDAR_WEATHER:
            raise ValueError(f"unknown weather {weather!r}; expected one of {schemas.WEATHERS}")
        self.lidar_weather = lidar.LIDAR_WEATHER[weather]
        self.camera_weather = camera.CAMERA_WEATHER[weather]

    def scene(self, frame: FrameState):
        return self.builder.build(frame)

    def sweep(self, scene, frame: FrameState) -> lidar.Sweep:
        return self.lidar.sweep(scene, frame.ego.pose, self.lidar_weather, self.lidar_rng)

    def lidar_counts(self, sweeps: list[lidar.Sweep]) -> np.ndarray:
        """(5, 256, 256) BEV hit counts of the sweeps at t, t-1, t-2 (lidar.bev_counts)."""
        return lidar.bev_counts(
            sweeps,
            self.config.lidar.ground_threshold_m,
            self.pose_rng,
            self.config.pose_noise_m,
            self.config.pose_noise_rad,
        )

    def image(self, scene, frame: FrameState) -> np.ndarray:
        lamps = camera.lit_slots(self.static, frame, self.config.camera.range_m + 10.0)
        return self.camera.render(
            scene, frame.ego.pose, self.camera_weather, self.camera_rng, self.sun, lamps
        )


class _Timer:
    def __init__(self) -> None:
        self.s = dict.fromkeys(STAGES, 0.0)
        self.t = time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.s[stage] += now - self.t
        self.t = now


def episode_rng(seed: int) -> np.random.Generator:
    """The sensors' random stream of an episode (independent of SUMO's, same seed)."""
    return np.random.default_rng(np.random.SeedSequence([seed, 0x5E5]))


def recovery_rng(seed: int) -> np.random.Generator:
    """The stream that draws an episode's recovery frames and their rigs (SensorConfig)."""
    return np.random.default_rng(np.random.SeedSequence([seed, 0x12EC]))


def _rig(config: SensorConfig, rng: np.random.Generator) -> tuple[float, float]:
    """(shift_m, yaw_rad) of one frame's sensor rig: (0, 0), or a recovery frame's draw."""
    if config.recovery_share <= 0.0 or rng.random() >= config.recovery_share:
        return (0.0, 0.0)
    shift = float(rng.uniform(-config.recovery_shift_m, config.recovery_shift_m))
    yaw = float(np.radians(rng.uniform(-config.recovery_yaw_deg, config.recovery_yaw_deg)))
    return (shift, yaw)


def run_episode(
    spec: EpisodeSpec,
    sensors: SensorConfig = SensorConfig(),
    progress: Callable[[int], None] | None = None,
) -> EpisodeResult:
    """Drive one episode and return its table (see the module docstring)."""
    from datagen.world import World, WorldConfig, record
    from datagen.world.towns import network_sha256

    net = Path(spec.net_path)
    static = load_static_scene(net)
    sense = Sensors(static, sensors, spec.weather, episode_rng(spec.seed))
    rigs = recovery_rng(spec.seed)
    config = WorldConfig(
        net_path=net,
        seed=spec.seed,
        weather=spec.weather,
        behaviour=spec.behaviour,
        target_point=sensors.target_point,
    )
    timer = _Timer()
    states: list[FrameState] = []
    sweeps: dict[int, lidar.Sweep] = {}
    rows: list[dict] = []
    reported = 0
    with World(config) as world:
        timer.lap("sim")  # start-up counts as simulation
        stream: Iterator[FrameState] = record(world, HISTORY + spec.n_frames + FUTURE)
        for state in stream:
            timer.lap("sim")
            states.append(state)
            k = len(states) - 1 - FUTURE  # this frame's future is now complete
            if k < 0:
                continue
            row = _process(k, states, sweeps, sense, spec, timer, rigs)
            if row is not None:
                rows.append(row)
                if progress is not None and len(rows) - reported >= 5:
                    progress(len(rows) - reported)
                    reported = len(rows)
            timer.t = time.perf_counter()
        timer.lap("sim")
        end_reason = world.ended
        stats = dict(world.stats)
    if progress is not None and len(rows) > reported:
        progress(len(rows) - reported)
    table = episode_table(rows, sensors, network_sha256(net), spec.seed, spec.episode_id)
    stats["timing"] = {k: round(v, 4) for k, v in timer.s.items()}
    stats["frames"] = len(rows)
    return EpisodeResult(table=table, end_reason=end_reason, stats=stats)


def episode_table(
    rows: list[dict], sensors: Sensors, net_sha256: str, seed: int, episode_id: str
) -> pa.Table:
    """An episode's rows (numbered here 0, 1, ... as `frame`) as a validated shard table with
    the file metadata: generator version, sensor config, network and seed. What `datagen
    build` and `drive collect` write."""
    for i, row in enumerate(rows):
        row["frame"] = i
    meta = schemas.file_metadata(
        generator_version=generator_version(),
        config=sensors.to_dict(),
        network_sha256=net_sha256,
        seed=seed,
    )
    table = pa.Table.from_pylist(rows, schema=schemas.schema(meta))
    schemas.validate(table, where=episode_id)
    return table


def _process(
    k: int,
    states: list[FrameState],
    sweeps: dict[int, lidar.Sweep],
    sense: Sensors,
    spec: EpisodeSpec,
    timer: _Timer,
    rigs: np.random.Generator,
) -> dict | None:
    """Sweep frame k (kept for the next two frames) and, past the history, make its row. A
    recovery frame (`_rig`) is sensed again from its rig for the row (its camera and the LiDAR
    sweep at t; the past sweeps, aligned into the rig's frame, stay the ego's own), while the
    ego's own sweep is what later frames keep as their history."""
    frame = states[k]
    scene = sense.scene(frame)
    timer.lap("scene")
    sweeps[k] = sense.sweep(scene, frame)
    sweeps.pop(k - HISTORY - 1, None)
    if k < HISTORY:
        timer.lap("lidar")
        return None
    rig = _rig(sense.config, rigs)
    seen, now = frame, sweeps[k]
    if rig != (0.0, 0.0):
        pose = labels.rig_pose(frame.ego.pose, *rig)
        seen = replace(frame, ego=replace(frame.ego, pose=pose))
        now = sense.sweep(scene, seen)
    encoded = encode_sensors(
        sense, scene, seen, [now, *(sweeps[k - j] for j in range(1, HISTORY + 1))], timer
    )
    future = states[k + 1 : k + 1 + FUTURE]
    row = labels.frame_labels(frame, future, now.actor_hits, rig).row()  # FrameLabels -> columns
    semantic = labels.bev_semantic(sense.static.label_map, seen.ego.pose)
    timer.lap("labels")
    row.update(
        episode_id=spec.episode_id,
        town=spec.town,
        weather=spec.weather,
        behaviour=spec.behaviour,
        **encoded,
        bev_semantic=codecs.encode_bev_semantic(semantic),
    )
    timer.lap("encode")
    return row


def encode_sensors(
    sense: Sensors,
    scene,
    frame: FrameState,
    sweeps: list[lidar.Sweep],
    timer: _Timer | None = None,
) -> dict[str, bytes]:
    """The sensor columns of one frame as the shards hold them (image, lidar_bev,
    lidar_ground_t): the camera seen from `frame`'s ego pose in `scene`, and the LiDAR BEV of
    `sweeps` (at t, t-1, t-2, newest first: HISTORY + 1) in that pose's frame. The one encoder
    of a frame: the build and closed-loop driving (drive/sim.py) both call it."""
    counts = sense.lidar_counts(sweeps)
    bev, ground_t = lidar.lidar_bev_channels(counts), lidar.ground_channel(counts)
    if timer is not None:
        timer.lap("lidar")
    image = sense.image(scene, frame)
    if timer is not None:
        timer.lap("camera")
    return {
        "image": codecs.encode_image(image, sense.config.jpeg_quality),
        "lidar_bev": codecs.encode_lidar_bev(bev),
        "lidar_ground_t": codecs.encode_lidar_ground(ground_t),
    }
