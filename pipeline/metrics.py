"""Image metrics shared by training validation and the evaluate stage: angular error, IoU."""

from __future__ import annotations

import numpy as np

from pipeline.vectors import length


def angular_errors(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Angles in degrees between unit-normalised ``pred`` and ``target`` at ``mask`` pixels."""
    a = pred[mask].astype(np.float64)
    b = target[mask].astype(np.float64)
    a /= np.maximum(length(a), 1e-12)[:, None]
    b /= np.maximum(length(b), 1e-12)[:, None]
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))


MISSED_DEG = 90.0
"""The error a reference pixel scores where a method shows no fluid: a normal at right angles."""


def errors_over_reference(pred: np.ndarray, target: np.ndarray, mask: np.ndarray, t_mask: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, int]:
    """The evaluation's rule, one pixel set for every method: every pixel of the reference mask
    ``t_mask`` scores, its angle where the method's ``mask`` shows fluid and ``MISSED_DEG`` where it
    does not, so a method cannot score better by leaving hard pixels out (its extra pixels count
    against it in IoU). Returns those errors, the angles on ``mask & t_mask`` alone (the per-mask
    figure) and the number of missed pixels."""
    shared = angular_errors(pred, target, mask & t_mask)
    missed = int((t_mask & ~mask).sum())
    return np.concatenate([shared, np.full(missed, MISSED_DEG)]), shared, missed


def summarize_angles(errors: np.ndarray) -> dict[str, float]:
    """Mean, median and shares under 5, 10 and 20 degrees."""
    if errors.size == 0:
        return {"mean_deg": float("nan"), "median_deg": float("nan"), "under_5": float("nan"),
                "under_10": float("nan"), "under_20": float("nan"), "pixels": 0}
    return {"mean_deg": float(errors.mean()), "median_deg": float(np.median(errors)),
            "under_5": float((errors < 5).mean()), "under_10": float((errors < 10).mean()),
            "under_20": float((errors < 20).mean()), "pixels": int(errors.size)}


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks (1 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)
