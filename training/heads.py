"""The five heads on the scene feature F_DSU (paper Sec. III-B), one class each.

Every head takes its own ECA-weighted copy of F_DSU, (B, C, h, w) with C = 1024 and h = w = 8
in the paper model, and returns raw outputs (logits, not probabilities): the losses
(training/losses.py) and the decoders (training/targets.py) apply sigmoid / softmax themselves.
"""

from __future__ import annotations

import torch
from torch import nn

DENSITY_CHANNELS = 7
"""Per timestep: 1 heatmap logit + 6 regression channels (dx, dy, log w, log l, sin, cos)."""
DENSITY_TIMESTEPS = 3  # t, t+0.5 s, t+1.0 s


class PlanningHead(nn.Module):
    """Average pool -> 3-layer MLP (C -> 128) -> four cascaded GRU steps -> waypoints.

    As TransFuser's planner: each GRU step is fed the previous waypoint and the target point
    and predicts the next waypoint's offset (the "differential waypoints" of Sec. III-B).

    Args:
        in_dim: channels of F_DSU.
        hidden: GRU state size (the MLP's output).
        n_waypoints: T_future.
        speed: the MLP also reads the measured ego speed (ours, ModelConfig.planner_speed; in
            the paper's model the speed reaches the planner only through TransFuser's velocity
            embedding in the fusion tokens; measured: docs/learning.md).
    """

    def __init__(self, in_dim: int, hidden: int = 128, n_waypoints: int = 4, speed: bool = False):
        super().__init__()
        self.n_waypoints = n_waypoints
        self.speed = speed
        self.mlp = nn.Sequential(
            nn.Linear(in_dim + speed, in_dim // 2),
            nn.ReLU(inplace=True),
            nn.Linear(in_dim // 2, in_dim // 4),
            nn.ReLU(inplace=True),
            nn.Linear(in_dim // 4, hidden),
        )
        self.gru = nn.GRUCell(input_size=4, hidden_size=hidden)  # (waypoint x, y, target x, y)
        self.delta = nn.Linear(hidden, 2)

    def forward(
        self, f: torch.Tensor, target_point: torch.Tensor, speed: torch.Tensor
    ) -> torch.Tensor:
        """f (B, C, h, w), target_point (B, 2) m ego, speed (B,) m/s -> waypoints
        (B, T_future, 2) m ego."""
        x = f.mean(dim=(2, 3))
        if self.speed:  # the measured speed beside the pooled feature (ours, not the paper's)
            x = torch.cat([x, speed[:, None].to(x.dtype)], dim=1)
        h = self.mlp(x)  # (B, hidden)
        wp = f.new_zeros(f.shape[0], 2)  # the ego's own position: the origin
        waypoints = []
        for _ in range(self.n_waypoints):
            h = self.gru(torch.cat([wp, target_point], dim=1), h)
            wp = wp + self.delta(h)
            waypoints.append(wp)
        return torch.stack(waypoints, dim=1)


class UpsamplingDecoder(nn.Sequential):
    """CenterNet's decoder (Zhou et al. 2019): k steps of 4x4 stride-2 transposed conv, BN, ReLU.

    Channels start at `width` and halve each step, down to width / 8.

    Args:
        in_dim: channels of F_DSU.
        steps: number of 2x up-samplings (output side = input side * 2**steps).
        width: channels after the first step.
    """

    def __init__(self, in_dim: int, steps: int, width: int):
        layers, prev = [], in_dim
        for i in range(steps):
            out = max(width >> i, width // 8)
            layers += [
                nn.ConvTranspose2d(prev, out, kernel_size=4, stride=2, padding=1, bias=False),
                nn.BatchNorm2d(out),
                nn.ReLU(inplace=True),
            ]
            prev = out
        super().__init__(*layers)
        self.out_dim = prev


class DensityHead(nn.Module):
    """Object density map O (R x R x 21): decoder, then two 1x1 convs for heatmap and regression.

    Output channel 7 * t + k holds, for timestep t in (t, t+0.5 s, t+1.0 s), k = 0 the heatmap
    logit and k = 1..6 the regression (dx, dy, log w, log l, sin yaw, cos yaw) of an object
    centred in that pixel (encoding in training/targets.py).
    """

    def __init__(self, in_dim: int, steps: int, width: int):
        super().__init__()
        self.decoder = UpsamplingDecoder(in_dim, steps, width)
        self.heatmap = nn.Conv2d(self.decoder.out_dim, DENSITY_TIMESTEPS, kernel_size=1)
        self.regression = nn.Conv2d(
            self.decoder.out_dim, DENSITY_TIMESTEPS * (DENSITY_CHANNELS - 1), kernel_size=1
        )
        # CenterNet's prior: start every pixel at p(object) = 0.1 so the focal loss is stable.
        nn.init.constant_(self.heatmap.bias, -2.19)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        """f (B, C, h, w) -> (B, 21, R, R)."""
        x = self.decoder(f)
        heat = self.heatmap(x)  # (B, 3, R, R)
        reg = self.regression(x)  # (B, 18, R, R)
        B, _, R, _ = heat.shape
        out = torch.cat([heat.unsqueeze(2), reg.view(B, DENSITY_TIMESTEPS, -1, R, R)], dim=2)
        return out.flatten(1, 2)  # (B, 3 * 7, R, R), timestep-major


class BEVHead(nn.Module):
    """BEV map M (R x R x 3): the same decoder, then a 1x1 conv to class logits."""

    def __init__(self, in_dim: int, steps: int, width: int, n_classes: int = 3):
        super().__init__()
        self.decoder = UpsamplingDecoder(in_dim, steps, width)
        self.classify = nn.Conv2d(self.decoder.out_dim, n_classes, kernel_size=1)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        """f (B, C, h, w) -> logits (B, 3, R, R) over (other, drivable, lane marking)."""
        return self.classify(self.decoder(f))


class PooledHead(nn.Module):
    """Pool the (B, C, h, w) map over positions (`pool`, one of training.config.POOLS), then
    one fully connected layer to logits."""

    def __init__(self, in_dim: int, n_out: int, pool: str = "avg"):
        super().__init__()
        self.pool = pool  # ModelConfig checks it
        self.fc = nn.Linear(in_dim * (2 if pool == "avgmax" else 1), n_out)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        """f (B, C, h, w) -> logits (B, n_out)."""
        v = f.mean(dim=(2, 3))
        if self.pool == "avgmax":
            v = torch.cat([v, f.amax(dim=(2, 3))], dim=1)
        return self.fc(v)


class TrafficRuleHead(PooledHead):
    """Two independent sigmoid outputs (multi-label): red light ahead, stop sign ahead.

    "Red light" is the shards' `traffic_light == "red"`; a yellow light counts as not red.
    The paper says only that "the feature is reduced to 1024 dimensions" (Sec. III-B); with
    `pool="avgmax"` (ours, `ModelConfig.traffic_pool`) the maximum over positions sits beside
    the mean, so that a lamp or sign filling one of the 8x8 cells is not averaged away.
    """

    def __init__(self, in_dim: int, pool: str = "avg"):
        super().__init__(in_dim, 2, pool)


class WeatherHead(PooledHead):
    """Softmax over the four weathers, in `schemas.WEATHERS` order."""

    def __init__(self, in_dim: int):
        super().__init__(in_dim, 4)
