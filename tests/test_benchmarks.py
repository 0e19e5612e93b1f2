"""The benchmarks keep running with the shipped weights: a small measurement of ``bench_render.py``
(the density weights once broke its plain forward pass, and no test noticed)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def test_bench_render_measures_a_frame_with_the_shipped_weights(tmp_path):
    import bench_render

    from pipeline.config import DatasetConfig
    from pipeline.parallel import Launcher
    from pipeline.particles import read_particles
    from pipeline.screen import ScreenSpace
    from pipeline.shading import Shader

    refiner, generator = bench_render.shipped_refiner("cpu")
    x = read_particles(ROOT / "tests" / "data" / "dam_break_frame_9_6859_particles.bgeo").positions
    launch, shader = Launcher("cpu"), Shader("cpu")
    try:
        row = bench_render.measure(x, 0.025, 64, DatasetConfig(), ScreenSpace("cpu"), launch, shader, refiner,
                                   generator, 1, tmp_path)
    finally:
        shader.close()
        launch.close()
    assert row["rp_px"] > 0  # the fluid is in view
    for step in ("inputs", "refiner", "plain_refiner", "pipelined_frame"):
        assert row[step] > 0, step
    if refiner.spec.density:
        with pytest.raises(SystemExit, match="density"):
            bench_render.shipped_refiner("cpu", "sphere")
