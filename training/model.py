"""II-DSU (paper Sec. III-B): two ConvNeXt encoders fused by TransFuser layers into the scene
feature F_DSU, one ECA module per head, and five heads.

    image (B,3,256,256) --ConvNeXt stage i--\\            /--> ECA --> planning  (B,4,2)
                                             fusion i x4 -- cat, 1x1 --> F_DSU (B,1024,8,8) ...
    lidar (B,4,256,256) --ConvNeXt stage i--/             \\--> ECA --> detection (B,21,R,R),
                                                                      bev (B,3,R,R),
                                                                      traffic (B,2), weather (B,4)

That is the paper's model (ModelConfig's defaults). The additions of ours live in
training/lamps.py and attach at two named points of `IIDSU`: lamp maps concatenated where F_DSU
is made (`IIDSU.lamps`), and a camera-only traffic head whose logits F_DSU's traffic head
corrects (`IIDSU.camera_traffic`).

    >>> from training.config import PRESETS
    >>> model = IIDSU(PRESETS["tiny"][0])
    >>> out = model(image, lidar, speed, target_point)   # dict: head name -> raw output
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from training.config import ModelConfig
from training.convnext import ConvNeXt
from training.heads import (
    BEVHead,
    DensityHead,
    PlanningHead,
    TrafficRuleHead,
    WeatherHead,
)
from training.lamps import CameraTrafficHead, LampMaps, rename_old_keys, traffic_residual

INPUTS = ("image", "lidar", "speed", "target_point")
"""Batch keys the model reads, in `IIDSU.forward`'s argument order."""

IMAGENET_MEAN = (0.485, 0.456, 0.406)  # the camera is normalised as for ImageNet training
IMAGENET_STD = (0.229, 0.224, 0.225)


