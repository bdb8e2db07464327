"""Additions of ours for the traffic-rule task, attached to the paper's model at named points
(training/model.py `IIDSU`); none is in the paper, each is off in its model (training/config.py).

A signal lamp is 1.5-3 px wide in the paper's camera (400x300, 100 degrees, 256 crop); after
the encoder's stride of 32 it shares one cell of F_DSU's 8x8 grid with its whole surround, and
the tiny model learnt "red light" from LiDAR context (standing at a junction) rather than from
the lamps (docs/learning.md). The additions let the lamps reach the traffic-rule output:

- `LampMaps` (ModelConfig.lamp_channels, pixel_lamp_channels): maps from the camera's first
  stage (stride 4, before any fusion) and from per-pixel colour detectors on the image, each
  max-pooled to F_DSU's grid; attached where F_DSU is made (concatenated into its 1x1 conv).
- `CameraTrafficHead` (ModelConfig.camera_traffic): the traffic rule from the camera alone (the
  lamp maps; without them, camera stages 2-4 run again on the unfused first stage); attached
  beside the heads as a second training signal (TrainConfig.lambda_camera_tf).
- `traffic_residual` (ModelConfig.traffic_residual, traffic_residual_dropout): F_DSU's traffic
  head predicts a correction added to the camera-only head's logits, dropped at random in
  training; attached to the traffic head's output.

The other additions are options of the paper's parts: ModelConfig.planner_speed
(heads.PlanningHead), ModelConfig.traffic_pool (heads.PooledHead) and TrainConfig.zoom_out
(training/augment.py).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from training.heads import TrafficRuleHead


class LampMaps(nn.Module):
    """Signal-lamp maps at F_DSU's grid: (B, stage_channels + pixel_channels, g, g).

    Args:
        stage_dim: channels of the camera's first stage (ModelConfig.dims[0]).
        stage_channels: maps from a 1x1 conv on that stage (stride 4); 0 = none.
        pixel_channels: maps from a 1x1 conv and GELU on the normalised image (stride 1, each
            pixel's colour judged before any stride mixes a lamp with its surround); 0 = none.
        grid: side of F_DSU's grid (ModelConfig.feature_px); every map is max-pooled to it.
    """

    def __init__(self, stage_dim: int, stage_channels: int, pixel_channels: int, grid: int):
        super().__init__()
        self.grid = grid
        self.channels = stage_channels + pixel_channels
        self.stage = nn.Conv2d(stage_dim, stage_channels, 1) if stage_channels else None
        self.pixel = None
        if pixel_channels:
            self.pixel = nn.Sequential(nn.Conv2d(3, pixel_channels, 1), nn.GELU())

    def forward(self, image: torch.Tensor, first_stage: torch.Tensor) -> torch.Tensor:
        """image (B, 3, H, W) normalised; first_stage (B, dims[0], H / 4, W / 4), the camera's
        first stage before fusion -> (B, channels, g, g): the stage maps, then the pixel maps."""
        maps = (
            []
            if self.stage is None
            else [F.adaptive_max_pool2d(self.stage(first_stage), self.grid)]
        )
        maps += [] if self.pixel is None else [pooled_pixel_lamps(self.pixel, image, self.grid)]
        return torch.cat(maps, dim=1)


def pooled_pixel_lamps(pixel_lamp: nn.Sequential, x: torch.Tensor, px: int) -> torch.Tensor:
    """`adaptive_max_pool2d(pixel_lamp(x), px)` for `pixel_lamp` = (1x1 Conv2d, GELU), without
    the full-resolution GELU and its backward (tiny config, one thread: 12 against 32 ms of CPU
    a training step, docs/speed.md).

    GELU falls, then rises (one minimum, at -0.75), so its maximum over a cell is at the
    cell's largest or smallest conv output: the pooled maps are GELU of those two, the larger
    one. The conv runs once without autograd to find them; their values are recomputed from
    the input pixels they come from, so the gradient reaches the conv's weights through the
    pixel each cell selects, as the max-pool's does.

    Args:
        x: (B, 3, H, W) float, the normalised camera image (needs no gradient).
        px: side of the pooled maps; divides H and W.
    Returns:
        (B, k, px, px), k = the conv's output channels.
    """
    conv = pixel_lamp[0]
    B, C, H, W = x.shape
    k = conv.out_channels
    weight = conv.weight.view(k, C)
    chunk = max(1, (16 << 20) // (2 * k * H * W * x.element_size()))  # outputs <= 16 MB
    with torch.no_grad():  # flat indices of the cells' largest z and largest -z, one conv
        both = torch.cat([weight, -weight]).view(2 * k, C, 1, 1)
        index = torch.cat(
            [
                F.adaptive_max_pool2d(F.conv2d(part, both), px, return_indices=True)[1]
                for part in x.split(chunk)
            ]
        )  # (B, 2k, px, px)
    index = index.reshape(B, 2 * k * px * px, 1).expand(B, -1, C)
    pixels = x.permute(0, 2, 3, 1).reshape(B, H * W, C)  # a view of channels_last memory
    chosen = torch.gather(pixels, 1, index).view(B, 2, k, px, px, C)  # the cells' pixels
    z = (chosen * weight.view(1, 1, k, 1, 1, C)).sum(-1) + conv.bias.view(1, 1, k, 1, 1)
    lamps = pixel_lamp[1](z)  # (B, 2, k, px, px): GELU at the largest and the smallest
    return torch.maximum(lamps[:, 0], lamps[:, 1])


class CameraTrafficHead(TrafficRuleHead):
    """Red light and stop sign from the camera alone (B, 2) logits: no LiDAR and no speed reach
    it (the fusion layers carry both). It reads the lamp maps when the model has them, else the
    camera's unfused first stage run through camera stages 2-4 a second time.

    Args:
        in_dim: channels it reads (the lamp maps', else the camera's last stage's).
        pool: ModelConfig.traffic_pool.
    """

    def forward(
        self,
        lamps: torch.Tensor | None,
        first_stage: torch.Tensor,
        stages: nn.ModuleList,
    ) -> torch.Tensor:
        """lamps (B, k, g, g) or None; first_stage (B, dims[0], H / 4, W / 4) unfused; stages
        the camera encoder's -> (B, 2) logits."""
        x = lamps
        if x is None:
            x = first_stage
            for stage in stages[1:]:
                x = stage(x)  # (B, dims[-1], H / 32, W / 32)
        return super().forward(x)


def traffic_residual(
    fused: torch.Tensor, camera: torch.Tensor, dropout: float, training: bool
) -> torch.Tensor:
    """The traffic logits (B, 2): the camera-only head's plus F_DSU's head's as a correction,
    so that the lamps the camera head finds are the starting point rather than one input that
    per-town LiDAR context can overrule. In training each correction is dropped with
    probability `dropout` (the logit is then the camera head's alone), kept ones scaled by
    1 / (1 - dropout)."""
    return F.dropout(fused, dropout, training) + camera


def rename_old_keys(state_dict: dict, prefix: str) -> None:
    """In place: a state dict saved before the additions moved here (keys `lamp.*`,
    `pixel_lamp.*` on IIDSU) gets today's keys (`lamps.stage.*`, `lamps.pixel.*`)."""
    for old, new in (("lamp.", "lamps.stage."), ("pixel_lamp.", "lamps.pixel.")):
        for key in [k for k in state_dict if k.startswith(prefix + old)]:
            state_dict[prefix + new + key[len(prefix + old) :]] = state_dict.pop(key)
