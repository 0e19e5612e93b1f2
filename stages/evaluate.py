"""``make evaluate``: every method against the mesh reference on held-out sequences.

Held out: every frame of ``dataset.holdout_scenes``, the validation camera path of the other
scenes, and the imported particle scenes of ``evaluate.imported_scenes``. Per method: normal
error (mean, median, share under 5 / 10 / 20 degrees), silhouette IoU, PSNR and SSIM of the shaded
image against the shaded mesh, temporal flicker, and milliseconds per frame. Writes
``data/evaluate/<config>-<key>/report.md``, ``metrics.json`` and PNG figures.
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity
from tqdm import tqdm

from pipeline import cache
from pipeline.camera import camera_for_frame
from pipeline.config import SceneConfig, to_dict
from pipeline.device import warp_device
from pipeline.exr import read_exr, stack
from pipeline.frames import frame_name, load_frame, read_sequence_info
from pipeline.metrics import angular_errors, iou, summarize_angles
from pipeline.model.data import input_channels
from pipeline.parallel import Launcher
from pipeline.plots import evaluation_figures
from pipeline.render import method_maps, normal_source, refine, shade_frame
from pipeline.screen import ScreenSpace
from pipeline.shading import Shader, tonemap
from pipeline.shading.background import BackgroundRenderer
from pipeline.timing import Timings
from stages import dataset, render, simulate
from stages.common import Run, make_run, parse_args, stage_main

log = logging.getLogger("deep_ssfr")
TIMED_FRAMES = 3


def sequences(run: Run) -> list[tuple[SceneConfig, str]]:
    """(scene, camera path) pairs that training never saw."""
    cfg = run.config
    out = []
    for scene in run.loaded.scenes.values():
        if scene.name in cfg.dataset.holdout_scenes:
            out += [(scene, c) for c in dataset.CAMERAS]
        elif cfg.dataset.validation_camera != "none":
            out.append((scene, cfg.dataset.validation_camera))
    out += [(scene, c) for scene in run.loaded.imported.values() for c in dataset.CAMERAS]
    return out


def _method_maps(method: str, ch: dict, refiner, threshold: float):
    """(normals, mask, depth) of a method from a dataset frame's channels."""
    if method == "refined":
        n, mask = refine(refiner, ch, threshold)
        return n, mask, ch[input_channels(refiner.splat).blurred]
    if method == "mesh":
        return stack(ch, "target.N."), ch["target.A"] > 0, ch["target.Z"]
    maps = method_maps(method, ch)
    return maps["normals"], maps["mask"] > 0, maps["depth"]


