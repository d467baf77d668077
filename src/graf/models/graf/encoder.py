"""ResNet-18 feature extractor of a neighbor's spatial spectrum (supplement D), in plain torch.

``[N, 1, 90, 360]`` (or ``[N, 90, 360]``) -> ``[N, widths[-1]]``: optional ``downsample`` x
``downsample`` average pooling, stem conv 7x7 stride 2 + max-pool 3x3 stride 2, four stages of two
BasicBlocks (stride 1, 2, 2, 2; channel widths ``widths``), global average pooling.

Normalisation: GroupNorm instead of ResNet's BatchNorm.  A spectrum's feature then depends on that
spectrum alone: not on which other neighbors (or how many, L varies per target) share the batch, not on
train/eval mode, and not on how inference is chunked.  Groups: ``gcd(C, 32)`` but at least two channels
per group (32 groups from 64 channels up, 8 groups of 2 at 16 channels).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn


def group_norm(channels: int) -> nn.GroupNorm:
    groups = math.gcd(channels, min(32, max(1, channels // 2)))
    return nn.GroupNorm(groups, channels)


class BasicBlock(nn.Module):
    """ResNet's basic block (two 3x3 convolutions and a shortcut) with group norm instead of batch norm: a
    batch of a few targets' neighbors is too small for batch statistics."""

    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.norm1 = group_norm(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.norm2 = group_norm(cout)
        self.shortcut = None
        if stride != 1 or cin != cout:
            self.shortcut = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), group_norm(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.norm1(self.conv1(x)))
        y = self.norm2(self.conv2(y))
        return F.relu(y + (x if self.shortcut is None else self.shortcut(x)))


class ResNetEncoder(nn.Module):
    """ResNet-18 (2 BasicBlocks per stage) with GroupNorm; ``out_dim == widths[-1]``."""

    def __init__(
        self,
        widths: Sequence[int] = (64, 128, 256, 512),
        in_channels: int = 1,
        downsample: int = 1,
        blocks_per_stage: int = 2,
    ):
        super().__init__()
        widths = [int(w) for w in widths]
        if not widths or downsample < 1:
            raise ValueError(f"need at least one stage and downsample >= 1, got {widths}, {downsample}")
        self.in_channels, self.downsample, self.out_dim = int(in_channels), int(downsample), widths[-1]
        self.stem = nn.Sequential(
            nn.Conv2d(self.in_channels, widths[0], 7, 2, 3, bias=False),
            group_norm(widths[0]),
            nn.ReLU(inplace=True),
            nn.MaxPool2d(3, 2, 1),
        )
        stages, cin = [], widths[0]
        for i, w in enumerate(widths):
            blocks = [BasicBlock(cin, w, 1 if i == 0 else 2)]
            blocks += [BasicBlock(w, w) for _ in range(blocks_per_stage - 1)]
            stages.append(nn.Sequential(*blocks))
            cin = w
        self.stages = nn.Sequential(*stages)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
        for m in self.modules():  # zero-init each block's last norm: blocks start as identities (Goyal et al.)
            if isinstance(m, BasicBlock):
                nn.init.zeros_(m.norm2.weight)

    def forward_map(self, x: torch.Tensor) -> torch.Tensor:
        """The feature map before pooling, ``[N, widths[-1], h, w]`` (3 x 12 from 90 x 360 at stride 32):
        ray-aligned features sample it at each ray's direction."""
        if x.dim() == 3:
            x = x.unsqueeze(1)
        if self.downsample > 1:
            x = F.avg_pool2d(x, self.downsample, ceil_mode=True)
        return self.stages(self.stem(x))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.forward_map(x).mean(dim=(-2, -1))
