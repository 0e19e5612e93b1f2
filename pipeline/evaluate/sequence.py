"""Every normal-map method of one held-out sequence against the reference surface.

Per method: normal error over the reference's pixels (mean, median, share under 5 / 10 / 20 degrees;
a reference pixel the method misses scores 90 degrees: ``metrics.errors_over_reference``), the share
of reference pixels missed, the error on the method's own mask alone (the older, looser figure),
silhouette IoU, PSNR and SSIM of the shaded image against the shaded reference, temporal flicker
(the frame-to-frame change of the mean error), the per-pixel temporal error between consecutive
evaluated frames (``pipeline.evaluate.temporal``) and milliseconds per frame from particles to the
normal map.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity
from tqdm import tqdm

from pipeline.camera import camera_for_frame
from pipeline.config import Config, SceneConfig
from pipeline.device import warp_device
from pipeline.evaluate.temporal import normal_change, surface_flow, temporal_errors
from pipeline.exr import read_exr, stack
from pipeline.frames import frame_name, load_frame, spread
from pipeline.methods import method_maps, normal_source, refine, shade_frame
from pipeline.metrics import angular_errors, errors_over_reference, iou, summarize_angles
from pipeline.model.scale import median_radius_px
from pipeline.parallel import Launcher
from pipeline.screen import ScreenSpace
from pipeline.shading import Shader, tonemap
from pipeline.shading.background import BackgroundRenderer, Surroundings
from pipeline.surface import particle_ellipsoids
from pipeline.timing import Timings

TIMED_FRAMES = 3


@dataclass(frozen=True)
class HeldOut:
    """One held-out sequence: a scene seen along one camera path, its dataset views and particles."""

    scene: SceneConfig
    camera: str
    records: list[dict]       # the dataset manifest's records of this camera path, in frame order
    dataset_dir: Path
    sim_dir: Path
    particle_radius: float


def _maps(method: str, ch: dict, refiner, threshold: float, focal_px: float, radius: float):
    """(normals, mask, depth) of a method from a dataset frame's channels."""
    if method == "refined":
        return refine(refiner, ch, threshold, focal_px, radius)
    if method == "mesh":
        return stack(ch, "target.N."), ch["target.A"] > 0, ch["target.Z"]
    maps = method_maps(method, ch)
    return maps["normals"], maps["mask"] > 0, maps["depth"]


