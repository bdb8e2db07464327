"""The sensors' configuration: what the LiDAR and camera are and how their data are encoded."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import schemas
from datagen.sensors import camera, lidar
from datagen.sensors.raycast import RAYCASTERS, ray_backend
from schemas import codecs

HISTORY = 2  # past sweeps in the LiDAR BEV (t-1, t-2)


@dataclass(frozen=True)
class SensorConfig:
    """Sensors and encoding (defaults: the paper's setup, Sec. III-A; see lidar.py, camera.py).

    Attributes:
        lidar, camera: the two sensors.
        raycaster: how their rays are cast (datagen/sensors/raycast.py): "embree", the fast path
            (where it cannot load, trimesh's, with one warning line), or "trimesh", trimesh.ray
            on the same Embree (`--sensor raycaster=trimesh`): the same hits, distances equal
            to ~1e-5 m. In iidsu.config_json only where trimesh's ran, so the default's shards
            keep their bytes.
        jpeg_quality: of the stored camera crop.
        pose_noise_m, pose_noise_rad: GPS/IMU noise (standard deviation) on the poses that align
            the t-1 and t-2 sweeps; 0 = exact recorded poses.
        target_point: the `target_point` column's form, "sparse" (the next point of the sparse
            route plan, the paper's route goal) or "dense" (30 m along the lane path); see
            datagen/world/config.py WorldConfig. Not a sensor, but it shapes the data, so it is
            recorded here (iidsu.config_json) and set with `--sensor target_point=dense`.
        recovery_share: the share of frames sensed from a shifted and turned rig (recovery
            frames, datagen/episode.py `_rig`; TransFuser++'s camera augmentation, Jaeger et
            al. 2023, carla_garage config.py camera_translation_augmentation /
            camera_rotation_augmentation), with every label in that rig's frame
            (labels.frame_labels), so the model sees itself beside its lane and askew and learns
            the way back; the rig's shift is uniform in +-recovery_shift_m to the side and its
            turn in +-recovery_yaw_deg. Like target_point it shapes the labels, not what a
            sensor sees in closed loop (schemas.LABEL_ONLY_CONFIG_KEYS).
        driver: who drove the ego: "expert" (the recorded expert, waypoints from its future), or
            what `drive collect` says of the policy that drove it (on-policy frames labelled
            with the expert's plan); label-only too.
    """

    lidar: lidar.LidarConfig = field(default_factory=lidar.LidarConfig)
    camera: camera.CameraConfig = field(default_factory=camera.CameraConfig)
    raycaster: str = "embree"
    jpeg_quality: int = codecs.DEFAULT_JPEG_QUALITY
    pose_noise_m: float = 0.0
    pose_noise_rad: float = 0.0
    target_point: str = "sparse"
    recovery_share: float = 0.0
    recovery_shift_m: float = 1.0
    recovery_yaw_deg: float = 5.0
    driver: str = "expert"

    def __post_init__(self):
        if self.raycaster not in RAYCASTERS:
            raise ValueError(f"raycaster must be one of {RAYCASTERS}")
        from datagen.world.route import TARGET_FORMS

        if self.target_point not in TARGET_FORMS:
            raise ValueError(f"target_point must be one of {TARGET_FORMS}")
        if not 0.0 <= self.recovery_share <= 1.0:
            raise ValueError(f"recovery_share must be in [0, 1], got {self.recovery_share}")
        if self.recovery_shift_m < 0.0 or self.recovery_yaw_deg < 0.0:
            raise ValueError("recovery_shift_m and recovery_yaw_deg must be >= 0")

    def to_dict(self) -> dict:
        """Everything that shapes the data, for the shard metadata (iidsu.config_json): this
        config, the weather tables, the BEV grid and the recording rates (the ray backend only
        where it is trimesh's: forced, or the fast path cannot load here)."""
        config = asdict(self)
        if ray_backend(config.pop("raycaster")).NAME != "embree":
            config["raycaster"] = "trimesh"
        return {
            **config,
            "lidar_weather": {k: asdict(v) for k, v in lidar.LIDAR_WEATHER.items()},
            "camera_weather": {k: asdict(v) for k, v in camera.CAMERA_WEATHER.items()},
            "bev_grid": {
                "size_px": schemas.BEV_SIZE_PX,
                "px_per_m": schemas.BEV_PX_PER_M,
                "ahead_m": schemas.BEV_AHEAD_M,
                "side_m": schemas.BEV_SIDE_M,
            },
            "frame_rate_hz": schemas.FRAME_RATE_HZ,
            "lidar_history_frames": HISTORY,
        }
