"""``make evaluate``: every method against the mesh reference on held-out sequences.

Held out: every frame of ``dataset.holdout_scenes``, the validation camera path of the other
scenes, and the imported particle scenes of ``evaluate.imported_scenes`` (metrics:
``pipeline.evaluate``). Writes ``data/evaluate/<config>-<key>/report.md``, ``metrics.json`` and PNG
figures.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from pipeline import cache
from pipeline.config import to_dict
from pipeline.dataset import CAMERAS
from pipeline.evaluate.report import write_report
from pipeline.evaluate.sequence import HeldOut, aggregate, evaluate_sequence
from pipeline.executor import run_tasks
from pipeline.frames import read_sequence_info
from pipeline.plots import evaluation_figures
from stages import dataset, render, simulate
from stages.common import Run, StageOptions, make_run

log = logging.getLogger("deep_ssfr")


def sequences(run: Run) -> list[HeldOut]:
    """The sequences training never saw: every camera of the held-out and imported scenes, the
    validation camera of the others. Scenes that chose the trainer's best checkpoint
    (``train.validation_scenes``) are left out."""
    cfg = run.config
    pairs = []
    for scene in run.loaded.scenes.values():
        if scene.name in cfg.train.validation_scenes:
            continue
        if scene.name in cfg.dataset.holdout_scenes:
            pairs += [(scene, c) for c in CAMERAS]
        elif cfg.dataset.validation_camera != "none":
            pairs.append((scene, cfg.dataset.validation_camera))
    pairs += [(scene, c) for scene in run.loaded.imported.values() for c in CAMERAS]
    simulate.ahead(run, list({scene.name: scene for scene, _ in pairs}.values()))
    out = []
    for scene, camera in pairs:
        entry, sim = dataset.ensure(run, scene), simulate.ensure(run, scene)
        records = [r for r in entry.manifest()["frames"] if r["camera"] == camera]
        out.append(HeldOut(scene, camera, records, entry.dir, sim.dir, read_sequence_info(sim.dir).particle_radius))
    return out


def sized_runs(opts: StageOptions) -> list[Run]:
    """One run per evaluated size (``evaluate.sizes``; the dataset's own size when empty), each reading
    the held-out views of that size."""
    run = make_run(opts)
    sizes = run.config.evaluate.sizes
    if not sizes:
        return [run]
    return [make_run(opts, {"dataset": {"width": s, "height": s}}) for s in sizes]


def main(opts: StageOptions) -> None:
    """``deep-ssfr evaluate``."""
    runs = sized_runs(opts)
    run = runs[0]
    methods = tuple(run.config.evaluate.methods)
    # 'trained' weights come from the config's own training views, not from one evaluated size's
    refiner, metaball, weights = render.networks(make_run(opts) if run.config.evaluate.sizes else run, methods)
    groups = [(r, sequences(r)) for r in runs]
    keys = {f"{r.config.dataset.width}/{s.scene.name}/{s.camera}": dataset.ensure(r, s.scene).key
            for r, group in groups for s in group}
    config = {"evaluate": to_dict(run.config.evaluate), "render": to_dict(run.config.render)}
    if metaball is not None:
        config["metaball"] = to_dict(run.config.metaball)
    entry = cache.entry(run.data_dir, "evaluate", Path(run.loaded.path).stem, config, {**keys, "weights": weights},
                        run.device)
    if not entry.begin(force=run.force):
        log.info("evaluate: cached (%s)", entry.dir / "report.md")
        return
    start = time.perf_counter()
    by_size = {}
    for r, group in groups:
        size, cfg, device = r.config.dataset.width, r.config, r.device  # a Ray task carries these, not the run
        results = run_tasks(lambda s, cfg=cfg, device=device: evaluate_sequence(s, cfg, refiner, methods, device,
                                                                                metaball),
                            group, cfg.executor, cfg.ray_address, device)
        by_size[size] = (results, aggregate(results, methods))
        for m in methods:
            t = by_size[size][1][m]
            log.info("evaluate %4d px %-9s mean %6.2f deg, median %5.2f, <10 deg %5.1f%%, IoU %.3f, PSNR %.2f, "
                     "flicker %.2f, temporal %.2f, %.0f ms/frame", size, m, t["mean_deg"], t["median_deg"],
                     100 * t["under_10"], t["iou"], t["psnr"], t["flicker_deg"], t["temporal_deg"], t["ms_per_frame"])
        if "metaball" in methods:
            t = by_size[size][1]["metaball"]
            log.info("evaluate %4d px metaball against its own ray-marched surface: mean %6.2f deg, median %5.2f, "
                     "IoU %.3f", size, t["own_mean_deg"], t["own_median_deg"], t["own_iou"])
    first = next(iter(by_size))
    evaluation_figures(entry.dir, *by_size[first], methods)
    write_report(entry.dir, by_size, methods, weights)
    slim = {str(size): {"overall": table, "sequences": [{k: v for k, v in r.items() if k != "examples"}
                                                        for r in results]}
            for size, (results, table) in by_size.items()}
    cache.write_json_atomic(entry.path("metrics.json"), {"overall": by_size[first][1],
                                                          "sequences": slim[str(first)]["sequences"], "sizes": slim})
    entry.finish(["report.md", "metrics.json", "methods.png", "frames.png", "examples.png"], {},
                 wall_seconds=round(time.perf_counter() - start, 1))
    log.info("evaluate: report in %s", entry.path("report.md"))
