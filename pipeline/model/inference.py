"""Refiner inference on the CPU (or GPU) at render time.

Five things make it cheaper than a plain forward pass of the training-time module, without
changing its output beyond rounding: batch norm folded into the preceding convolutions, each
decoder stage's nearest-neighbour upsampling and 3x3 convolution done as four 2x2 convolutions of
the coarse image (``NearestUpConv``),
channels-last tensors (oneDNN's preferred layout for convolutions on the CPU), bfloat16 arithmetic
where the hardware has it (``render.refiner_precision``), and the network run only on the fluid's
bounding box grown by ``CROP_MARGIN_PX`` (at most the generator's receptive radius, with which
the fluid's normals are the whole image's to rounding). The refined method keeps only pixels near
the splat's fluid, so the rest of the output is dropped anyway. The box starts on a multiple of the
generator's stride, so the stride-2 convolutions sample the same pixels as on the whole image.
"""

from __future__ import annotations

import copy
import hashlib
import json
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from pipeline.device import native_bfloat16
from pipeline.model.data import InputSpec, Splat
from pipeline.model.networks import Generator


def inference_dtype(device: str, precision: str = "auto") -> torch.dtype:
    """The dtype of the refiner's arithmetic: ``precision`` 'float32' or 'bfloat16', or 'auto':
    bfloat16 where the hardware multiplies it natively (a CUDA GPU with bf16, a CPU with AVX512-BF16
    or AMX, where oneDNN's bf16 convolutions run the refiner 2.2x faster than float32), float32
    elsewhere (emulated bf16 would be slower)."""
    if precision != "auto":
        return {"float32": torch.float32, "bfloat16": torch.bfloat16}[precision]
    return torch.bfloat16 if native_bfloat16(device) else torch.float32


def fold_batch_norm(module: nn.Module) -> nn.Module:
    """Fold every BatchNorm2d that follows a Conv2d inside a Sequential into the convolution
    (in place; eval-mode statistics). Returns the module."""
    for child in module.children():
        if isinstance(child, nn.Sequential):
            for i in range(len(child) - 1):
                if isinstance(child[i], nn.Conv2d) and isinstance(child[i + 1], nn.BatchNorm2d):
                    child[i] = fuse_conv_bn_eval(child[i], child[i + 1])
                    child[i + 1] = nn.Identity()
        fold_batch_norm(child)
    return module


class NearestUpConv(nn.Module):
    """A nearest-neighbour 2x upsampling followed by a 3x3 convolution (padding 1) and an
    activation, computed on the coarse image: each of the four output phases (row and column
    parity) reads a 2x2 block of coarse pixels, whose weights are the 3x3 kernel's taps summed
    where they fall on the same coarse pixel. 4 instead of 9 taps an output pixel, and the
    upsampled image is never made: on the refiner's 38k 1080p box 72 -> 63 ms a pass (bfloat16)."""

    def __init__(self, conv: nn.Conv2d, activation: nn.Module):
        super().__init__()
        if conv.kernel_size != (3, 3) or conv.stride != (1, 1) or conv.padding != (1, 1) or conv.groups != 1:
            raise ValueError(f"NearestUpConv replaces a 3x3 convolution of stride 1 and padding 1, not {conv}")
        w = conv.weight.detach().float()
        # coarse offset -1 / 0 for an even output row or column, 0 / +1 for an odd one
        taps = {0: (w[:, :, 0:1], w[:, :, 1:3].sum(2, keepdim=True)),
                1: (w[:, :, 0:2].sum(2, keepdim=True), w[:, :, 2:3])}
        for a in (0, 1):
            rows = torch.cat(taps[a], 2)
            cols = {0: (rows[..., 0:1], rows[..., 1:3].sum(3, keepdim=True)),
                    1: (rows[..., 0:2].sum(3, keepdim=True), rows[..., 2:3])}
            for b in (0, 1):
                self.register_buffer(f"phase{a}{b}", torch.cat(cols[b], 3).to(conv.weight.dtype))
        bias = conv.bias.detach() if conv.bias is not None else torch.zeros(conv.out_channels)
        self.register_buffer("bias", bias.clone())
        self.activation = activation

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, _, h, w = x.shape
        padded = nn.functional.pad(x, (1, 1, 1, 1))
        out = torch.empty((n, self.bias.shape[0], 2 * h, 2 * w), dtype=x.dtype, device=x.device,
                          memory_format=torch.channels_last if x.is_contiguous(memory_format=torch.channels_last)
                          else torch.contiguous_format)
        for a in (0, 1):
            for b in (0, 1):
                out[:, :, a::2, b::2] = nn.functional.conv2d(padded[:, :, a:a + h + 1, b:b + w + 1],
                                                             getattr(self, f"phase{a}{b}"), self.bias)
        return self.activation(out)


