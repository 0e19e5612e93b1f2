"""Losses of the refiner (Choi et al. 2021, equations 1-4).

How the paper's formulas are read here:

- Adversarial (eq. 1): binary cross-entropy on the discriminator's logit; the generator
  minimises -log D(y, G(y)) (the non-saturating form of log(1 - D)).
- Content (eq. 3): L_C = lambda_C * mean |x~ - x| over all pixels and channels (L1; the L2
  ablation uses the mean squared difference). Background pixels are in it: the target there is
  the zero vector, which is what teaches the network the silhouette.
- Normal constraint (eq. 2): L_N = lambda_N * min(1 - |N(x~)|, |x~|). N decodes a stored pixel to
  its vector; our network outputs the vector itself, so N is the identity. The paper writes
  ||.||_1 loosely; we take the per-pixel Euclidean length l = |x~| and the loss
  mean over pixels of min(|1 - l|, l): zero exactly when every pixel is a unit normal (fluid) or
  the zero vector (empty). The absolute value also penalises lengths above one, which tanh
  outputs can reach (up to sqrt(3)) and which 1 - l would reward.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def normal_constraint_loss(pred: torch.Tensor) -> torch.Tensor:
    """Mean over pixels of min(|1 - |n||, |n|) for an N x 3 x H x W normal map."""
    length = torch.sqrt((pred * pred).sum(dim=1) + 1e-12)
    return torch.minimum((1.0 - length).abs(), length).mean()


def content_loss(pred: torch.Tensor, target: torch.Tensor, kind: str = "l1") -> torch.Tensor:
    """L1 (default) or L2 distance between predicted and target normal maps."""
    if kind == "l1":
        return (pred - target).abs().mean()
    if kind == "l2":
        return ((pred - target) ** 2).mean()
    raise ValueError(f"content loss must be l1 or l2, got {kind!r}")


def adversarial_loss(logits: torch.Tensor, real: bool) -> torch.Tensor:
    """BCE of the discriminator's logits against all-real or all-fake labels."""
    labels = torch.ones_like(logits) if real else torch.zeros_like(logits)
    return F.binary_cross_entropy_with_logits(logits, labels)
