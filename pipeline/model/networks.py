"""Generator and discriminator of the refiner (Choi et al. 2021, section 4.2).

Generator: convolution + batch norm + Leaky ReLU, stride-2 encoder stages, residual blocks at the
bottleneck, and a decoder that up-samples by nearest-neighbour resize followed by a same-size
convolution (no transposed convolution, so no checkerboard). Encoder features are added to the
decoder at each scale (residual skips). The auxiliary depth channels are concatenated with the
normal at the input. Fully convolutional: any size that is a multiple of ``stride`` works. With
``residual`` the output is the input normal plus the decoded correction (no tanh; the head starts
at zero, so an untrained generator returns its input), which trains far faster on little data.

Discriminator: convolution + batch norm + Leaky ReLU stages, a fully connected layer and a
sigmoid (applied inside the loss as BCE-with-logits for numerical stability). It sees the
screen-space normal (the condition) next to a real or generated normal map.
"""

from __future__ import annotations

import torch
from torch import nn


def conv_bn(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    """3x3 convolution, batch norm, Leaky ReLU(0.2)."""
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout),
                         nn.LeakyReLU(0.2, inplace=True))


class ResBlock(nn.Module):
    """x + BN(conv(LReLU(BN(conv(x)))))."""

    def __init__(self, ch: int):
        super().__init__()
        self.body = nn.Sequential(conv_bn(ch, ch), nn.Conv2d(ch, ch, 3, 1, 1, bias=False), nn.BatchNorm2d(ch))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


class Generator(nn.Module):
    """Refines a screen-space normal map (plus optional depth features) into a mesh-like one."""

    def __init__(self, in_channels: int = 5, base_channels: int = 24, downsamples: int = 2, res_blocks: int = 4,
                 residual: bool = False, out_channels: int = 3, residual_at: list[int] | None = None):
        """``residual``: the output is the input's first three channels plus a learnt correction;
        ``residual_at`` = [i, o]: only output channels o..o+2 are input channels i..i+2 plus a
        correction, the others pass through tanh as without it. Either starts as that identity."""
        super().__init__()
        if residual and out_channels != 3:
            raise ValueError("a residual generator returns its input normal: out_channels must be 3")
        self.args = {"in_channels": in_channels, "base_channels": base_channels, "downsamples": downsamples,
                     "res_blocks": res_blocks, "residual": residual, "out_channels": out_channels}
        if residual_at is not None:
            self.args["residual_at"] = list(residual_at)
        self.residual = residual
        self.residual_at = residual_at
        self.stride = 2**downsamples
        ch = [base_channels * 2**k for k in range(downsamples + 1)]
        self.stem = conv_bn(in_channels, ch[0])
        self.down = nn.ModuleList([conv_bn(ch[k], ch[k + 1], stride=2) for k in range(downsamples)])
        self.res = nn.Sequential(*[ResBlock(ch[-1]) for _ in range(res_blocks)])
        self.up = nn.ModuleList([
            nn.Sequential(nn.Upsample(scale_factor=2, mode="nearest"), conv_bn(ch[k + 1], ch[k]))
            for k in reversed(range(downsamples))
        ])
        self.head = nn.Conv2d(ch[0], out_channels, 3, 1, 1)
        if residual or residual_at is not None:  # starts as the identity of the input normal
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)

    def receptive_radius(self) -> int:
        """Pixels beyond which an input cannot change an output pixel (an upper bound).

        Every 3x3 convolution reaches one pixel of its own scale (2^k input pixels at scale k), and
        each nearest-neighbour up-sampling shifts by up to one pixel of the coarser scale."""
        d, b = len(self.down), len(self.res)
        stem_and_head = 2
        encoder = sum(2**k for k in range(d))
        bottleneck = 2 * b * 2**d
        decoder = sum(2**k + 2 ** (k + 1) for k in range(d))
        return stem_and_head + encoder + bottleneck + decoder

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        if h % self.stride or w % self.stride:
            raise ValueError(f"input {h}x{w} is not a multiple of the generator stride {self.stride}")
        skips = [self.stem(x)]
        for down in self.down:
            skips.append(down(skips[-1]))
        y = self.res(skips[-1])
        for up, skip in zip(self.up, reversed(skips[:-1]), strict=True):
            y = up(y) + skip
        if self.residual:
            return x[:, :3] + self.head(y)
        if self.residual_at is not None:
            i, o = self.residual_at
            out = self.head(y)
            t = torch.tanh(out)
            return torch.cat([t[:, :o], x[:, i:i + 3] + out[:, o:o + 3], t[:, o + 3:]], dim=1)
        return torch.tanh(self.head(y))


class Discriminator(nn.Module):
    """Conditional discriminator: (condition normal, candidate normal) -> logit of 'real'."""

    def __init__(self, in_channels: int = 6, base_channels: int = 16, layers: int = 4):
        super().__init__()
        self.args = {"in_channels": in_channels, "base_channels": base_channels, "layers": layers}
        mods: list[nn.Module] = [nn.Conv2d(in_channels, base_channels, 4, 2, 1), nn.LeakyReLU(0.2, inplace=True)]
        ch = base_channels
        for _ in range(layers - 1):
            mods += [nn.Conv2d(ch, ch * 2, 4, 2, 1, bias=False), nn.BatchNorm2d(ch * 2),
                     nn.LeakyReLU(0.2, inplace=True)]
            ch *= 2
        # a fixed 4x4 grid before the fully connected layer, so any crop size works
        mods += [nn.AdaptiveAvgPool2d(4), nn.Flatten(), nn.Linear(ch * 16, 1)]
        self.net = nn.Sequential(*mods)

    def forward(self, condition: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([condition, normal], dim=1)).squeeze(1)


def count_parameters(module: nn.Module) -> int:
    """Trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