def evaluate_sequence(seq: HeldOut, config: Config, refiner, methods: tuple[str, ...], device: str,
                      metaball=None) -> dict:
    """Per-method metrics of one held-out sequence, plus per-frame errors and examples for the figures.

    The ``metaball`` method is also scored against its own ray-marched metaball surface on every
    ``metaball.target_stride``-th evaluated frame (``own_*`` figures), and that surface against the
    mesh (``surface_*``: what a network that reproduced it exactly would score)."""
    if "metaball" in methods and metaball is None:
        raise ValueError("the metaball method needs a metaball generator")
    rp = config.render
    records = spread(seq.records, config.evaluate.frames_per_sequence)
    width, height = config.dataset.width, config.dataset.height
    shader = Shader(warp_device(device))
    launch = Launcher(warp_device(device)) if "metaball" in methods else None
    background = BackgroundRenderer(Surroundings.of_scene(seq.scene), rp, width, height)
    scores = {k: {m: [] for m in methods} for k in ("errors", "on_mask", "missed", "per_frame", "iou", "psnr",
                                                     "ssim", "temporal", "temporal_missed")}
    own: dict[str, list] = {"errors": [], "iou": [], "surface": []}
    examples, radii = [], []
    ss = ScreenSpace(warp_device(device))
    previous = None  # the last frame's particles, camera and maps, for the temporal error
    try:
        for k, r in enumerate(tqdm(records, desc=f"evaluate {seq.scene.name}/{seq.camera}", unit="frame",
                                   leave=False)):
            ch = read_exr(seq.dataset_dir / r["file"])
            cam = camera_for_frame(seq.scene.cameras, seq.camera, r["index"], len(seq.records), width, height)
            radii.append(median_radius_px(ch["Z"], cam.focal_px, seq.particle_radius))
            bg, bg_depth = background.render(cam)
            bg = shader.fill_sky(bg, bg_depth, cam, rp)
            target, t_mask = stack(ch, "target.N."), ch["target.A"] > 0
            maps = {m: _maps(m, ch, refiner, rp.normal_threshold, cam.focal_px, seq.particle_radius)
                    for m in (*methods, "mesh") if m != "metaball"}
            x, _ = load_frame(seq.sim_dir / frame_name(r["frame"]))
            if "metaball" in methods:
                ell = (particle_ellipsoids(x, seq.particle_radius, config.dataset, launch)
                       if metaball.config.anisotropic else None)
                g = metaball.gbuffers(x, seq.particle_radius, cam, launch, ell)
                maps["metaball"] = (g["normals"], g["mask"] > 0, g["depth"])
                if k % config.metaball.target_stride == 0:
                    surface = metaball.targets(x, seq.particle_radius, cam, launch, ell)
                    on = surface["mask"] > 0
                    own["errors"].append(angular_errors(g["normals"], surface["normals"], (g["mask"] > 0) & on))
                    own["iou"].append(iou(g["mask"] > 0, on))
                    own["surface"].append(errors_over_reference(surface["normals"], target, on, t_mask)[0])
            shaded = {}
            for m, (n, mask, depth) in maps.items():
                src = {"normals": n.astype(np.float32), "depth": np.where(mask, depth, 0).astype(np.float32),
                       "mask": mask.astype(np.float32), "thickness": ch["thickness"]}
                shaded[m] = tonemap(shade_frame(src, bg, bg_depth, cam, rp, shader).beauty).astype(np.float32) / 255
                if m == "mesh":
                    continue
                e, on_mask, missed = errors_over_reference(n, target, mask, t_mask)
                scores["errors"][m].append(e)
                scores["on_mask"][m].append(on_mask)
                scores["missed"][m].append(missed)
                scores["per_frame"][m].append(float(e.mean()) if e.size else float("nan"))
                scores["iou"][m].append(iou(mask, t_mask))
            now = {"x": x, "cam": cam, "maps": maps, "target": target, "t_mask": t_mask,
                   "depth": np.where(t_mask, ch["target.Z"], 0.0)}
            if previous is not None:
                _score_change(ss, previous, now, methods, seq.particle_radius, scores)
            previous = now
            if len(examples) < 3 and t_mask.mean() > 0.02 and r["index"] % 4 == 0:
                examples.append({"scene": seq.scene.name, "frame": r["frame"], "target": target,
                                 **{m: maps[m][0] for m in methods}})
            for m in methods:
                scores["psnr"][m].append(peak_signal_noise_ratio(shaded["mesh"], shaded[m], data_range=1.0))
                scores["ssim"][m].append(structural_similarity(shaded["mesh"], shaded[m], channel_axis=-1,
                                                               data_range=1.0))
    finally:
        ss.close()
        background.close()
        shader.close()
        if launch is not None:
            launch.close()
    timings = time_methods(seq, config, (*methods, "mesh"), refiner, device, metaball)
    result = {m: _summary(m, scores, timings) for m in methods}
    if "metaball" in methods:
        errors = summarize_angles(np.concatenate(own["errors"]) if own["errors"] else np.zeros(0))
        surface = summarize_angles(np.concatenate(own["surface"]) if own["surface"] else np.zeros(0))
        result["metaball"].update({f"own_{k}": v for k, v in errors.items()}, own_iou=float(np.mean(own["iou"])),
                                  own_frames=len(own["iou"]), **{f"surface_{k}": v for k, v in surface.items()})
    result["mesh"] = {"ms_per_frame": timings["mesh"]}
    return {"scene": seq.scene.name, "camera": seq.camera, "frames": len(records), "size": [width, height],
            "radius_px": float(np.median(radii)) if radii else 0.0, "methods": result, "examples": examples}


def _score_change(ss: ScreenSpace, before: dict, after: dict, methods, radius: float, scores: dict) -> None:
    """Each method's per-pixel temporal errors from one evaluated frame to the next."""
    cams = before["cam"], after["cam"]
    flow = surface_flow(ss, before["x"], after["x"], radius, *cams, before["depth"], before["t_mask"], after["depth"],
                        after["t_mask"])
    truth = normal_change(flow, before["target"], after["target"], after["t_mask"], *cams)
    for m in methods:
        e, missed = temporal_errors(flow, before["maps"][m][:2], after["maps"][m][:2], truth, *cams)
        scores["temporal"][m].append(e)
        scores["temporal_missed"][m].append(missed)