def evaluate_sequence(run: Run, scene: SceneConfig, camera_path: str, refiner,
                      methods: tuple[str, ...]) -> dict:
    """Per-method metrics of one held-out sequence, plus per-frame errors for the figures."""
    p, rp = run.config.evaluate, run.config.render
    entry = dataset.ensure(run, scene)
    records = [r for r in entry.manifest()["frames"] if r["camera"] == camera_path]
    path_frames = len(records)
    if p.max_frames:
        records = [records[int(i)] for i in np.linspace(0, len(records) - 1, min(p.max_frames, len(records))).round()]
    width, height = run.config.dataset.width, run.config.dataset.height
    device = warp_device(run.device)
    shader = Shader(device)
    background = BackgroundRenderer(scene, rp, width, height)
    errors = {m: [] for m in methods}
    per_frame = {m: [] for m in methods}
    ious = {m: [] for m in methods}
    psnr = {m: [] for m in methods}
    ssim = {m: [] for m in methods}
    examples = []
    try:
        for r in tqdm(records, desc=f"evaluate {scene.name}/{camera_path}", unit="frame", leave=False):
            ch = read_exr(entry.path(r["file"]))
            cam = camera_for_frame(scene.cameras, camera_path, r["index"], path_frames, width, height)
            bg, bg_depth = background.render(cam)
            bg = shader.fill_sky(bg, bg_depth, cam, rp)
            target = stack(ch, "target.N.")
            t_mask = ch["target.A"] > 0
            maps = {m: _method_maps(m, ch, refiner, rp.normal_threshold) for m in (*methods, "mesh")}
            shaded = {}
            for m, (n, mask, depth) in maps.items():
                src = {"normals": n.astype(np.float32), "depth": np.where(mask, depth, 0).astype(np.float32),
                       "mask": mask.astype(np.float32), "thickness": ch["thickness"]}
                shaded[m] = tonemap(shade_frame(src, bg, bg_depth, cam, rp, shader).beauty).astype(np.float32) / 255
                if m == "mesh":
                    continue
                e = angular_errors(n, target, mask & t_mask)
                errors[m].append(e)
                per_frame[m].append(float(e.mean()) if e.size else float("nan"))
                ious[m].append(iou(mask, t_mask))
            if len(examples) < 3 and t_mask.mean() > 0.02 and r["index"] % 4 == 0:
                examples.append({"scene": scene.name, "frame": r["frame"], "target": target,
                                 **{m: maps[m][0] for m in methods}})
            for m in methods:
                psnr[m].append(peak_signal_noise_ratio(shaded["mesh"], shaded[m], data_range=1.0))
                ssim[m].append(structural_similarity(shaded["mesh"], shaded[m], channel_axis=-1, data_range=1.0))
    finally:
        background.close()
        shader.close()
    timings = time_methods(run, scene, camera_path, (*methods, "mesh"), refiner)
    result = {}
    for m in methods:
        steps = np.abs(np.diff(np.array(per_frame[m])))
        steps = steps[np.isfinite(steps)]  # frames where a method shows no fluid have no error
        flicker = float(steps.mean()) if steps.size else 0.0
        result[m] = {**summarize_angles(np.concatenate(errors[m]) if errors[m] else np.zeros(0)),
                     "iou": float(np.mean(ious[m])), "psnr": float(np.mean(psnr[m])),
                     "ssim": float(np.mean(ssim[m])), "flicker_deg": flicker,
                     "ms_per_frame": timings.get(m, float("nan")), "per_frame_mean_deg": per_frame[m]}
    result["mesh"] = {"ms_per_frame": timings["mesh"]}
    return {"scene": scene.name, "camera": camera_path, "frames": len(records), "methods": result,
            "examples": examples}


def time_methods(run: Run, scene: SceneConfig, camera_path: str, methods, refiner) -> dict[str, float]:
    """Wall milliseconds per frame of each method from particles to its normal map (first frames)."""
    sim = simulate.ensure(run, scene)
    info = read_sequence_info(sim.dir)
    device = warp_device(run.device)
    ss, launch = ScreenSpace(device), Launcher(device)
    p = run.config.dataset
    out = {}
    try:
        for m in methods:
            t = Timings()
            for i in range(min(TIMED_FRAMES, info.frames)):
                x, _ = load_frame(sim.path(frame_name(i + 1)))
                cam = camera_for_frame(scene.cameras, camera_path, i, info.frames, p.width, p.height)
                with t("total"):
                    normal_source(m, x, info.particle_radius, cam, p, ss, launch, refiner,
                                  run.config.render.normal_threshold)
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
                    for k in ("mean_deg", "under_5", "under_10", "under_20")}
        table[m]["median_deg"] = float(np.nanmedian([row["median_deg"] for row in rows]))
        for k in ("iou", "psnr", "ssim", "flicker_deg", "ms_per_frame"):
            table[m][k] = float(np.nanmean([row[k] for row in rows]))
    table["mesh"] = {"ms_per_frame": float(np.nanmean([r["methods"]["mesh"]["ms_per_frame"] for r in results]))}
    return table


