"""Training and inference of the refiner: one object owning both networks and their optimisers."""

from __future__ import annotations

from contextlib import nullcontext
from typing import Any

import numpy as np
import torch
from torch.nn.parallel import DistributedDataParallel

from pipeline.config import TrainConfig, to_dict
from pipeline.device import native_bfloat16
from pipeline.model.data import InputSpec
from pipeline.model.losses import adversarial_loss, content_loss, normal_constraint_loss
from pipeline.model.networks import Discriminator, Generator


def seed_everything(seed: int) -> None:
    """Seed torch's CPU and CUDA generators."""
    torch.manual_seed(seed)
    if torch.cuda.is_available():
        torch.cuda.manual_seed_all(seed)


def build_generator(cfg: TrainConfig) -> Generator:
    """The generator a training config describes."""
    return Generator(InputSpec.of(cfg).channels, cfg.gen_base_channels, cfg.gen_downsamples, cfg.gen_res_blocks,
                     residual=cfg.residual)


def autocast_dtype(cfg: TrainConfig, device: torch.device) -> torch.dtype:
    """The training's autocast dtype under ``train.mixed_precision``: float16 on CUDA (with a loss
    scaler), bfloat16 on a CPU that multiplies it natively (AVX512-BF16 or AMX: 2.3x the images/s of
    float32 here, the weights and optimiser state staying float32), else float32 (no autocast)."""
    if not cfg.mixed_precision:
        return torch.float32
    if device.type == "cuda":
        return torch.float16
    return torch.bfloat16 if device.type == "cpu" and native_bfloat16("cpu") else torch.float32


