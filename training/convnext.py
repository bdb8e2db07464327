"""ConvNeXt (Liu et al., "A ConvNet for the 2020s", CVPR 2022): the encoder of both branches.

Written here rather than imported from timm, against the project's rule 8, because timm cannot
be imported beside this disk's torch: timm 1.0.31 imports torchvision at import time, and the
torchvision wheel pip resolves from PyPI (0.29.1) fails beside torch 2.13.0+cpu with
`RuntimeError: operator torchvision::nms does not exist` (measured). The module layout follows
timm's `convnext.py` so swapping timm back in is a local change: `ConvNeXtBlock` (one residual
unit), `ConvNeXtStage` (down-sampling + blocks), `ConvNeXt` (stem + stages, `feature_info`).

II-DSU interleaves the two encoders with fusion layers (training/model.py), so `ConvNeXt` has
no classifier head and exposes its stem and stages; `forward_features` runs them alone.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class LayerNorm2d(nn.LayerNorm):
    """LayerNorm over the channels of a (B, C, H, W) map."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x.permute(0, 2, 3, 1)  # (B, H, W, C)
        x = F.layer_norm(x, self.normalized_shape, self.weight, self.bias, self.eps)
        return x.permute(0, 3, 1, 2)


class DropPath(nn.Module):
    """Stochastic depth: zero a residual branch for a random subset of samples in training."""

    def __init__(self, p: float):
        super().__init__()
        self.p = p

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.training or self.p == 0.0:
            return x
        keep = x.new_empty((x.shape[0],) + (1,) * (x.ndim - 1)).bernoulli_(1.0 - self.p)
        return x * keep / (1.0 - self.p)


class ConvNeXtBlock(nn.Module):
    """x + drop_path(gamma * MLP(LayerNorm(DwConv7x7(x)))).

    Two equivalent implementations exist (timm offers both): (1) DwConv -> LayerNorm2d ->
    1x1 Conv -> GELU -> 1x1 Conv, all channels-first; (2) DwConv -> permute -> LayerNorm ->
    Linear -> GELU -> Linear -> permute. We use (1): measured on the 2-core CPU of our CI
    (forward + backward, batch 8, channels_last), 46 ms against 72 ms at 64 channels on 64x64
    and 23 ms against 39 ms at 256 channels on 16x16; it also keeps channels_last end to end.

    Args:
        dim: channels in and out.
        drop_path: probability of dropping the residual branch (stochastic depth).
        layer_scale_init: initial value of the per-channel scale gamma (ConvNeXt: 1e-6).
    """

    def __init__(self, dim: int, drop_path: float = 0.0, layer_scale_init: float = 1e-6):
        super().__init__()
        self.dwconv = nn.Conv2d(dim, dim, kernel_size=7, padding=3, groups=dim)
        self.norm = LayerNorm2d(dim, eps=1e-6)
        self.fc1 = nn.Conv2d(dim, 4 * dim, kernel_size=1)  # inverted bottleneck, ratio 4
        self.act = nn.GELU()
        self.fc2 = nn.Conv2d(4 * dim, dim, kernel_size=1)
        self.gamma = nn.Parameter(torch.full((dim, 1, 1), layer_scale_init))
        self.drop_path = DropPath(drop_path) if drop_path > 0 else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, C, H, W) -> same
        y = self.fc2(self.act(self.fc1(self.norm(self.dwconv(x)))))
        return x + self.drop_path(self.gamma * y)


class ConvNeXtStage(nn.Module):
    """Down-sampling (LayerNorm2d + 2x2 stride-2 conv, or nothing) then `depth` blocks.

    Args:
        in_dim, out_dim: channels before and after the stage.
        depth: number of ConvNeXt blocks.
        downsample: halve the resolution first (every stage but the first).
        drop_paths: stochastic depth per block, length `depth`.
    """

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        depth: int,
        downsample: bool,
        drop_paths: list[float],
        layer_scale_init: float = 1e-6,
    ):
        super().__init__()
        if downsample:
            self.downsample = nn.Sequential(
                LayerNorm2d(in_dim, eps=1e-6), nn.Conv2d(in_dim, out_dim, kernel_size=2, stride=2)
            )
        else:
            self.downsample = nn.Identity()
        self.blocks = nn.Sequential(
            *(ConvNeXtBlock(out_dim, drop_paths[i], layer_scale_init) for i in range(depth))
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.blocks(self.downsample(x))


class ConvNeXt(nn.Module):
    """Stem (4x4 stride-4 conv + LayerNorm2d) and four stages: /4, /2, /2, /2 (paper Sec. III-B).

    Args:
        in_chans: input channels (3 for the camera, 4 or 2 for the LiDAR BEV).
        depths: blocks per stage; ConvNeXt-Tiny is (3, 3, 9, 3).
        dims: channels per stage; the paper uses (64, 128, 256, 512).
        drop_path: stochastic depth of the last block, rising linearly from 0 at the first.
        layer_scale_init: initial layer scale.

    Attributes:
        feature_info: per stage, `dict(num_chs=C, reduction=stride)` relative to the input.
    """

    def __init__(
        self,
        in_chans: int,
        depths: tuple[int, ...] = (3, 3, 9, 3),
        dims: tuple[int, ...] = (64, 128, 256, 512),
        drop_path: float = 0.0,
        layer_scale_init: float = 1e-6,
    ):
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(in_chans, dims[0], kernel_size=4, stride=4), LayerNorm2d(dims[0], eps=1e-6)
        )
        n = sum(depths)
        rates = [drop_path * i / max(n - 1, 1) for i in range(n)]  # linear, 0 at the first
        self.stages = nn.ModuleList()
        self.feature_info = []
        start, prev = 0, dims[0]
        for i, (depth, dim) in enumerate(zip(depths, dims)):
            self.stages.append(
                ConvNeXtStage(
                    prev, dim, depth, i > 0, rates[start : start + depth], layer_scale_init
                )
            )
            self.feature_info.append(dict(num_chs=dim, reduction=4 * 2**i))
            start, prev = start + depth, dim
        self.apply(_init_weights)

    def forward_features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """(B, in_chans, H, W) -> one (B, dims[i], H / 4 / 2**i, W / 4 / 2**i) map per stage."""
        features = []
        x = self.stem(x)
        for stage in self.stages:
            x = stage(x)
            features.append(x)
        return features


def _init_weights(module: nn.Module) -> None:
    """ConvNeXt's init: truncated normal (std 0.02) weights, zero biases, for convs and linears."""
    if isinstance(module, nn.Conv2d | nn.Linear):
        nn.init.trunc_normal_(module.weight, std=0.02)
        if module.bias is not None:
            nn.init.zeros_(module.bias)
