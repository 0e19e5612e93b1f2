"""The pix2pix networks and losses of the metaball system (Horvath 2019, section 5.3, after Isola et
al., "Image-to-Image Translation with Conditional Adversarial Networks", CVPR 2017, as ported to
TensorFlow by affinelayer/pix2pix-tensorflow, which the thesis builds on).

Generator: a U-Net of 8 encoders (4x4 convolutions, stride 2, channels 1, 2, 4, 8, 8, 8, 8, 8 times
``base_channels``, Leaky ReLU 0.2) and 8 decoders (ReLU, then an up-sampling convolution to 8, 8, 8,
8, 4, 2, 1 times ``base_channels`` and finally 7 channels; dropout 0.5 after the first three), each
decoder after the first reading its predecessor concatenated with the mirror encoder; tanh output.
The thesis' table lists the decoders' sizes after that concatenation (512, ..., 64 at 32 base
channels). Batch norm follows every convolution but the first encoder's, the innermost encoder's
and the last decoder's (pix2pix-tensorflow normalises the innermost one too; on its 1 x 1 output at
256 x 256 with one image per batch that is undefined, so we follow the PyTorch pix2pix there).

Discriminator: on the 4 input channels concatenated with 7 real or generated ones, 8x8 convolutions
(padded by 1) to 1, 2, 4, 8 times ``base_channels`` and then 1 channel, with strides 2, 2, 2, 1, 1,
Leaky ReLU 0.2, batch norm on the middle three, and a sigmoid: a patch map of 50 x 50 at 512 x 512
(the thesis' table 5.3; the layer before the last has stride 1 too, as in pix2pix).

With the thesis' widths (32 and 64) the pair has 24,706,248 parameters: its stated 24,706,760 less
the 512 of the innermost batch norm. The generator alone has 13,615,623 (54.5 MB in float32); the
default of 16 base channels has 3,408,135 (13.6 MB), under the project's 20 MB limit for shipped
weights.
"""

from __future__ import annotations

import torch
from torch import nn

EPS = 1e-12
"""Added inside the logarithms of the losses, as pix2pix-tensorflow does."""

ENCODER_WIDTHS = (1, 2, 4, 8, 8, 8, 8, 8)
"""Output channels of the 8 encoders in multiples of ``base_channels``."""

DECODER_WIDTHS = (8, 8, 8, 8, 4, 2, 1)
"""Output channels of the decoders before the last (innermost first) in multiples of ``base_channels``."""

DROPOUT_DECODERS = 3
"""Decoders (innermost first) followed by dropout."""

PAPER_GENERATOR = {"in_channels": 4, "out_channels": 7, "base_channels": 32, "upsample": "transpose"}
"""The thesis' generator arguments."""

PAPER_DISCRIMINATOR = {"in_channels": 11, "base_channels": 64, "kernel_size": 8}
"""The thesis' discriminator arguments."""