class Refiner:
    """cGAN of Choi et al.: G refines the normal map, D judges (condition, normal) pairs."""

    def __init__(self, cfg: TrainConfig, device: str = "cpu", seed: int = 0):
        self.cfg, self.device = cfg, torch.device(device)
        seed_everything(seed)
        self.generator = build_generator(cfg).to(self.device)
        self.discriminator = Discriminator(6, cfg.disc_base_channels, cfg.disc_layers).to(self.device)
        betas = (cfg.beta1, 0.999)
        self.opt_g = torch.optim.Adam(self.generator.parameters(), lr=cfg.lr, betas=betas)
        self.opt_d = torch.optim.Adam(self.discriminator.parameters(), lr=cfg.lr, betas=betas)
        self.sched_g = torch.optim.lr_scheduler.ExponentialLR(self.opt_g, gamma=cfg.lr_decay)
        self.sched_d = torch.optim.lr_scheduler.ExponentialLR(self.opt_d, gamma=cfg.lr_decay)
        self.autocast_dtype = autocast_dtype(cfg, self.device)
        self.amp = self.autocast_dtype == torch.float16  # float16 needs its loss scaled, bfloat16 not
        self.scaler = torch.amp.GradScaler("cuda", enabled=self.amp)
        # oneDNN's (and cuDNN's) fast layout for convolutions: 1.6x the images/s on this CPU alone
        for net in (self.generator, self.discriminator):
            net.to(memory_format=torch.channels_last)
        self.train_generator: torch.nn.Module = self.generator
        """What ``train_step`` runs: the generator, or its DistributedDataParallel wrapper."""
        self.train_discriminator: torch.nn.Module = self.discriminator
        """What ``train_step`` runs: the discriminator, or its DistributedDataParallel wrapper."""

    def distribute(self) -> None:
        """Wrap both networks in DistributedDataParallel (the process group must be up): gradients
        are averaged over the processes, so their copies stay equal. Checkpoints keep saving the
        unwrapped modules, whose keys ``load_generator`` reads. Batch-norm statistics stay per
        process (each sees its slice of the global batch) and are not broadcast: only rank 0's are
        saved, and training-mode normalisation never reads them."""
        ids = [self.device.index] if self.device.type == "cuda" else None
        self.train_generator = DistributedDataParallel(self.generator, device_ids=ids)
        self.train_discriminator = DistributedDataParallel(self.discriminator, device_ids=ids)
        for wrapped in (self.train_generator, self.train_discriminator):
            wrapped.broadcast_buffers = False  # after construction: the argument is deprecated in torch 2.13

    def _autocast(self):
        if self.autocast_dtype == torch.float32:
            return nullcontext()
        return torch.autocast(self.device.type, dtype=self.autocast_dtype)

    def train_step(self, inputs: np.ndarray | torch.Tensor, target: np.ndarray | torch.Tensor) -> dict[str, float]:
        """One discriminator and one generator update on a batch (N x C x H x W arrays or tensors)."""
        cfg = self.cfg
        generator, discriminator = self.train_generator, self.train_discriminator
        x = torch.as_tensor(inputs).to(self.device, non_blocking=True).contiguous(memory_format=torch.channels_last)
        y = torch.as_tensor(target).to(self.device, non_blocking=True).contiguous(memory_format=torch.channels_last)
        cond = x[:, :3]
        generator.train()
        discriminator.train()
        with self._autocast():
            fake = generator(x)
        use_gan = cfg.lambda_adversarial > 0
        loss_d = torch.zeros((), device=self.device)
        if use_gan:
            with self._autocast():
                loss_d = 0.5 * (adversarial_loss(discriminator(cond, y), True)
                                + adversarial_loss(discriminator(cond, fake.detach()), False))
            self.opt_d.zero_grad(set_to_none=True)
            self.scaler.scale(loss_d).backward()
            self.scaler.step(self.opt_d)
        # the discriminator's own gradients of this pass are thrown away: do not average them
        unsynced = discriminator.no_sync() if isinstance(discriminator, DistributedDataParallel) else nullcontext()
        with self._autocast(), unsynced:
            adv = adversarial_loss(discriminator(cond, fake), True) if use_gan else torch.zeros((), device=self.device)
            lc = content_loss(fake.float(), y, cfg.content_loss)
            ln = normal_constraint_loss(fake.float())
            loss_g = cfg.lambda_adversarial * adv + cfg.lambda_content * lc + cfg.lambda_normal * ln
        self.opt_g.zero_grad(set_to_none=True)
        self.scaler.scale(loss_g).backward()
        self.scaler.step(self.opt_g)
        self.scaler.update()
        return {"loss_d": loss_d.item(), "loss_adv": adv.item(), "loss_content": lc.item(),
                "loss_normal": ln.item(), "loss_g": loss_g.item()}

    def end_epoch(self) -> None:
        """Decay the learning rates."""
        self.sched_g.step()
        self.sched_d.step()

    @torch.no_grad()
    def predict(self, inputs: np.ndarray) -> np.ndarray:
        """Refined normals (H x W x 3) of one C x H x W input (eval mode)."""
        return predict(self.generator, inputs, self.device)

    def state(self, epoch: int, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        """Everything a checkpoint holds: weights, construction arguments, config, optimisers."""
        return {"generator": self.generator.state_dict(), "discriminator": self.discriminator.state_dict(),
                "generator_args": dict(self.generator.args), "discriminator_args": dict(self.discriminator.args),
                "opt_g": self.opt_g.state_dict(), "opt_d": self.opt_d.state_dict(),
                "sched_g": self.sched_g.state_dict(), "sched_d": self.sched_d.state_dict(),
                "scaler": self.scaler.state_dict(), "config": to_dict(self.cfg), "epoch": epoch,
                **(extra or {})}

    def load_state(self, state: dict[str, Any]) -> None:
        """Restore a checkpoint made by :meth:`state`."""
        self.generator.load_state_dict(state["generator"])
        self.discriminator.load_state_dict(state["discriminator"])
        self.opt_g.load_state_dict(state["opt_g"])
        self.opt_d.load_state_dict(state["opt_d"])
        self.sched_g.load_state_dict(state["sched_g"])
        self.sched_d.load_state_dict(state["sched_d"])
        self.scaler.load_state_dict(state["scaler"])


@torch.inference_mode()
def predict(generator: Generator, inputs: np.ndarray, device: torch.device | str = "cpu") -> np.ndarray:
    """Run a generator on one C x H x W input, padding to its stride; returns H x W x 3.

    The plain forward pass of the training-time module (validation during training);
    ``pipeline.model.inference.Refiner`` is the faster one for rendering."""
    generator.eval()
    _, h, w = inputs.shape
    s = generator.stride
    ph, pw = (-h) % s, (-w) % s
    x = torch.from_numpy(np.ascontiguousarray(inputs))[None]
    if ph or pw:
        x = torch.nn.functional.pad(x, (0, pw, 0, ph))
    y = generator(x.to(device))[0, :, :h, :w]
    return y.permute(1, 2, 0).float().cpu().numpy()


def load_generator(path, device: str = "cpu") -> tuple[Generator, dict[str, Any]]:
    """Rebuild a generator from a checkpoint alone (``weights_only=True``); returns it and the
    checkpoint's metadata (config, epoch, metrics)."""
    state = torch.load(path, map_location=device, weights_only=True)
    generator = Generator(**state["generator_args"]).to(device)
    generator.load_state_dict(state["generator"])
    generator.eval()
    meta = {k: v for k, v in state.items() if k in ("config", "epoch", "metrics", "generator_args")}
    return generator, meta


def validation_metrics(generator: Generator, frames: list, device: torch.device | str = "cpu",
                       threshold: float = 0.5) -> tuple[dict[str, Any], list[np.ndarray]]:
    """Angular error of refined and input (bilateral) normals against the mesh target.

    The evaluation's rule (``metrics.errors_over_reference``): every target pixel counts, 90 degrees
    where the compared map shows no fluid (refined pixels by ``masks.refined_mask``, as the
    renderer drops them), so the best checkpoint cannot win by a shrinking mask. Returns the
    summary and the refined maps (for the PNG sheet).
    """
    from pipeline.masks import REFINED_REACH_PX, normal_mask, refined_mask
    from pipeline.metrics import errors_over_reference, iou, summarize_angles

    refined_err, input_err, ious, preds = [], [], [], []
    for f in frames:
        pred = predict(generator, f.inputs, device)
        target = np.moveaxis(f.target, 0, -1)
        given = np.moveaxis(f.inputs[:3], 0, -1)
        t_mask = normal_mask(target)
        r_mask = refined_mask(pred, f.fluid, threshold, REFINED_REACH_PX)
        refined_err.append(errors_over_reference(pred, target, r_mask, t_mask)[0])
        input_err.append(errors_over_reference(given, target, normal_mask(given), t_mask)[0])
        ious.append(iou(r_mask, t_mask))
        preds.append(pred)
    refined = summarize_angles(np.concatenate(refined_err))
    baseline = summarize_angles(np.concatenate(input_err))
    return {"refined": refined, "bilateral": baseline, "refined_iou": float(np.mean(ious))}, preds