def coarse_upsampling(generator: Generator) -> Generator:
    """Each decoder stage of a batch-norm-folded generator (``nn.Upsample`` then convolution and
    activation) as a ``NearestUpConv`` (in place). Returns the generator."""
    for k, stage in enumerate(generator.up):
        upsample, (conv, norm, activation) = stage
        if not isinstance(upsample, nn.Upsample) or upsample.mode != "nearest" or upsample.scale_factor != 2 \
                or not isinstance(norm, nn.Identity):
            raise ValueError(f"decoder stage {k} is not a folded nearest 2x upsampling and convolution: {stage}")
        generator.up[k] = NearestUpConv(conv, activation)
    return generator


def fluid_window(fluid, margin: int, stride: int) -> tuple[int, int, int, int] | None:
    """(y0, y1, x0, x1) of the fluid's bounding box grown by ``margin``, with y0 and x0 on
    multiples of ``stride`` and clamped to the image; None when there is no fluid. ``fluid`` may be
    a tensor on a GPU: only its row and column flags come to the host."""
    rows_any, cols_any = fluid.any(1), fluid.any(0)
    if isinstance(rows_any, torch.Tensor):
        rows_any, cols_any = rows_any.cpu().numpy(), cols_any.cpu().numpy()
    rows, cols = np.flatnonzero(rows_any), np.flatnonzero(cols_any)
    if rows.size == 0:
        return None
    h, w = fluid.shape
    y0 = max(int(rows[0]) - margin, 0) // stride * stride
    x0 = max(int(cols[0]) - margin, 0) // stride * stride
    return y0, min(int(rows[-1]) + margin + 1, h), x0, min(int(cols[-1]) + margin + 1, w)


CROP_MARGIN_PX = 24
"""How far (working pixels) past the fluid's box the network's input reaches. The receptive radius
(46 px for the shipped generator) bounds what can reach a fluid pixel, but what does is far nearer:
on 28 views of six held-out sequences at 1024 px (128-724 px at the working scale) 24 px moves the
fluid's normals by 0.003 degree on average against the whole radius (at most 0.65 degree, at a few
pixels by the box's edge; bfloat16's run-to-run rounding alone reads 0.006) and their error against
the mesh by 0.0002 degree, for a network input 21% smaller at 38k particles in 1080p and 12% at 1M.
16 px moves them by 0.009 degree (0.08 on a small blob's view, whose fluid is all near its box's
edge), 8 px by 0.03 (docs/performance.md)."""

FLIP_MAX_PIXELS = 1 << 18
"""The generator's input (after the crop to the fluid) is also run mirrored left to right, and the two
outputs averaged, when it has at most this many pixels: on the validation scene that lowers the mean
error by 0.2-0.3 degree at 192, 256 and 512 px (5.81 to 5.57 over the three) with the same missed
share and IoU (``benchmarks/tune_inference.py --flips 0 inf``), for a second pass of the network,
which under a quarter of a megapixel costs little; a 1080p frame of a million particles (0.4 MP
at the working scale) keeps one pass. 0: never."""


