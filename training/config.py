"""Model and training configuration: two frozen dataclasses, two sizes, two architectures.

Sizes (PRESETS): `paper` is the model of the II-DSU paper (Sec. III) at its size; `tiny` is the
same architecture shrunk so that a training step runs in a fraction of a second on a laptop CPU
(tests, `make demo`). Architectures (ARCHITECTURES): the dataclasses' defaults are the paper's
model with nothing of ours; `ours` is it plus the additions of OURS_MODEL and OURS_TRAIN
(`with_architecture`, `train fit --arch ours`), each also switchable on its own. The CLI starts
from a preset and overrides fields with `dataclasses.replace`; checkpoints store both configs
(`to_dict`) so `--resume`, `eval`, `analyze`, `show` and `drive` rebuild the same model.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

POOLS = ("avg", "avgmax")
"""How a pooled head (training/heads.py) reduces its map: "avg", a C-d mean over positions (the
planning head's reduction in the paper); "avgmax", the mean and the maximum side by side (2C-d)."""

HEADS = ("planning", "detection", "bev", "traffic", "weather")
"""Every head of the model, planning first; the four auxiliary ones can be switched off."""


@dataclass(frozen=True)
class ModelConfig:
    """Architecture of II-DSU (paper Sec. III-B). The defaults are the paper's model, with no
    addition of ours (`architecture(cfg) == "paper"`).

    Where the paper is silent the choice is TransFuser's (Prakash et al. 2021, the paper's
    baseline, whose fusion layer and planner it reuses): the fusion depth (8 attention blocks, 4
    heads per layer), 8x8 token anchors per modality, learned position embeddings plus a
    velocity embedding of the measured ego speed (the only place the speed enters the paper's
    model), the LiDAR count clip (5, TransFuser's hist_max_per_pixel), the planner's MLP
    halving its width per layer and its GRU reading (previous waypoint, target point). ConvNeXt's
    own choices fill the encoder: ConvNeXt-Tiny's depths and stochastic depth (0.1) and layer
    scale (1e-6); TransFuser's encoders are ImageNet-pretrained, these cannot be (the paper's
    widths are not ConvNeXt-T's). CenterNet's decoder widths (256, 128, 64) for the dense heads,
    ECA's adaptive kernel rule, and a mean over positions for "reduced to 1024 dimensions".

    Ours (`OURS_MODEL`, `train fit --arch ours`): the fields below "Additions of ours", each off
    here and switchable on its own; docs/learning.md has what each was measured to do.
    """

    # Encoders: ConvNeXt-Tiny's depths with the paper's widths, down-sampling /4, /2, /2, /2.
    depths: tuple[int, ...] = (3, 3, 9, 3)
    dims: tuple[int, ...] = (64, 128, 256, 512)
    drop_path: float = 0.1  # stochastic depth at the last block (ConvNeXt-T's ImageNet value)
    layer_scale_init: float = 1e-6  # ConvNeXt's layer scale initial value
    input_px: int = 256  # camera crop and LiDAR BEV side (Sec. III-A); a multiple of 32
    # TransFuser fusion (Prakash et al. 2021): both maps pooled to an 8x8 token grid, 8
    # attention blocks with 4 heads per fusion layer, as in TransFuser's GPT.
    fusion_tokens: int = 8  # token grid side per modality (the final 256/32 = 8 map, unpooled)
    fusion_blocks: int = 8
    fusion_heads: int = 4
    feature_dim: int = 1024  # channels of F_DSU, the 8x8 scene feature (Sec. III-A)
    # Heads (Sec. III-B).
    planner_hidden: int = 128  # GRU state; the 3-layer MLP reduces F_DSU's 1024-d to this
    n_waypoints: int = 4  # T_future; the shards hold +0.5 .. +2.0 s
    output_px: int = 256  # R, side of the dense heads' maps; 256 / 2**k with k >= 0
    decoder_width: int = 256  # channels after the first up-sampling step; halved per step
    lidar_clip_count: float = 5.0  # LiDAR counts are clipped here and scaled to [0, 1]
    # (TransFuser's hist_max_per_pixel)
    # Ablation switches (the paper's Table III rows).
    detection: bool = True
    bev: bool = True
    traffic: bool = True
    weather: bool = True
    single_frame_lidar: bool = False  # LiDAR input: the current sweep only (training/model.py)

    # Additions of ours (training/lamps.py, training/heads.py), all off in the paper's model;
    # what each changed on held-out towns: docs/learning.md.
    # The planner's MLP also reads the measured ego speed, m/s (heads.PlanningHead).
    planner_speed: bool = False
    # A traffic-rule head on the camera alone, before any fusion, trained beside F_DSU's
    # (lamps.CameraTrafficHead; loss weight TrainConfig.lambda_camera_tf).
    camera_traffic: bool = False
    # How the traffic-rule heads reduce their 8x8 map: "avg" (the paper's mean) or "avgmax"
    # (mean and maximum side by side, so a lamp filling one cell of 64 is not averaged away).
    traffic_pool: str = "avg"
    # Signal-lamp maps: a 1x1 conv on the camera's first stage (stride 4, unfused), this many
    # maps max-pooled to F_DSU's grid and concatenated into the 1x1 conv that makes F_DSU
    # (lamps.LampMaps). 0 = off.
    lamp_channels: int = 0
    # Per-pixel colour detectors on the normalised image (a 1x1 conv 3 -> this many, GELU),
    # max-pooled beside the lamp maps (lamps.LampMaps). 0 = off.
    pixel_lamp_channels: int = 0
    # F_DSU's traffic head predicts a correction added to the camera-only head's logits
    # (lamps.traffic_residual); needs camera_traffic.
    traffic_residual: bool = False
    # In training, drop that correction per frame and logit with this probability (scaled as
    # dropout); 0 = off.
    traffic_residual_dropout: float = 0.0
    # Ours, in neither architecture (EXTRA_MODEL): False = the model never reads the measured ego
    # speed (the fusion's velocity embedding and, with planner_speed, the planner get 0). A
    # tiny model trained with it planned from the speed input alone: standing with the speed
    # set to 0, going with it set to 3 m/s, red light or not (docs/closed-loop.md, 2026-12-06).
    speed_input: bool = True

    def __post_init__(self):
        if len(self.depths) != 4 or len(self.dims) != 4:
            raise ValueError("depths and dims need four stages each")
        if self.lamp_channels < 0:
            raise ValueError(f"lamp_channels must be >= 0, got {self.lamp_channels}")
        if self.pixel_lamp_channels < 0:
            raise ValueError(f"pixel_lamp_channels must be >= 0, got {self.pixel_lamp_channels}")
        if not 0.0 <= self.traffic_residual_dropout < 1.0:
            raise ValueError(
                f"traffic_residual_dropout must be in [0, 1), got {self.traffic_residual_dropout}"
            )
        if self.traffic_pool not in POOLS:
            raise ValueError(f"traffic_pool must be one of {POOLS}, got {self.traffic_pool!r}")
        if self.input_px % 32:
            raise ValueError(f"input_px must be a multiple of 32, got {self.input_px}")
        side = self.input_px // 32
        up = self.output_px / side  # the dense decoders up-sample F_DSU by this factor
        if up < 1 or up != 2 ** round(math.log2(up)):
            raise ValueError(
                f"output_px must be {side} times a power of two (the F_DSU map is {side}x{side}),"
                f" got {self.output_px}"
            )

    @property
    def heads(self) -> tuple[str, ...]:
        """The heads this model has: planning and every auxiliary head not switched off."""
        on = {"detection": self.detection, "bev": self.bev, "traffic": self.traffic}
        on["weather"] = self.weather
        return ("planning",) + tuple(h for h in HEADS[1:] if on[h])

    @property
    def has_camera_traffic(self) -> bool:
        """The camera-only traffic-rule head is on (only with the traffic head: the "No Traffic
        Rule" ablation must not learn the rule elsewhere)."""
        return self.camera_traffic and self.traffic

    @property
    def has_traffic_residual(self) -> bool:
        """F_DSU's traffic-rule head adds its logits to the camera-only head's."""
        return self.traffic_residual and self.has_camera_traffic

    @property
    def lidar_in_channels(self) -> int:
        """Channels of the LiDAR input: 4 (ground summed over t, t-1, t-2; above-ground at t,
        t-1, t-2), or 2 for the single-frame ablation (ground and above-ground at t)."""
        return 2 if self.single_frame_lidar else 4

    @property
    def feature_px(self) -> int:
        """Side of F_DSU and of the last encoder stage: input_px / 32."""
        return self.input_px // 32

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @property
    def additions(self) -> tuple[str, ...]:
        """The additions of ours this config switches on (fields of OURS_MODEL that differ
        from the paper's model), in OURS_MODEL's order, then EXTRA_MODEL's; () for the paper's
        model."""
        paper = ModelConfig()
        return tuple(
            k for k in (*OURS_MODEL, *EXTRA_MODEL) if getattr(self, k) != getattr(paper, k)
        )

    @classmethod
    def from_dict(cls, d: dict) -> ModelConfig:
        # A checkpoint stores every field it was trained with; one from before an addition
        # existed was trained without it, i.e. with the paper's value (the default).
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation, data and loss weights. The paper gives the loss's form (Sec. III-C) but
    none of these values: AdamW at 1e-4 is TransFuser's (Prakash et al. 2021); the batch,
    epochs, schedule and loss weights are ours (see `train fit --help`)."""

    shards: str = "data"
    out: str = "runs/iidsu"
    epochs: int = 30
    batch_size: int = 32
    lr: float = 1e-4  # AdamW peak learning rate (TransFuser's)
    min_lr_frac: float = 0.01  # the cosine decays to lr * min_lr_frac
    warmup_frac: float = 0.02  # share of all steps spent in linear warm-up
    weight_decay: float = 0.01  # on weights of dimension >= 2 only (not norms, biases)
    grad_clip: float = 1.0
    num_workers: int = 4  # DataLoader processes decoding JPEG/PNG per training process
    shuffle_buffer: int = 512  # encoded frames held per worker for shuffling (~35 kB each)
    open_row_groups: int = 64  # row groups a worker reads from at once (training/data.py)
    val_fraction: float = 0.1  # share of episodes held out, unless val_towns is given
    val_towns: tuple[str, ...] = ()  # hold out these towns' episodes instead
    seed: int = 0
    # Ours (OURS_TRAIN): camera zoom-out augmentation (training/augment.py). This share of the
    # training frames is shrunk about the image centre by a factor uniform in [zoom_out, 1), so
    # that a signal lamp is seen at the sizes other junction widths give. 1 or more: off (the
    # paper names no augmentation); measured: docs/learning.md.
    zoom_out: float = 1.0
    zoom_out_probability: float = 0.5
    compile: bool = False  # torch.compile the model (worth it on a GPU, slow to start)
    # Decoded-frame cache (training/cache.py): its directory ("": $IIDSU_CACHE/decoded, else
    # ~/.cache/iidsu/decoded) and its bound in GB (0: off, every epoch decodes the shards).
    cache_dir: str = ""
    cache_gb: float = 32.0
    # Intra-op CPU threads per process; 0: the cores this process may run on (its CPU
    # affinity) divided among the processes of the machine (training/device.py `cpu_threads`).
    threads: int = 0
    # Ours: decay of an exponential moving average of the weights, updated every step; the
    # average is what validation scores and last.pt's "model" holds (training/fit.py). 0 = off.
    ema_decay: float = 0.0
    val_metrics: bool = True  # `train eval`'s metrics on the held-out frames every epoch
    # A checkpoint whose weights start the run (fine-tuning, e.g. after `drive collect`); the
    # optimizer and schedule start afresh. "": random initial weights.
    init: str = ""
    # Loss weights: L = l_wp L_wp + l_O (alpha L_heat + beta L_reg) + l_M L_M
    #                   + l_tf (gamma L_light + delta L_sign) + l_wc L_wc   (Sec. III-C).
    # The weights are ours (the paper gives none): planning dominates, as Sec. III-C wishes;
    # the rest only gives F_DSU prior knowledge.
    lambda_wp: float = 1.0
    lambda_o: float = 0.2
    lambda_m: float = 0.2
    lambda_tf: float = 0.1
    lambda_wc: float = 0.1
    # Ours: weight of the camera-only traffic-rule term (ModelConfig.camera_traffic; only with
    # it), as much as the traffic head's own.
    lambda_camera_tf: float = 0.1
    # Cross-entropy weights of the BEV classes (other, drivable, lane marking): ours. Markings
    # are ~8 % of the pixels at R = 64 (3 % at 256); with equal weights the tiny model predicted
    # none on a held-out town (docs/learning.md, "BEV weights 1-1-1").
    bev_class_weights: tuple[float, ...] = (1.0, 1.0, 3.0)
    # Positive-class weights of L_light and L_sign (BCE pos_weight): ours. A red light governs
    # ~15-25 % of the frames and a stop sign fewer; unweighted, the tiny model's red-light head
    # ended at "never red" on a held-out town (docs/learning.md, "BEV weights 1-1-1").
    traffic_pos_weight: tuple[float, float] = (3.0, 3.0)
    # Ours, in neither architecture: frames where the ego's speed contradicts the traffic
    # label's usual context (red light or stop sign while moving, neither while stopped) weigh
    # this much in L_light and L_sign (losses.context_weights); 1 = off (3 measured worse:
    # docs/learning.md).
    traffic_context_weight: float = 1.0
    alpha: float = 1.0
    beta: float = 1.0
    gamma: float = 1.0
    delta: float = 1.0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        # runs from before an option had none: its default is "off"
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


ARCHITECTURES = ("paper", "ours")
"""`train fit --arch`: the paper's II-DSU (Sec. III), or it with every addition of ours."""

OURS_MODEL: dict[str, object] = {
    "planner_speed": True,
    "camera_traffic": True,
    "traffic_pool": "avgmax",
    "lamp_channels": 8,
    "pixel_lamp_channels": 8,
    "traffic_residual": True,
    "traffic_residual_dropout": 0.5,
}
"""The additions of ours to ModelConfig, with the values `--arch ours` sets (each field's
comment says what it does; docs/learning.md what it was measured to do)."""

EXTRA_MODEL = ("speed_input",)
"""Options of ours outside both architectures (each field's comment says what it does)."""

OURS_TRAIN: dict[str, object] = {"zoom_out": 0.55}
"""The addition of ours to TrainConfig that `--arch ours` sets."""


def with_architecture(
    model: ModelConfig, train: TrainConfig, arch: str
) -> tuple[ModelConfig, TrainConfig]:
    """`model` and `train` with every addition of ours set to `arch`'s value: the paper's
    (off) or OURS_MODEL / OURS_TRAIN's. Every other field is kept."""
    if arch not in ARCHITECTURES:
        raise ValueError(f"architecture must be one of {ARCHITECTURES}, got {arch!r}")
    if arch == "paper":
        m, t = ModelConfig(), TrainConfig()
        paper_model = {k: getattr(m, k) for k in OURS_MODEL}
        paper_train = {k: getattr(t, k) for k in OURS_TRAIN}
        return dataclasses.replace(model, **paper_model), dataclasses.replace(train, **paper_train)
    return dataclasses.replace(model, **OURS_MODEL), dataclasses.replace(train, **OURS_TRAIN)


def architecture(model: ModelConfig, train: TrainConfig | None = None) -> str:
    """The architecture's name: `paper` (no addition of ours), `ours` (every addition at
    OURS_MODEL / OURS_TRAIN's value), else `paper + ` the additions that are on."""
    on = list(model.additions)
    if train is not None:
        paper = TrainConfig()
        on += [k for k in OURS_TRAIN if getattr(train, k) != getattr(paper, k)]
    if not on:
        return "paper"
    ours = all(getattr(model, k) == v for k, v in OURS_MODEL.items())
    ours = ours and not any(k in on for k in EXTRA_MODEL)
    if ours and (train is None or all(getattr(train, k) == v for k, v in OURS_TRAIN.items())):
        return "ours"
    return "paper + " + ", ".join(on)


PRESETS: dict[str, tuple[ModelConfig, TrainConfig]] = {
    # The paper's model (Sec. III); the training recipe is ours and TransFuser's (TrainConfig).
    "paper": (ModelConfig(), TrainConfig()),
    # The same architecture shrunk for CPUs: one block per stage, widths / 4, F_DSU 8x8x128, one
    # attention block per fusion layer, 64x64 dense maps (0.5 m per pixel).
    "tiny": (
        ModelConfig(
            depths=(1, 1, 1, 1),
            dims=(16, 32, 64, 128),
            drop_path=0.0,
            fusion_blocks=1,
            fusion_heads=2,
            feature_dim=128,
            planner_hidden=64,
            output_px=64,
            decoder_width=32,
        ),
        TrainConfig(batch_size=8, lr=1e-3, warmup_frac=0.05, num_workers=1, shuffle_buffer=256),
    ),
}


def preset(name: str, arch: str = "paper") -> tuple[ModelConfig, TrainConfig]:
    """PRESETS[name] (the paper's architecture at that size) as `arch` ("paper" or "ours")."""
    return with_architecture(*PRESETS[name], arch)
