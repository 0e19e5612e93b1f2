"""``make evaluate``: every method against the mesh reference on held-out sequences.

Held out: every frame of ``dataset.holdout_scenes``, the validation camera path of the other
scenes, and the imported particle scenes of ``evaluate.imported_scenes`` (metrics:
``pipeline.evaluate``). Writes ``data/evaluate/<config>-<key>/report.md``, ``metrics.json`` and PNG
figures.
"""

from __future__ import annotations

import logging
import sys
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
    validation camera of the others."""
    cfg = run.config
    pairs = []
    for scene in run.loaded.scenes.values():
        if scene.name in cfg.dataset.holdout_scenes:
            pairs += [(scene, c) for c in CAMERAS]
        elif cfg.dataset.validation_camera != "none":
            pairs.append((scene, cfg.dataset.validation_camera))
    pairs += [(scene, c) for scene in run.loaded.imported.values() for c in CAMERAS]
    out = []
    for scene, camera in pairs:
        entry, sim = dataset.ensure(run, scene), simulate.ensure(run, scene)
        records = [r for r in entry.manifest()["frames"] if r["camera"] == camera]
        out.append(HeldOut(scene, camera, records, entry.dir, sim.dir, read_sequence_info(sim.dir).particle_radius))
    return out


def main(opts: StageOptions) -> None:
    """``deep-ssfr evaluate``."""
    run = make_run(opts)
    methods = tuple(run.config.evaluate.methods)
    refiner, weights = render.load_refiner(run) if "refined" in methods else (None, "")
    seqs = sequences(run)
    keys = {f"{s.scene.name}/{s.camera}": dataset.ensure(run, s.scene).key for s in seqs}
    entry = cache.entry(run.data_dir, "evaluate", Path(run.loaded.path).stem,
                        {"evaluate": to_dict(run.config.evaluate), "render": to_dict(run.config.render)},
                        {**keys, "weights": weights}, run.device)
    if not entry.begin(force=run.force):
        log.info("evaluate: cached (%s)", entry.dir / "report.md")
        return
    start = time.perf_counter()
    cfg, device = run.config, run.device  # a Ray task carries these, not the run
    results = run_tasks(lambda s: evaluate_sequence(s, cfg, refiner, methods, device), seqs, cfg.executor,
                        cfg.ray_address)
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
    from stages.cli import main as cli

    sys.exit(cli(["evaluate", *sys.argv[1:]]))