class Refiner:
    """A generator prepared for inference: ``refiner(inputs, fluid) -> H x W x 3`` normals.

    It also carries how its input is made (``spec``: depth features, splat kind, working scale), as
    recorded in the checkpoint's training config."""

    def __init__(self, generator: Generator, device: str | torch.device = "cpu", crop: bool = True,
                 spec: InputSpec | None = None, precision: str = "float32", margin: int | None = None):
        """``precision``: 'float32', 'bfloat16' or 'auto' (``inference_dtype``); ``margin``: the
        crop's reach past the fluid (default ``CROP_MARGIN_PX``, never past the receptive radius)."""
        self.spec = spec or InputSpec()
        self.device = torch.device(device)
        self.dtype = inference_dtype(str(self.device), precision)
        self.stride = generator.stride
        reach = generator.receptive_radius()
        self.margin = min(reach, CROP_MARGIN_PX if margin is None else margin)
        self.crop = crop
        net = coarse_upsampling(fold_batch_norm(copy.deepcopy(generator).eval()))
        self.net = net.to(self.device, self.dtype, memory_format=torch.channels_last)

    @property
    def splat(self) -> Splat:
        """The splat kind the generator's input is made of."""
        return self.spec.splat

    @property
    def auxiliary(self) -> bool:
        """Whether the input carries depth features besides the normal."""
        return self.spec.auxiliary

    def __call__(self, inputs: np.ndarray, fluid: np.ndarray | None = None) -> np.ndarray:
        """Refined normals of one C x H x W input (H x W x 3 on the host); with ``fluid`` (H x W
        bool) only its window is computed and the rest of the output is the zero vector."""
        return self.run(inputs, fluid).permute(1, 2, 0).contiguous().cpu().numpy()

    @torch.inference_mode()
    def run(self, inputs: np.ndarray | torch.Tensor, fluid: np.ndarray | torch.Tensor | None = None) -> torch.Tensor:
        """``__call__``'s normals as a 3 x H x W float32 tensor left on the refiner's device (on a
        GPU the call returns while the network runs). ``inputs`` and ``fluid`` may be tensors
        there already (``pipeline.model.data.prepare`` of device channels)."""
        _, h, w = inputs.shape
        out = torch.zeros((3, h, w), dtype=torch.float32, device=self.device)
        window = (0, h, 0, w)
        if self.crop and fluid is not None:
            window = fluid_window(fluid, self.margin, self.stride)
            if window is None:
                return out
        y0, y1, x0, x1 = window
        x = inputs[:, y0:y1, x0:x1]
        x = (x.contiguous() if isinstance(x, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(x)))[None]
        ph, pw = (-(y1 - y0)) % self.stride, (-(x1 - x0)) % self.stride
        if ph or pw:
            x = nn.functional.pad(x, (0, pw, 0, ph))
        x = x.to(self.device, self.dtype).contiguous(memory_format=torch.channels_last)
        y = self.net(x)
        if x.shape[-2] * x.shape[-1] <= FLIP_MAX_PIXELS:  # and mirrored: the normal's X turns round
            mirror = torch.ones(x.shape[1], dtype=x.dtype, device=x.device)
            mirror[0] = -1.0
            mirrored = self.net((x * mirror[:, None, None]).flip(-1)).flip(-1)
            y = 0.5 * (y + mirrored * mirror[:3, None, None])
        out[:, y0:y1, x0:x1] = y[0, :, : y1 - y0, : x1 - x0].float()
        return out


def load_refiner(path, device: str | torch.device = "cpu", precision: str = "auto") -> Refiner:
    """A render-time refiner from a training checkpoint (``weights_only=True``)."""
    from pipeline.model.trainer import load_generator

    generator, meta = load_generator(path, str(device))
    return Refiner(generator, device, spec=InputSpec.of(meta["config"]), precision=precision)




def checked_digest(path: Path) -> str:
    """The SHA-256 of a weights file, checked against the one its card (``<name>.json`` beside it,
    written when the weights were shipped) records: damaged or swapped weights load as numbers
    all the same, and would change every frame without a word."""
    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    card = Path(path).with_suffix(".json")
    if card.is_file():
        try:
            recorded = json.loads(card.read_text(encoding="utf-8")).get("sha256")
        except (ValueError, AttributeError):
            raise RuntimeError(f"the card {card} of the weights {path} is not a JSON object; restore it") from None
        if recorded is not None and recorded != digest:
            raise RuntimeError(f"the weights {path} are not the ones their card {card.name} records (SHA-256 "
                               f"{digest[:12]}, card {str(recorded)[:12]}): restore them (git checkout {path}) or "
                               f"ship them again")
    return digest


def load_weights(path: Path, device: str | torch.device = "cpu", precision: str = "auto") -> tuple[Refiner, str]:
    """A refiner from a checkpoint file and a short content hash of it (for cache keys); a missing
    or unreadable file, or one its card disowns (``checked_digest``), raises ``FileNotFoundError`` /
    ``RuntimeError`` naming it."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no generator checkpoint at {path}; run `make train` and set render.weights to "
                                "'trained' or a checkpoint path, or restore the shipped weights")
    digest = checked_digest(path)
    try:
        refiner = load_refiner(path, device, precision)
    except Exception as exc:
        raise RuntimeError(f"cannot load generator checkpoint {path} ({exc})") from None
    return refiner, digest[:12]
