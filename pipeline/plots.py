"""PNG figures: normal-map sheets, error maps and training curves (matplotlib, no display)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.cache import atomic_path


def _pyplot():
    """matplotlib's pyplot on the Agg backend, imported when a figure is first drawn: importing it
    took half a second of every process's start, render and demo included, which draw none."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def normal_rgb(normals: np.ndarray) -> np.ndarray:
    """H x W x 3 normals to RGB in [0, 1] ((n + 1) / 2), black where empty."""
    fluid = np.linalg.norm(normals, axis=-1, keepdims=True) > 0.5
    return np.where(fluid, np.clip(normals * 0.5 + 0.5, 0, 1), 0.0)


def angle_map(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Per-pixel angle in degrees where both maps show fluid, NaN elsewhere."""
    a = pred / np.maximum(np.linalg.norm(pred, axis=-1, keepdims=True), 1e-12)
    b = target / np.maximum(np.linalg.norm(target, axis=-1, keepdims=True), 1e-12)
    both = (np.linalg.norm(pred, axis=-1) > 0.5) & (np.linalg.norm(target, axis=-1) > 0.5)
    ang = np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))
    return np.where(both, ang, np.nan)


def _save(fig, path: Path) -> None:
    plt = _pyplot()
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)


def error_sheet(path: Path, frames: list, preds: list[np.ndarray]) -> None:
    """Rows of input | refined | target | angular error of the refined map."""
    plt = _pyplot()
    if not frames:
        return
    fig, axes = plt.subplots(len(frames), 4, figsize=(12, 3 * len(frames)), squeeze=False)
    for row, (f, pred) in enumerate(zip(frames, preds, strict=True)):
        given = np.moveaxis(f.inputs[:3], 0, -1)
        target = np.moveaxis(f.target, 0, -1)
        panels = [normal_rgb(given), normal_rgb(pred), normal_rgb(target)]
        for col, (img, title) in enumerate(zip(panels, ("input (bilateral)", "refined", "target (mesh)"),
                                               strict=True)):
            axes[row, col].imshow(img)
            axes[row, col].set_title(title)
        im = axes[row, 3].imshow(angle_map(pred, target), cmap="magma", vmin=0, vmax=45)
        axes[row, 3].set_title("error (deg)")
        fig.colorbar(im, ax=axes[row, 3], fraction=0.046)
    for ax in axes.ravel():
        ax.axis("off")
    _save(fig, path)


def loss_curves(path: Path, history: list[dict]) -> None:
    """Training losses and validation angular error per epoch."""
    plt = _pyplot()
    if not history:
        return
    epochs = [h["epoch"] for h in history]
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for key in ("loss_content", "loss_normal", "loss_adv", "loss_d"):
        a.plot(epochs, [h[key] for h in history], label=key.replace("loss_", ""))
    a.set_yscale("log")
    a.set_xlabel("epoch")
    a.set_title("training losses")
    a.legend()
    b.plot(epochs, [h["val"]["refined"]["mean_deg"] for h in history], label="refined")
    b.plot(epochs, [h["val"]["bilateral"]["mean_deg"] for h in history], label="bilateral input", ls="--")
    b.set_xlabel("epoch")
    b.set_ylabel("mean angular error (deg)")
    b.set_title("held-out normals vs mesh")
    b.legend()
    _save(fig, path)


def metaball_curves(path: Path, history: list[dict]) -> None:
    """The metaball generator's (and discriminator's) losses and validation normal error per epoch."""
    plt = _pyplot()
    if not history:
        return
    epochs = [h["epoch"] for h in history]
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for key in ("loss_d", "loss_gan", "loss_l1"):
        if any(h[key] > 0 for h in history):  # no adversarial terms when the generator learns L1 alone
            a.plot(epochs, [h[key] for h in history], label=key.replace("loss_", ""))
    a.set_yscale("log")
    a.set_xlabel("epoch")
    a.set_title("training losses")
    a.legend()
    b.plot(epochs, [h["val"]["mean_deg"] for h in history], label="mean")
    b.plot(epochs, [h["val"]["median_deg"] for h in history], label="median", ls="--")
    b.set_xlabel("epoch")
    b.set_ylabel("angular error (deg)")
    b.set_title("validation normals vs the ray-marched metaballs")
    b.legend()
    _save(fig, path)


def evaluation_figures(folder: Path, results: list[dict], table: dict, methods) -> None:
    """methods.png (mean error and share under 10 degrees), frames.png (error over frames per
    sequence) and examples.png (normal maps and error maps of a few held-out frames)."""
    plt = _pyplot()
    folder = Path(folder)
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.5))
    a.bar(methods, [table[m]["mean_deg"] for m in methods], color="tab:blue")
    a.set_ylabel("mean angular error (deg)")
    b.bar(methods, [100 * table[m]["under_10"] for m in methods], color="tab:green")
    b.set_ylabel("pixels under 10 deg (%)")
    for ax in (a, b):  # seven or more method names side by side overlap unless turned
        ax.tick_params(axis="x", labelrotation=30)
        plt.setp(ax.get_xticklabels(), ha="right")
    fig.suptitle("held-out normal maps against the mesh")
    _save(fig, folder / "methods.png")

    cols = min(3, len(results))
    rows = (len(results) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.5 * cols, 3 * rows), squeeze=False)
    for ax, res in zip(axes.ravel(), results, strict=False):
        for m in methods:
            ax.plot(res["methods"][m]["per_frame_mean_deg"], label=m)
        ax.set_title(f"{res['scene']} / {res['camera']}", fontsize=9)
        ax.set_xlabel("frame")
        ax.set_ylabel("mean error (deg)")
    for ax in axes.ravel()[len(results):]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=7)
    _save(fig, folder / "frames.png")

    examples = [e for r in results for e in r["examples"]][:4]
    if not examples:
        fig = plt.figure()
        _save(fig, folder / "examples.png")
        return
    fig, axes = plt.subplots(len(examples), len(methods) + 1, figsize=(2.6 * (len(methods) + 1), 2.6 * len(examples)),
                             squeeze=False)
    for row, ex in zip(axes, examples, strict=True):
        for ax, m in zip(row, (*methods, "target"), strict=True):
            ax.imshow(normal_rgb(ex[m]))
            ax.set_title(f"{m}" if m != "target" else f"mesh ({ex['scene']} {ex['frame']})", fontsize=8)
            ax.axis("off")
    _save(fig, folder / "examples.png")
