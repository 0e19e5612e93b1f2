"""Training of the metaball generator (Horvath 2019, section 5.3): epochs over the cached views,
validation, checkpoints that resume. With ``gan_weight`` > 0 a PatchGAN discriminator trains beside
it (the thesis' pix2pix pair); with 0 the generator learns the L1 loss alone, which its per-pixel
targets (a deterministic function of the balls) need no adversary for.

Writes into one folder: ``last.pt`` (both networks, both Adam states, epoch, history; atomic),
``best.pt`` (the generator with its arguments and the config, chosen on the validation views'
normal error with silhouette misses counted as 90 degrees), ``metrics.jsonl`` and ``loss_curve.png``.
Views are held in memory as float16, cut to random ``crop`` squares that show surface, and turned
by random quarter turns and mirrored, the encoded normals turned alike. Each epoch draws from its
own seeds, so a resumed run makes the draws a straight one would.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from pipeline.cache import atomic_path
from pipeline.config import MetaballConfig, to_dict
from pipeline.metaball import decode_gbuffers, input_names
from pipeline.metaball.dataset import training_pair
from pipeline.metaball.networks import (
    PatchDiscriminator,
    UNetGenerator,
    discriminator_loss,
    generator_loss,
    init_weights,
)
from pipeline.metaball.views import params_of
from pipeline.metrics import angular_errors, iou, summarize_angles
from pipeline.model.data import rotate_quarter
from pipeline.model.networks import Generator
from pipeline.model.train import TimeLimitReached, TrainingError
from pipeline.plots import metaball_curves

log = logging.getLogger("deep_ssfr")

SHIPPED_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "metaball.pt"
"""The metaball generator shipped in the package (``make metaball-ship`` replaces it in place)."""

VAL_VIEWS = 24
"""Validation views scored each epoch (spread over the validation scenes)."""


def generator_args(m: MetaballConfig) -> dict:
    """The generator's arguments of a config (stored in every checkpoint; ``kind`` picks the class)."""
    channels = len(input_names(m.input))
    if m.architecture == "unet":
        return {"in_channels": channels, "out_channels": 7, "base_channels": m.base_channels, "upsample": m.upsample}
    args = {"kind": "resnet", "in_channels": channels, "out_channels": 7, "base_channels": m.base_channels,
            "downsamples": 2, "res_blocks": m.res_blocks}
    if m.residual and m.input != "circles":  # the encoded normal: input channels 1-3, target channels 4-6
        args["residual_at"] = [1, 4]
    return args


def input_normals(kind: str) -> tuple[slice, ...]:
    """The encoded normal blocks of an input kind (the sphere input's front normal), which turn with
    the image."""
    return (slice(1, 4),) if kind != "circles" else ()


def loss_weights(m: MetaballConfig) -> torch.Tensor:
    """Per target channel (``TARGET_CHANNELS``) weight of the L1 term. The sphere input carries no
    absolute depth (its codes are relative, so that views look alike at any distance), so the
    depth code, which counts from the view's nearest ball, is not learnt from it: the method takes
    its depth from the sphere splat instead (``pipeline.metaball.inference``)."""
    w = torch.ones(7)
    if m.input != "circles":
        w[3] = 0.0
    return w[None, :, None, None]


def build_generator(args: dict) -> torch.nn.Module:
    """A generator from its checkpoint arguments: the refiner's ResNet or the thesis' U-Net (checkpoints
    from before the choice hold no ``kind``)."""
    args = dict(args)
    if args.pop("kind", "unet") == "resnet":
        return Generator(**args)
    return UNetGenerator(**args)


def side_multiple(generator: torch.nn.Module) -> int:
    """What the generator's input sides must be multiples of (the U-Net's eight halvings: 256)."""
    return getattr(generator, "stride", 256)