def init_weights(module: nn.Module) -> None:
    """pix2pix initialisation: convolution weights from N(0, 0.02), biases 0, batch-norm scales from N(1, 0.02)."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            nn.init.normal_(m.weight, 0.0, 0.02)
            nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.normal_(m.weight, 1.0, 0.02)
            nn.init.zeros_(m.bias)


def up_convolution(cin: int, cout: int, upsample: str) -> nn.Module:
    """Double the size: the thesis' 4x4 stride-2 transposed convolution, or a nearest-neighbour resize
    then a 3x3 convolution, which cannot leave the checkerboard of uneven kernel overlap."""
    if upsample == "transpose":
        return nn.ConvTranspose2d(cin, cout, 4, 2, 1)
    if upsample == "resize":
        return nn.Sequential(nn.Upsample(scale_factor=2, mode="nearest"), nn.Conv2d(cin, cout, 3, 1, 1))
    raise ValueError(f"upsample must be 'transpose' or 'resize', got {upsample!r}")


class UNetGenerator(nn.Module):
    """pix2pix U-Net: circle image (4 channels in [-1, 1]) to colour, depth and normal (7 channels, tanh)."""

    def __init__(self, in_channels: int = 4, out_channels: int = 7, base_channels: int = 16,
                 upsample: str = "transpose", dropout: float = 0.5):
        super().__init__()
        self.args = {"in_channels": in_channels, "out_channels": out_channels, "base_channels": base_channels,
                     "upsample": upsample, "dropout": dropout}
        enc = [base_channels * m for m in ENCODER_WIDTHS]
        self.stride = 2 ** len(enc)
        self.encoders = nn.ModuleList()
        for k, cout in enumerate(enc):
            layers: list[nn.Module] = [] if k == 0 else [nn.LeakyReLU(0.2)]
            layers.append(nn.Conv2d(in_channels if k == 0 else enc[k - 1], cout, 4, 2, 1))
            if 0 < k < len(enc) - 1:
                layers.append(nn.BatchNorm2d(cout))
            self.encoders.append(nn.Sequential(*layers))
        self.decoders = nn.ModuleList()
        cin = enc[-1]
        for k, mult in enumerate(DECODER_WIDTHS):
            cout = base_channels * mult
            layers = [nn.ReLU(), up_convolution(cin, cout, upsample), nn.BatchNorm2d(cout)]
            if k < DROPOUT_DECODERS and dropout > 0:
                layers.append(nn.Dropout(dropout))
            self.decoders.append(nn.Sequential(*layers))
            cin = cout + enc[-2 - k]
        self.decoders.append(nn.Sequential(nn.ReLU(), up_convolution(cin, out_channels, upsample), nn.Tanh()))
        init_weights(self)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        if h % self.stride or w % self.stride:
            raise ValueError(f"input {h}x{w} is not a multiple of the generator stride {self.stride}")
        skips = []
        for encoder in self.encoders:
            x = encoder(x)
            skips.append(x)
        y = self.decoders[0](skips[-1])
        for decoder, skip in zip(self.decoders[1:], reversed(skips[:-1]), strict=True):
            y = decoder(torch.cat([y, skip], dim=1))
        return y


class PatchDiscriminator(nn.Module):
    """pix2pix PatchGAN on (condition, image): a map of probabilities that each patch is real."""

    def __init__(self, in_channels: int = 11, base_channels: int = 64, kernel_size: int = 8):
        super().__init__()
        self.args = {"in_channels": in_channels, "base_channels": base_channels, "kernel_size": kernel_size}
        widths = [base_channels * m for m in (1, 2, 4, 8)]
        layers: list[nn.Module] = []
        cin = in_channels
        for k, (cout, stride) in enumerate(zip(widths, (2, 2, 2, 1), strict=True)):
            layers.append(nn.Conv2d(cin, cout, kernel_size, stride, 1))
            if k > 0:
                layers.append(nn.BatchNorm2d(cout))
            layers.append(nn.LeakyReLU(0.2))
            cin = cout
        layers += [nn.Conv2d(cin, 1, kernel_size, 1, 1), nn.Sigmoid()]
        self.net = nn.Sequential(*layers)
        init_weights(self)

    def forward(self, condition: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([condition, image], dim=1))


def patch_map_size(size: int, kernel_size: int = 8) -> int:
    """Side of the discriminator's patch map for a ``size`` x ``size`` input (50 at 512, 18 at 256)."""
    for stride in (2, 2, 2, 1, 1):
        size = (size + 2 - kernel_size) // stride + 1
    return size


def discriminator_loss(real: torch.Tensor, fake: torch.Tensor) -> torch.Tensor:
    """mean(-(log D(x, y) + log(1 - D(x, G(x))))) over the patch maps of real and generated pairs."""
    return (-(torch.log(real + EPS) + torch.log(1.0 - fake + EPS))).mean()


def generator_loss(fake: torch.Tensor, output: torch.Tensor, target: torch.Tensor, gan_weight: float = 500.0,
                   l1_weight: float = 0.5) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(total, GAN, L1): GAN = mean(-log D(x, G(x))), L1 = mean |y - G(x)|, total = gan_weight GAN +
    l1_weight L1, with the weights the thesis states (500 and 0.5; pix2pix's defaults are 1 and 100)."""
    gan = (-torch.log(fake + EPS)).mean()
    l1 = (target - output).abs().mean()
    return gan_weight * gan + l1_weight * l1, gan, l1


def count_parameters(module: nn.Module) -> int:
    """Trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