def _summary(m: str, scores: dict, timings: dict) -> dict:
    per_frame = scores["per_frame"][m]
    steps = np.abs(np.diff(np.array(per_frame)))
    steps = steps[np.isfinite(steps)]  # frames where a method shows no fluid have no error
    errors, on_mask = scores["errors"][m], scores["on_mask"][m]
    summary = summarize_angles(np.concatenate(errors) if errors else np.zeros(0))
    shared = np.concatenate(on_mask) if on_mask else np.zeros(0)
    temporal = np.concatenate(scores["temporal"][m]) if scores["temporal"][m] else np.zeros(0)
    followed = temporal.size + sum(scores["temporal_missed"][m])
    # a sequence of one frame has no change to measure: NaN, left out of the averages
    return {**summary, "missed": sum(scores["missed"][m]) / max(summary["pixels"], 1),
            "mask_mean_deg": float(shared.mean()) if shared.size else float("nan"),
            "iou": float(np.mean(scores["iou"][m])), "psnr": float(np.mean(scores["psnr"][m])),
            "ssim": float(np.mean(scores["ssim"][m])),
            "flicker_deg": float(steps.mean()) if steps.size else float("nan"),
            "temporal_deg": float(temporal.mean()) if temporal.size else float("nan"),
            "temporal_pixels": int(temporal.size),
            "temporal_missed": sum(scores["temporal_missed"][m]) / followed if followed else float("nan"),
            "ms_per_frame": timings.get(m, float("nan")), "per_frame_mean_deg": per_frame}


def time_methods(seq: HeldOut, config: Config, methods, refiner, device: str, metaball=None) -> dict[str, float]:
    """Wall milliseconds per frame of each method from particles to its normal map (first frames;
    on a GPU until its work is done, not only queued: the refined maps stay there as tensors)."""
    wdev = warp_device(device)
    ss, launch = ScreenSpace(wdev), Launcher(wdev)
    p = config.dataset
    frames = [r["frame"] for r in seq.records[:TIMED_FRAMES]]
    out = {}
    try:
        for m in methods:
            t = Timings(sync=True)
            for i, frame in enumerate(frames):
                x, _ = load_frame(seq.sim_dir / frame_name(frame))
                cam = camera_for_frame(seq.scene.cameras, seq.camera, i, len(seq.records), p.width, p.height)
                with t("total"):
                    normal_source(m, x, seq.particle_radius, cam, p, ss, launch, refiner,
                                  config.render.normal_threshold, metaball=metaball)
            out[m] = round(t.mean_ms("total"), 1)
    finally:
        ss.close()
        launch.close()
    return out


def aggregate(results: list[dict], methods) -> dict:
    """Pixel-weighted means over all sequences, per method."""
    table = {}
    for m in methods:
        rows = [r["methods"][m] for r in results]
        w = np.array([row["pixels"] for row in rows], float)
        w = w / max(w.sum(), 1)
        table[m] = {k: float(np.nansum([row[k] * wi for row, wi in zip(rows, w, strict=True)]))
                    for k in ("mean_deg", "under_5", "under_10", "under_20", "missed")}
        shared = np.array([row["pixels"] * (1 - row["missed"]) for row in rows], float)
        table[m]["mask_mean_deg"] = float(np.nansum([row["mask_mean_deg"] * wi for row, wi in
                                                     zip(rows, shared / max(shared.sum(), 1), strict=True)]))
        table[m]["median_deg"] = float(np.nanmedian([row["median_deg"] for row in rows]))
        for k in ("iou", "psnr", "ssim", "flicker_deg", "ms_per_frame"):
            table[m][k] = float(np.nanmean([row[k] for row in rows]))
        # per-pixel temporal error: pixel-weighted over the sequences of more than one frame
        w = np.array([row["temporal_pixels"] for row in rows], float)
        table[m]["temporal_deg"] = (sum(row["temporal_deg"] * wi for row, wi in zip(rows, w, strict=True) if wi)
                                    / w.sum() if w.sum() else float("nan"))
    if "metaball" in methods:  # against its own ray-marched surface
        rows = [r["methods"]["metaball"] for r in results]
        w = np.array([row["own_pixels"] for row in rows], float)
        table["metaball"]["own_mean_deg"] = float(np.nansum([row["own_mean_deg"] * wi for row, wi in
                                                             zip(rows, w / max(w.sum(), 1), strict=True)]))
        table["metaball"]["own_median_deg"] = float(np.nanmedian([row["own_median_deg"] for row in rows]))
        table["metaball"]["own_iou"] = float(np.nanmean([row["own_iou"] for row in rows]))
        w = np.array([row["surface_pixels"] for row in rows], float)
        table["metaball"]["surface_mean_deg"] = float(np.nansum([row["surface_mean_deg"] * wi for row, wi in
                                                                 zip(rows, w / max(w.sum(), 1), strict=True)]))
        table["metaball"]["surface_median_deg"] = float(np.nanmedian([row["surface_median_deg"] for row in rows]))
    table["mesh"] = {"ms_per_frame": float(np.nanmean([r["methods"]["mesh"]["ms_per_frame"] for r in results]))}
    return table
