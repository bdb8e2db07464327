"""Model and training configuration: two frozen dataclasses, two named presets.

`paper` is the model of the II-DSU paper (Sec. III); `tiny` is the same architecture shrunk so
that a training step runs in a fraction of a second on a laptop CPU (tests, `make demo`). The CLI
starts from a preset and overrides fields with `dataclasses.replace`; checkpoints store both
configs (`to_dict`) so `--resume`, `eval`, `analyze` and `show` rebuild the same model.
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
    """Architecture of II-DSU (paper Sec. III-B). Defaults are the paper's model."""

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
    # Ours, not the paper's: the planner's MLP also reads the measured ego speed, m/s (the
    # paper feeds it only to the fusion tokens; see training/heads.py PlanningHead).
    planner_speed: bool = True
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
    # Ours, not the paper's: a training-time traffic-rule head on the camera alone
    # (training/model.py IIDSU.camera_traffic): it reads the lamp maps (lamp_channels), or,
    # without them, stages 2-4 of the camera run again on the unfused first stage. Without it
    # the tiny model read red lights from LiDAR context, not from the lamps: trained on a
    # 16k-frame v10 build, its red-light F1 with a flat camera image was still 0.78 on
    # grid_small and 0.36 on the held-out town (0.96 and 0.42 with the image), and a linear
    # probe of the camera encoder alone found no red light (F1 0.37 seen, 0.05 held out;
    # bench/probe.py --head red [--blank image]).
    camera_traffic: bool = True
    # Ours: how the traffic-rule heads (and the camera-only one) reduce their 8x8 map; the paper
    # says only "reduced to 1024 dimensions" (Sec. III-B). "avg" is the mean over positions, as
    # the planning head's; "avgmax" adds the maximum beside it, because a signal lamp 1.5-3 px
    # wide fills one cell of 64 and a mean dilutes it (one threshold on the raw image's third
    # largest redness R - max(G, B), chosen on the seven training towns of the 16k v10 build,
    # scores held-out arterial's red lights F1 0.81; the avg-pooled model 0.47).
    traffic_pool: str = "avgmax"
    # Ours: signal-lamp channels. A 1x1 conv on the camera encoder's first stage (stride 4,
    # before any fusion) gives this many maps, each max-pooled to F_DSU's 8x8 grid and fed
    # with the fused maps into the 1x1 conv that makes F_DSU; the camera-only traffic-rule head
    # reads them instead of re-running stages 2-4. A held-out lamp is 1.5-3 px: on the 16k v10
    # build a camera-only red-light classifier trained on seven towns scored on held-out
    # arterial F1 0.21 reading the stride-32 map, 0.32 at stride 8 and 0.63-0.80 with 8 such
    # stride-4 maps (1,000 steps each; 3 seeds: 0.80, 0.68, 0.63). 0 = off (earlier runs).
    lamp_channels: int = 8
    # Ours: pixel lamp channels. Per-pixel colour detectors on the normalised camera image (a
    # 1x1 conv 3 -> this many, then GELU) give maps max-pooled to F_DSU's grid beside the lamp
    # maps above, so that a lamp's colour is judged per pixel before any stride mixes it with
    # its surround (one threshold on the raw image's third-largest redness scores held-out
    # arterial F1 0.81). On bench/learn.py's 16k check: held-out red-light F1 0.873 with 8,
    # 0.75 without (README "Does it learn?"); 29 ms forward and backward for 8 images on one
    # thread, against 123 for a 3 -> 16 -> 8 MLP. 0 = off (runs from before the option).
    pixel_lamp_channels: int = 8
    # Ours: F_DSU's traffic-rule head predicts a correction to the camera-only head's logits
    # (IIDSU.forward: traffic = head(ECA(F_DSU)) + camera_traffic), so that the lamp evidence
    # the camera head finds is the fused head's starting point, not one input among 2C + k that
    # the fused head may overrule with per-town LiDAR context. On the 16k v10 check (6 epochs,
    # one run each) held-out arterial's red-light F1 went from 0.42 (camera-only head 0.66) to
    # 0.63 (0.73). Needs the camera-only head; off without it.
    traffic_residual: bool = True
    # Ours: in training, each frame's F_DSU correction of each traffic output is dropped with
    # this probability (the logit is then the camera head's alone) and kept ones are scaled by
    # 1 / (1 - p), as dropout does; at evaluation it is always kept. It makes the correction
    # pay for its variance, against per-town context the fused head learns on the training
    # towns. 0 = off. On the 16k v10 check (6 epochs, one run each) 0.5 raised held-out
    # arterial's red-light F1 from 0.63 to 0.75 (recall within 5 m of the stop line from 0.16
    # to 0.61 on 800 sampled frames) and stop signs from 0.76 to 0.81.
    traffic_residual_dropout: float = 0.5

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

    @classmethod
    def from_dict(cls, d: dict) -> ModelConfig:
        # Checkpoints from before an option was added were trained without it.
        d = {
            "planner_speed": False,
            "camera_traffic": False,
            "traffic_pool": "avg",
            "lamp_channels": 0,
            "pixel_lamp_channels": 0,
            "traffic_residual": False,
            "traffic_residual_dropout": 0.0,
            **d,
        }
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
    # Ours: camera zoom-out augmentation (training/augment.py). Half the training frames are
    # shrunk about the image centre by a factor uniform in [zoom_out, 1), so that a signal lamp
    # is seen at the sizes other junction widths give (1 or more: off).
    zoom_out: float = 0.55
    zoom_out_probability: float = 0.5
    compile: bool = False  # torch.compile the model (worth it on a GPU, slow to start)
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
    # Ours: weight of the camera-only traffic-rule term (ModelConfig.camera_traffic), as much as
    # the traffic head's own.
    lambda_camera_tf: float = 0.1
    # Cross-entropy weights of the BEV classes (other, drivable, lane marking): ours. Markings
    # are ~8 % of the pixels at R = 64 (3 % at 256; measured on an 8-town build), and with equal
    # weights the tiny model never predicted them on a held-out town (lane IoU 0.00).
    bev_class_weights: tuple[float, ...] = (1.0, 1.0, 3.0)
    # Positive-class weights of L_light and L_sign (BCE pos_weight): ours. A red light governs
    # ~15-25 % of the frames and a stop sign fewer; unweighted, the tiny model's red-light head
    # flipped to "never red" on a held-out town (F1 0.77 at epochs 1 and 3, 0.00 at the end).
    traffic_pos_weight: tuple[float, float] = (3.0, 3.0)
    # Ours: frames where the ego's speed contradicts the traffic label's usual context (red
    # light or stop sign while moving, neither while stopped) weigh this much in L_light and
    # L_sign (losses.context_weights), against the "stopped means red" shortcut; 1 = off.
    traffic_context_weight: float = 1.0  # off: 3 measured worse (held-out red F1 0.33 vs 0.47)
    alpha: float = 1.0
    beta: float = 1.0
    gamma: float = 1.0
    delta: float = 1.0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        # runs from before these options had neither
        d = {"zoom_out": 1.0, "traffic_context_weight": 1.0, "ema_decay": 0.0, **d}
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


PRESETS: dict[str, tuple[ModelConfig, TrainConfig]] = {
    "paper": (ModelConfig(), TrainConfig()),
    # The same model shrunk for CPUs: one block per stage, widths / 4, F_DSU 8x8x128, one
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
