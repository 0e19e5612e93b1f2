"""The shipped generator: it loads from the package alone and beats its input on unseen data;
``make demo`` runs end to end on a shrunk default."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from pipeline.camera import camera_for_frame
from pipeline.config_files import load
from pipeline.masks import normal_mask
from pipeline.methods import refine
from pipeline.metrics import angular_errors
from pipeline.model import SHIPPED_WEIGHTS as SHIPPED
from pipeline.model.data import input_channels
from pipeline.model.inference import load_refiner
from pipeline.model.trainer import load_generator
from pipeline.parallel import Launcher
from pipeline.screen import ScreenSpace
from pipeline.sim.pbf import PBFSolver
from pipeline.surface import particle_ellipsoids, reconstruct
from pipeline.views import screen_space_inputs, target_channels
from stages import cli
from tests.conftest import ROOT


def test_shipped_weights_load_with_their_config_and_metrics():
    generator, meta = load_generator(SHIPPED)
    card = json.loads(SHIPPED.with_suffix(".json").read_text())
    assert meta["config"]["auxiliary_features"] is True
    assert card["held_out"]["refined"]["mean_deg"] < card["held_out"]["bilateral"]["mean_deg"]
    assert SHIPPED.stat().st_size < 20 * 2**20
    assert generator.stride == 2 ** meta["generator_args"]["downsamples"]


@pytest.mark.slow
def test_shipped_weights_beat_the_bilateral_input_on_an_unseen_scene():
    """Merging is held out of the default training set: simulate it afresh (another seed), build
    one frame's input and mesh target, and compare angular errors against the mesh."""
    loaded = load(ROOT / "configs" / "default.yaml")
    assert "merging" in loaded.config.dataset.holdout_scenes
    scene = loaded.scenes["merging"]
    solver = PBFSolver(scene, loaded.config.simulate, "cpu", seed=12345)
    for f in range(1, 41):
        solver.advance_frame(f)
    x, _ = solver.state()
    solver.close()
    p = loaded.config.dataset
    r = loaded.config.simulate.particle_radius
    ss, launch = ScreenSpace("cpu"), Launcher("cpu")
    cam = camera_for_frame(scene.cameras, "orbit", 20, 50, p.width, p.height)
    ch = screen_space_inputs(x, r, cam, p, ss, filters=("bilateral",),
                             ellipsoids=particle_ellipsoids(x, r, p, launch, density=True),
                             aniso_filters=("bilateral",))
    ch.update(target_channels(reconstruct(x, r, p, launch), cam, launch))
    ss.close()
    launch.close()
    refiner = load_refiner(SHIPPED)
    refined, mask, _ = refine(refiner, ch, 0.5, cam.focal_px, r)
    target = np.stack([ch[f"target.N.{a}"] for a in "XYZ"], -1)
    given = np.stack([ch[name] for name in input_channels(refiner.splat).normal], -1)
    t_mask = normal_mask(target)
    e_refined = angular_errors(refined, target, mask & t_mask)
    e_input = angular_errors(given, target, normal_mask(given) & t_mask)
    assert t_mask.mean() > 0.05
    assert e_refined.mean() < e_input.mean(), (e_refined.mean(), e_input.mean())


def test_demo_runs_end_to_end_shrunk(tmp_path, capsys):
    body = {"base": str(ROOT / "configs" / "default.yaml"), "data_dir": str(tmp_path / "data"),
            "simulate": {"particle_radius": 0.03, "frames": 4},
            "render": {"width": 64, "height": 64}}
    config = tmp_path / "demo.yaml"
    config.write_text(yaml.safe_dump(body))
    assert cli.main(["demo", "--config", str(config)]) == 0
    out = capsys.readouterr().out
    assert "dam_break_comparison_sheet.png" in out and "frame_0001.exr" in out
    (entry,) = (tmp_path / "data" / "render").iterdir()
    assert len(list((entry / "frames").glob("*.exr"))) == 4
    assert (entry / "dam_break_refined.mp4").stat().st_size > 0