def write_report(folder: Path, results: list[dict], table: dict, methods, weights: str) -> None:
    """report.md with the overall table, per-sequence tables and figures."""
    names = {"gaussian": "Gaussian", "bilateral": "bilateral", "nrf": "narrow-range", "aniso": "ellipsoids",
             "aniso_nrf": "ellipsoids + narrow-range", "refined": "refined (cGAN)"}
    lines = ["# Evaluation: normal maps against the anisotropic marching-cubes mesh", "",
             f"Held-out sequences: {len(results)}; generator checkpoint `{weights}`. Errors are over pixels where "
             "both the method and the mesh show fluid; PSNR/SSIM compare the shaded image with the shaded mesh "
             "(tone-mapped, [0, 1]); flicker is the mean frame-to-frame change of the mean error.", "",
             "| method | mean (deg) | median (deg) | < 5 deg | < 10 deg | < 20 deg | IoU | PSNR (dB) | SSIM | "
             "flicker (deg) | ms/frame |", "|" + "---|" * 11]
    for m in methods:
        r = table[m]
        lines.append(f"| {names.get(m, m)} | {r['mean_deg']:.2f} | {r['median_deg']:.2f} | {100 * r['under_5']:.1f}% "
                     f"| {100 * r['under_10']:.1f}% | {100 * r['under_20']:.1f}% | {r['iou']:.3f} | {r['psnr']:.2f} "
                     f"| {r['ssim']:.3f} | {r['flicker_deg']:.2f} | {r['ms_per_frame']:.0f} |")
    lines += [f"| mesh (reference) | 0 | 0 | | | | 1 | | | | {table['mesh']['ms_per_frame']:.0f} |", "",
              "![mean error per method](methods.png)", "", "![error over frames](frames.png)", "",
              "![examples](examples.png)", "", "## Per sequence", ""]
    for res in results:
        lines += [f"### {res['scene']} / {res['camera']} ({res['frames']} frames)", "",
                  "| method | mean (deg) | < 10 deg | IoU | PSNR | SSIM |", "|---|---|---|---|---|---|"]
        for m in methods:
            r = res["methods"][m]
            lines.append(f"| {names.get(m, m)} | {r['mean_deg']:.2f} | {100 * r['under_10']:.1f}% | {r['iou']:.3f} "
                         f"| {r['psnr']:.2f} | {r['ssim']:.3f} |")
        lines.append("")
    with cache.atomic_path(folder / "report.md") as tmp:
        tmp.write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``make evaluate``."""
    run = make_run(parse_args("evaluate", argv))
    methods = tuple(run.config.evaluate.methods)
    refiner, weights = render.load_refiner(run) if "refined" in methods else (None, "")
    seqs = sequences(run)
    keys = {f"{s.name}/{c}": dataset.ensure(run, s).key for s, c in seqs}
    entry = cache.entry(run.data_dir, "evaluate", Path(run.loaded.path).stem,
                        {"evaluate": to_dict(run.config.evaluate), "render": to_dict(run.config.render)},
                        {**keys, "weights": weights}, run.device)
    if entry.is_complete() and not run.force:
        log.info("evaluate: cached (%s)", entry.dir / "report.md")
        return
    entry.begin(force=run.force)
    start = time.perf_counter()
    results = [evaluate_sequence(run, s, c, refiner, methods) for s, c in seqs]
    table = aggregate(results, methods)
    evaluation_figures(entry.dir, results, table, methods)
    write_report(entry.dir, results, table, methods, weights)
    slim = [{k: v for k, v in r.items() if k != "examples"} for r in results]
    cache.write_json_atomic(entry.path("metrics.json"), {"overall": table, "sequences": slim})
    entry.finish(["report.md", "metrics.json", "methods.png", "frames.png", "examples.png"], {},
                 wall_seconds=round(time.perf_counter() - start, 1))
    for m in methods:
        r = table[m]
        log.info("evaluate %-9s mean %6.2f deg, <10 deg %5.1f%%, IoU %.3f, PSNR %.2f, SSIM %.3f, %.0f ms/frame", m,
                 r["mean_deg"], 100 * r["under_10"], r["iou"], r["psnr"], r["ssim"], r["ms_per_frame"])
    log.info("evaluate: report in %s", entry.path("report.md"))


if __name__ == "__main__":
    sys.exit(stage_main("evaluate", main))