def random_crop(x: np.ndarray, y: np.ndarray, crop: int, rng: np.random.Generator,
                tries: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A ``crop`` square of a view (input C x H x W, encoded target 7 x H x W), padded with empty pixels
    where the view is smaller, placed at random until it shows surface in a tenth of its pixels (at
    most ``tries`` draws)."""
    h, w = x.shape[1:]
    if h < crop or w < crop:
        ph, pw = max(crop - h, 0), max(crop - w, 0)
        x = np.pad(x, ((0, 0), (0, ph), (0, pw)))
        y = np.concatenate([np.pad(y[:3], ((0, 0), (0, ph), (0, pw))),
                            np.pad(y[3:4], ((0, 0), (0, ph), (0, pw)), constant_values=1.0),
                            np.pad(y[4:], ((0, 0), (0, ph), (0, pw)))])
        h, w = x.shape[1:]
    for _ in range(tries):
        r, c = int(rng.integers(h - crop + 1)), int(rng.integers(w - crop + 1))
        yc = y[:, r:r + crop, c:c + crop]
        if (yc[4:7].max(axis=0) > 0).mean() >= 0.1:
            break
    return x[:, r:r + crop, c:c + crop], yc


def augment(x: np.ndarray, y: np.ndarray, turns: int, mirror: bool,
            x_normals: tuple[slice, ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    """A view (input C x H x W, encoded target 7 x H x W, both in [0, 1]) turned ``turns`` quarter turns
    anticlockwise and then mirrored left-right: the image as a camera rolled or mirrored would see it.
    The encoded normals (the target's and the input's ``x_normals`` blocks) turn with it ((x, y) ->
    (-y, x) a turn, x -> -x mirrored); empty stays 0."""
    return _turned(x, turns, mirror, x_normals), _turned(y, turns, mirror, (slice(4, 7),))


def _turned(a: np.ndarray, turns: int, mirror: bool, normals: tuple[slice, ...]) -> np.ndarray:
    """``augment`` of one C x H x W array whose ``normals`` blocks are encoded as (n + 1) / 2, 0 empty."""
    out = rotate_quarter(a, turns, ())
    if mirror:
        out = out[:, :, ::-1]
    out = np.ascontiguousarray(out)
    for s in normals:
        empty = out[s].max(axis=0) == 0
        n = rotate_quarter(2.0 * a[s] - 1.0, turns, (slice(0, 3),))
        if mirror:
            n = n[:, :, ::-1] * np.array([-1.0, 1.0, 1.0])[:, None, None]
        out[s] = np.where(empty, 0.0, 0.5 * (n + 1.0))
    return out


class Pix2Pix:
    """The generator, the PatchGAN discriminator and their Adam optimisers (the thesis' learning rate
    and beta1), with the thesis' losses weighted by ``gan_weight`` and ``l1_weight``."""

    def __init__(self, m: MetaballConfig, device: str, seed: int):
        torch.manual_seed(seed)
        self.m, self.device = m, torch.device(device)
        self.generator = build_generator(generator_args(m)).to(self.device)
        self.weights = loss_weights(m)
        if m.architecture == "unet":
            init_weights(self.generator)
        betas = (m.beta1, 0.999)
        self.opt_g = torch.optim.Adam(self.generator.parameters(), m.learning_rate, betas=betas)
        self.discriminator = self.opt_d = None
        if m.gan_weight > 0:
            self.discriminator = PatchDiscriminator(len(input_names(m.input)) + 7, m.disc_base_channels,
                                                    m.disc_kernel).to(self.device)
            init_weights(self.discriminator)
            self.opt_d = torch.optim.Adam(self.discriminator.parameters(), m.learning_rate, betas=betas)

    def train_step(self, x: torch.Tensor, y: torch.Tensor) -> dict[str, float]:
        """One step of both networks on a batch in [-1, 1] (the thesis' ``preprocess``)."""
        self.generator.train()
        fake = self.generator(x)
        if self.discriminator is None:
            w = self.weights.to(fake.device)
            l1 = ((y - fake).abs() * w).mean() / w.mean()
            total, gan, loss_d = self.m.l1_weight * l1, torch.zeros(()), torch.zeros(())
        else:
            self.discriminator.train()
            self.opt_d.zero_grad(set_to_none=True)
            loss_d = discriminator_loss(self.discriminator(x, y), self.discriminator(x, fake.detach()))
            loss_d.backward()
            self.opt_d.step()
            total, gan, l1 = generator_loss(self.discriminator(x, fake), fake, y, self.m.gan_weight,
                                            self.m.l1_weight)
        self.opt_g.zero_grad(set_to_none=True)
        total.backward()
        self.opt_g.step()
        return {k: float(v.detach()) for k, v in (("loss_d", loss_d), ("loss_g", total), ("loss_gan", gan),
                                                   ("loss_l1", l1))}

    def state(self, epoch: int, best: float, history: list) -> dict:
        out = {"epoch": epoch, "best": best, "history": history, "generator": self.generator.state_dict(),
               "opt_g": self.opt_g.state_dict(), "generator_args": generator_args(self.m), "config": to_dict(self.m)}
        if self.discriminator is not None:
            out |= {"discriminator": self.discriminator.state_dict(), "opt_d": self.opt_d.state_dict()}
        return out

    def load_state(self, state: dict) -> None:
        self.generator.load_state_dict(state["generator"])
        self.opt_g.load_state_dict(state["opt_g"])
        if self.discriminator is not None:
            self.discriminator.load_state_dict(state["discriminator"])
            self.opt_d.load_state_dict(state["opt_d"])


@torch.no_grad()
def predict(generator: torch.nn.Module, inputs: np.ndarray, device: torch.device | str = "cpu") -> np.ndarray:
    """The generator's 7 x H x W encoded G-buffers in [0, 1] for a 4 x H x W input in [0, 1] (eval
    mode: no dropout, batch norm from its running statistics). Sides that are not multiples of
    ``side_multiple`` are padded with empty pixels for the network and cropped back."""
    generator.eval()
    h, w = inputs.shape[1:]
    k = side_multiple(generator)
    x = torch.zeros((1, inputs.shape[0], -(-h // k) * k, -(-w // k) * k), device=device)
    x[0, :, :h, :w] = torch.from_numpy(np.ascontiguousarray(inputs, np.float32)).to(device)
    x = x.contiguous(memory_format=torch.channels_last)  # oneDNN's fast layout on a CPU (0.6-0.75x the time)
    return ((generator(2.0 * x - 1.0)[0, :, :h, :w] + 1.0) * 0.5).clamp(0.0, 1.0).cpu().numpy()


def validation_metrics(generator: torch.nn.Module, views: list[tuple[np.ndarray, np.ndarray]], m: MetaballConfig,
                       device: torch.device) -> dict:
    """Normal error (degrees) where prediction and target both show surface, silhouette IoU, the mean
    L1 of the encoded buffers, and ``score_deg``, which picks the best epoch: the normal error over
    every pixel either shows as surface, 90 degrees where only one does (a collapsed silhouette cannot
    win on the few normals it keeps)."""
    p = params_of(m)
    errors, ious, l1, scored = [], [], [], []
    for x, y in views:
        out = predict(generator, x.astype(np.float32), device)
        pred, target = decode_gbuffers(out, p), decode_gbuffers(y.astype(np.float32), p)
        shown, wanted = pred["mask"] > 0, target["mask"] > 0
        e = angular_errors(pred["normals"], target["normals"], shown & wanted)
        errors.append(e)
        scored += [e, np.full(int((shown ^ wanted).sum()), 90.0)]
        ious.append(iou(shown, wanted))
        l1.append(float(np.abs(out - y).mean()))
    return {**summarize_angles(np.concatenate(errors)), "iou": float(np.mean(ious)), "l1": float(np.mean(l1)),
            "score_deg": float(np.concatenate(scored).mean())}


def _load(paths: list[Path], m: MetaballConfig, desc: str) -> list[tuple[np.ndarray, np.ndarray]]:
    return [tuple(a.astype(np.float16) for a in training_pair(p, m))
            for p in tqdm(paths, desc=desc, unit="view", leave=False)]


def fit(folder: Path, m: MetaballConfig, seed: int, train_paths: list[Path], val_paths: list[Path],
        device: str) -> float:
    """Train (or resume) until ``m.epochs``; returns the best validation ``score_deg``.
    Raises ``TimeLimitReached`` after the epoch that passes ``m.time_limit_minutes``."""
    folder = Path(folder)
    last = folder / "last.pt"
    nets = Pix2Pix(m, device, seed)
    start, best, history = 0, math.inf, []
    if last.exists():
        try:
            state = torch.load(last, map_location=nets.device, weights_only=True)
        except Exception as exc:
            raise TrainingError(f"corrupt checkpoint {last} ({exc}); delete it or run `make metaball-train FORCE=1` "
                                "to train again") from None
        nets.load_state(state)
        start, best, history = int(state["epoch"]), float(state["best"]), list(state["history"])
        log.info("metaball train: resuming after epoch %d", start)
    elif m.init_from:
        init_generator(nets.generator, m)
    if start >= m.epochs:
        metaball_curves(folder / "loss_curve.png", history)  # a run stopped by its time limit has none yet
        return best
    train = _load(train_paths, m, "load train")
    sizes = {x.shape[1:] for x, _ in train}
    if not m.crop and len(sizes) > 1:
        raise TrainingError(f"metaball.crop is 0 but the training views have {len(sizes)} sizes (the working scale "
                            "draws each at its own): set metaball.crop")
    step = max(1, len(val_paths) // VAL_VIEWS)
    val = _load(val_paths[::step][:VAL_VIEWS], m, "load val") or train[:2]
    steps = max(1, len(train) // m.batch_size)
    log.info("metaball train: generator %.2f M parameters, discriminator %.2f M, %d views, %d steps of %d per epoch "
             "on %s", sum(p.numel() for p in nets.generator.parameters()) / 1e6,
             sum(p.numel() for p in (nets.discriminator or torch.nn.Module()).parameters()) / 1e6, len(train), steps,
             m.batch_size, device)

    def crop(view, rng):
        x, y = (a.astype(np.float32) for a in view)
        return random_crop(x, y, m.crop, rng) if m.crop else (x, y)

    began = time.perf_counter()
    for epoch in tqdm(range(start + 1, m.epochs + 1), desc="metaball train", unit="epoch", initial=start,
                      total=m.epochs):
        rng = np.random.default_rng([seed, 11, epoch])
        torch.manual_seed(seed * 100_003 + epoch)  # dropout
        order = rng.permutation(len(train))
        sums: dict[str, float] = {}
        t0 = time.perf_counter()
        for s in tqdm(range(steps), desc=f"epoch {epoch}", unit="step", leave=False):
            pairs = [augment(*crop(train[i], rng), int(rng.integers(4)), bool(rng.random() < 0.5),
                             input_normals(m.input)) for i in order[s * m.batch_size:(s + 1) * m.batch_size]]
            x = torch.from_numpy(np.stack([p[0] for p in pairs])).to(nets.device) * 2.0 - 1.0
            y = torch.from_numpy(np.stack([p[1] for p in pairs])).to(nets.device) * 2.0 - 1.0
            for k, v in nets.train_step(x, y).items():
                sums[k] = sums.get(k, 0.0) + v / steps
        seconds = time.perf_counter() - t0
        metrics = validation_metrics(nets.generator, val, m, nets.device)
        record = {"epoch": epoch, **sums, "val": metrics, "train_seconds": round(seconds, 1),
                  "images_per_second": round(steps * m.batch_size / seconds, 2)}
        history.append(record)
        improved, best = metrics["score_deg"] < best, min(best, metrics["score_deg"])
        state = nets.state(epoch, best, history)
        with atomic_path(last) as tmp:
            torch.save(state, tmp)
        if improved:
            with atomic_path(folder / "best.pt") as tmp:
                torch.save({k: state[k] for k in ("epoch", "generator", "generator_args", "config", "history")}
                           | {"metrics": metrics}, tmp)
        with atomic_path(folder / "metrics.jsonl") as tmp:
            tmp.write_text("".join(json.dumps(h) + "\n" for h in history))
        log.info("metaball epoch %d: D %.3f G %.3f (GAN %.3f, L1 %.4f) | val normals %.2f deg (median %.2f), IoU %.3f, "
                 "L1 %.4f | %.1f img/s", epoch, sums["loss_d"], sums["loss_g"], sums["loss_gan"], sums["loss_l1"],
                 metrics["mean_deg"], metrics["median_deg"], metrics["iou"], metrics["l1"], record["images_per_second"])
        if m.time_limit_minutes and epoch < m.epochs and time.perf_counter() - began > 60 * m.time_limit_minutes:
            log.info("metaball train: time limit of %g minutes reached after epoch %d of %d; the next run resumes",
                     m.time_limit_minutes, epoch, m.epochs)
            raise TimeLimitReached(epoch)
    metaball_curves(folder / "loss_curve.png", history)
    return best


def init_generator(generator: torch.nn.Module, m: MetaballConfig) -> None:
    """Load the generator weights ``m.init_from`` names into a new run's ``generator``; the checkpoint
    must hold the same architecture and have been trained on the same input, or on the other sphere
    input (same channels; only the normals' source differs)."""
    path = SHIPPED_WEIGHTS if m.init_from == "shipped" else Path(m.init_from)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise TrainingError(f"metaball.init_from: no checkpoint at {path}") from None
    except Exception as exc:
        raise TrainingError(f"metaball.init_from: cannot read {path} ({exc})") from None
    want, got = generator_args(m), state.get("generator_args", {})
    trained_on = state.get("config", {}).get("input", "circles")
    if got != want or (trained_on != m.input and "circles" in (trained_on, m.input)):
        raise TrainingError(f"metaball.init_from: {path} holds a generator {got} trained on {trained_on}, but this "
                            f"config builds {want} for {m.input}")
    generator.load_state_dict(state["generator"])
    log.info("metaball train: starting from the generator of %s (trained on the %s input)", path, trained_on)


def load_generator(path: Path, device: str = "cpu") -> tuple[torch.nn.Module, dict]:
    """A trained generator (``best.pt`` or the shipped weights) in eval mode, and its checkpoint dict."""
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except FileNotFoundError:
        raise FileNotFoundError(f"no metaball weights at {path}: run `make metaball-train` or set "
                                "metaball.weights") from None
    except Exception as exc:
        raise TrainingError(f"cannot read metaball weights {path} ({exc})") from None
    generator = build_generator(state["generator_args"]).to(device)
    generator.load_state_dict(state["generator"])
    generator.eval()
    return generator, state