class SelfAttention(nn.Module):
    """Multi-head self-attention over a token sequence (B, T, C)."""

    def __init__(self, dim: int, n_heads: int):
        super().__init__()
        self.n_heads = n_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, T, C = x.shape
        q, k, v = self.qkv(x).split(C, dim=2)
        q, k, v = (z.view(B, T, self.n_heads, C // self.n_heads).transpose(1, 2) for z in (q, k, v))
        y = F.scaled_dot_product_attention(q, k, v)  # (B, nh, T, hs)
        return self.proj(y.transpose(1, 2).reshape(B, T, C))


class Block(nn.Module):
    """Pre-norm transformer block: x + attn(ln(x)), then x + mlp(ln(x))."""

    def __init__(self, dim: int, n_heads: int):
        super().__init__()
        self.ln_1 = nn.LayerNorm(dim)
        self.attn = SelfAttention(dim, n_heads)
        self.ln_2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.ln_1(x))
        return x + self.mlp(self.ln_2(x))


class TransFuserLayer(nn.Module):
    """One fusion layer (TransFuser, Prakash et al. 2021; the paper's Fig. 2).

    Both feature maps are cut into an n x n grid of equal patches, each patch averaged into a
    token; the 2 n^2 tokens get learned position embeddings and a velocity embedding, pass
    through self-attention blocks, and each branch's tokens are up-sampled back to its map and
    added to it. Averaging patches is exactly `adaptive_avg_pool2d` to n x n (TransFuser's
    "anchors"); the alternative, one token per pixel, would give 2 * 64 * 64 = 8192 tokens at
    the first stage (attention memory ~ 8192^2 per head), so tokens are pooled at every stage
    and the grid is the last stage's own 8x8 map.

    Args:
        dim: channels of both feature maps at this stage.
        n_tokens: token grid side per modality.
        n_blocks, n_heads: attention blocks and heads.
    """

    def __init__(self, dim: int, n_tokens: int = 8, n_blocks: int = 8, n_heads: int = 4):
        super().__init__()
        self.n_tokens = n_tokens
        self.pos_emb = nn.Parameter(torch.zeros(1, 2 * n_tokens**2, dim))
        self.vel_emb = nn.Linear(1, dim)
        self.blocks = nn.Sequential(*(Block(dim, n_heads) for _ in range(n_blocks)))
        self.ln_f = nn.LayerNorm(dim)

    def forward(
        self, image: torch.Tensor, lidar: torch.Tensor, speed: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """image, lidar (B, C, H, W); speed (B,) m/s -> both maps with the fused tokens added."""
        n = self.n_tokens
        tokens = [F.adaptive_avg_pool2d(m, n).flatten(2).transpose(1, 2) for m in (image, lidar)]
        x = torch.cat(tokens, dim=1)  # (B, 2 n^2, C)
        x = x + self.pos_emb + self.vel_emb(speed[:, None]).unsqueeze(1)
        x = self.ln_f(self.blocks(x))
        fused = []
        for m, t in zip((image, lidar), x.split(n * n, dim=1)):
            t = t.transpose(1, 2).reshape(m.shape[0], m.shape[1], n, n)  # (B, C, n, n)
            fused.append(m + F.interpolate(t, size=m.shape[2:], mode="bilinear"))
        return fused[0], fused[1]


class ECA(nn.Module):
    """Efficient channel attention (Wang et al. 2020): global average pooling, a 1-D conv across
    channels, a sigmoid; the result re-weights the channels of F_DSU for one head.

    Kernel size k follows ECA's adaptive rule, k = |(log2 C + 1) / 2| rounded to odd: k = 5 for
    both C = 1024 (paper) and C = 128 (tiny). ECA's other option, a fixed k = 3, would see less
    of the channel neighbourhood for no saving worth having (k weights per module either way).
    """

    def __init__(self, channels: int):
        super().__init__()
        k = int(abs((math.log2(channels) + 1) / 2))
        k = k if k % 2 else k + 1
        self.conv = nn.Conv1d(1, 1, kernel_size=k, padding=k // 2, bias=False)

    def weights(self, f: torch.Tensor) -> torch.Tensor:
        """f (B, C, h, w) -> channel weights (B, C) in (0, 1) (what `train analyze` compares)."""
        y = f.mean(dim=(2, 3)).unsqueeze(1)  # (B, 1, C)
        return torch.sigmoid(self.conv(y)).squeeze(1)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        return f * self.weights(f)[:, :, None, None]


class IIDSU(nn.Module):
    """The whole model. `forward` returns a dict with one raw output per head in `cfg.heads`.

    LiDAR input (Sec. III-A): the shards' ch0 (at-ground hits summed over t, t-1, t-2) and
    ch1..3 (above-ground hits at t, t-1, t-2). With `single_frame_lidar` (Table III's "No
    Multi-frame LiDAR") it is the current sweep only: the `lidar_ground_t` column (ground hits
    at t) and ch1, as the loader builds it (training/data.py `_sample`).

    Additions of ours (training/lamps.py; None in the paper's model) attach at two points: the
    lamp maps (`lamps`) where F_DSU is made, and the camera-only traffic head
    (`camera_traffic`) with its residual on the traffic output.
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.image_encoder = ConvNeXt(3, cfg.depths, cfg.dims, cfg.drop_path, cfg.layer_scale_init)
        self.lidar_encoder = ConvNeXt(
            cfg.lidar_in_channels, cfg.depths, cfg.dims, cfg.drop_path, cfg.layer_scale_init
        )
        self.fusion = nn.ModuleList(
            TransFuserLayer(d, cfg.fusion_tokens, cfg.fusion_blocks, cfg.fusion_heads)
            for d in cfg.dims
        )
        self.lamps = None  # ours: signal-lamp maps into F_DSU
        if cfg.lamp_channels or cfg.pixel_lamp_channels:
            self.lamps = LampMaps(
                cfg.dims[0], cfg.lamp_channels, cfg.pixel_lamp_channels, cfg.feature_px
            )
        k = self.lamps.channels if self.lamps is not None else 0
        self.to_dsu = nn.Conv2d(2 * cfg.dims[-1] + k, cfg.feature_dim, kernel_size=1)
        self.eca = nn.ModuleDict({name: ECA(cfg.feature_dim) for name in cfg.heads})
        steps = int(math.log2(cfg.output_px // cfg.feature_px))
        C = cfg.feature_dim
        make = {
            "planning": lambda: PlanningHead(
                C, cfg.planner_hidden, cfg.n_waypoints, cfg.planner_speed
            ),
            "detection": lambda: DensityHead(C, steps, cfg.decoder_width),
            "bev": lambda: BEVHead(C, steps, cfg.decoder_width),
            "traffic": lambda: TrafficRuleHead(C, cfg.traffic_pool),
            "weather": lambda: WeatherHead(C),
        }
        self.heads = nn.ModuleDict({name: make[name]() for name in cfg.heads})
        self.camera_traffic = None  # ours: the traffic rule from the camera alone
        if cfg.has_camera_traffic:
            self.camera_traffic = CameraTrafficHead(k or cfg.dims[-1], cfg.traffic_pool)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), False)
        self.register_load_state_dict_pre_hook(
            lambda module, state, prefix, *_: rename_old_keys(state, prefix)
        )

    def encode(self, image: torch.Tensor, lidar: torch.Tensor, speed: torch.Tensor) -> torch.Tensor:
        """The scene feature F_DSU.

        Args:
            image: (B, 3, H, W) uint8 RGB camera crop.
            lidar: (B, 4, H, W) uint8 LiDAR BEV counts, ch0..ch3 of the shards; (B, 2, H, W)
                (ground and above-ground hits at t) for a single-frame model.
            speed: (B,) float32 ego speed, m/s.
        Returns:
            (B, feature_dim, H / 32, W / 32) float.
        """
        return self._encode(image, lidar, speed)[0]

    def _speed(self, speed: torch.Tensor) -> torch.Tensor:
        """The speed the model reads: as measured, or 0 without `cfg.speed_input` (ours)."""
        return speed if self.cfg.speed_input else torch.zeros_like(speed)

    def _encode(
        self, image: torch.Tensor, lidar: torch.Tensor, speed: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """F_DSU (the paper's architecture figure: two encoders, a TransFuser layer after each
        stage, the last stages concatenated into a 1x1 conv), the lamp maps (ours; None without
        them) and the camera's first stage before any fusion (what ours read)."""
        if lidar.shape[1] != self.cfg.lidar_in_channels:  # e.g. 4 summed channels, 2 wanted
            raise ValueError(
                f"LiDAR input has {lidar.shape[1]} channels; this model takes "
                f"{self.cfg.lidar_in_channels} (single_frame_lidar={self.cfg.single_frame_lidar})"
            )
        speed = self._speed(speed)
        image = (image.float() / 255.0 - self.mean) / self.std
        clip = self.cfg.lidar_clip_count
        x_img = self.image_encoder.stem(image)  # (B, dims[0], H / 4, W / 4)
        x_lid = self.lidar_encoder.stem(lidar.float().clamp(max=clip) / clip)
        stages = zip(self.image_encoder.stages, self.lidar_encoder.stages, self.fusion)
        for k, (img_stage, lid_stage, fuse) in enumerate(stages):
            x_img, x_lid = img_stage(x_img), lid_stage(x_lid)
            if k == 0:
                first_stage = x_img  # the camera's first stage, unfused (ours read it)
            x_img, x_lid = fuse(x_img, x_lid, speed)  # (B, dims[k], H / 2**(k+2), ...) each
        maps = [x_img, x_lid]  # (B, dims[-1], H / 32, W / 32) each
        lamps = None if self.lamps is None else self.lamps(image, first_stage)  # ours
        maps += [] if lamps is None else [lamps]  # (B, k, H / 32, W / 32)
        return self.to_dsu(torch.cat(maps, dim=1)), lamps, first_stage  # F_DSU (B, 1024, 8, 8)

    def forward(
        self,
        image: torch.Tensor,
        lidar: torch.Tensor,
        speed: torch.Tensor,
        target_point: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        """Inputs as in `encode`, plus target_point (B, 2) float32, m, ego frame.

        Returns raw head outputs: planning (B, 4, 2) waypoints in m (ego frame); detection
        (B, 21, R, R); bev (B, 3, R, R) logits; traffic (B, 2) logits; weather (B, 4) logits.
        Ours, with `cfg.camera_traffic`: camera_traffic (B, 2) logits of the camera alone (a
        training signal that makes the camera branch find the lamps and signs itself), and with
        `cfg.traffic_residual` the traffic logits are F_DSU's head's plus camera_traffic's.
        """
        f, lamps, first_stage = self._encode(image, lidar, speed)
        out = {}
        for name, head in self.heads.items():
            f_head = self.eca[name](f)  # ECA: this head's channel weights on F_DSU
            if name == "planning":
                out[name] = head(f_head, target_point, self._speed(speed))
            else:
                out[name] = head(f_head)
        if self.camera_traffic is not None:  # ours (training/lamps.py)
            camera = self.camera_traffic(lamps, first_stage, self.image_encoder.stages)
            out["camera_traffic"] = camera
            if self.cfg.has_traffic_residual:
                p = self.cfg.traffic_residual_dropout
                out["traffic"] = traffic_residual(out["traffic"], camera, p, self.training)
        return out

    def plan(
        self,
        image: torch.Tensor,
        lidar: torch.Tensor,
        speed: torch.Tensor,
        target_point: torch.Tensor,
    ) -> torch.Tensor:
        """The planning output alone, (B, T_future, 2) waypoints in m (ego frame): what driving
        needs, without the dense heads' cost. Inputs as in `forward`."""
        f = self.encode(image, lidar, speed)
        return self.heads["planning"](self.eca["planning"](f), target_point, self._speed(speed))
