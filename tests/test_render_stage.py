"""Render and evaluate smoke tests (2 frames, 64x64), output naming, videos, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import yaml

from pipeline.config import TrainConfig
from pipeline.exr import read_exr, read_exr_header, stack
from pipeline.media import count_video_frames, write_video
from pipeline.methods import channel_names
from pipeline.model.trainer import Refiner
from stages import cli
from tests.conftest import ROOT


def _config(tmp_path, weights: str, **render_opts) -> str:
    body = yaml.safe_load((ROOT / "configs" / "default.yaml").read_text())
    body.update({"scenes": ["dam_break", "merging"], "scene_dir": str(ROOT / "configs" / "scenes"),
                 "data_dir": str(tmp_path / "data")})
    body["simulate"].update({"particle_radius": 0.03, "frames": 4})
    body["dataset"] = {"width": 64, "height": 64, "frame_stride": 2, "holdout_scenes": ["merging"]}
    body["render"] = {"width": 64, "height": 64, "frame_stride": 2, "weights": weights, **render_opts}
    body["evaluate"] = {"frames_per_sequence": 2, "imported_scenes": ["splishsplash_double_dam_break"]}
    path = tmp_path / "default_small.yaml"
    path.write_text(yaml.safe_dump(body))
    return str(path)


def _record(entry, name: str) -> None:
    """Update a finished entry's manifest for a file a test replaced on purpose."""
    from pipeline.cache import HASH, file_hash

    manifest = json.loads((entry / "manifest.json").read_text())
    manifest["checks"][name] = {"size": (entry / name).stat().st_size, HASH: file_hash(entry / name)}
    (entry / "manifest.json").write_text(json.dumps(manifest))


def _tiny_checkpoint(tmp_path, splat: str = "sphere") -> str:
    cfg = TrainConfig(gen_base_channels=8, gen_res_blocks=1, disc_base_channels=8, disc_layers=2, input_splat=splat)
    path = tmp_path / f"tiny_{splat}.pt"
    torch.save(Refiner(cfg).state(0), path)
    return str(path)


def test_render_writes_named_exr_sequence_video_and_comparison(tmp_path):
    config = _config(tmp_path, _tiny_checkpoint(tmp_path), comparison=True)
    assert cli.main(["render", "--config", config, "--scene", "dam_break"]) == 0
    (entry,) = (tmp_path / "data" / "render").iterdir()
    exrs = sorted((entry / "frames").glob("*.exr"))
    assert [p.name for p in exrs] == ["frame_0001.exr", "frame_0003.exr"]
    ch = read_exr(exrs[-1])
    assert set(ch) == set(channel_names())
    beauty = stack(ch, "ViewLayer.Combined.", "RGBA")
    assert beauty.shape == (64, 64, 4) and np.isfinite(beauty).all() and (beauty[..., 3] == 1).all()
    fluid_alpha = ch["ViewLayer.Fluid.A"]
    assert fluid_alpha.max() == 1.0 and fluid_alpha.min() == 0.0, "fluid over a visible background"
    assert (ch["ViewLayer.Depth.Z"] > 0).all()
    assert np.abs(stack(ch, "ViewLayer.Vector.", "XYZW")[fluid_alpha > 0]).max() > 0, "the fluid moves"
    assert "worldToCamera" in read_exr_header(exrs[-1])
    assert count_video_frames(entry / "dam_break_refined.mp4") == 2
    assert count_video_frames(entry / "dam_break_comparison.mp4") == 2
    assert len(list((entry / "preview").glob("*.png"))) == 2
    # encoded while rendering, the videos are the ones a resumed run makes from the PNGs, byte for byte
    for video, stills in (("dam_break_refined.mp4", "preview"), ("dam_break_comparison.mp4", "compare")):
        write_video(tmp_path / video, sorted((entry / stills).glob("*.png")), 30.0)
        assert (tmp_path / video).read_bytes() == (entry / video).read_bytes()
    assert (entry / "dam_break_comparison_sheet.png").exists()
    from PIL import Image

    # bilateral | narrow-range | refined | metaballs | mesh
    assert Image.open(entry / "compare" / "frame_0001.png").size == (5 * 64, 64)
    manifest = json.loads((entry / "manifest.json").read_text())
    assert {"inputs", "refiner", "shading", "motion", "exr_write"} <= set(manifest["ms_per_frame"])
    assert len(manifest["weights"].split("+")) == 2, "keyed on both generators"


def _render_single_method(tmp_path, method: str):
    """Render the dam break with one method and no comparison; the entry and frame 3's fluid mask,
    after checking that the fluid's depths are positive and its view normals unit length."""
    config = _config(tmp_path, _tiny_checkpoint(tmp_path), method=method, comparison=False)
    assert cli.main(["render", "--config", config, "--scene", "dam_break"]) == 0
    (entry,) = (tmp_path / "data" / "render").iterdir()
    ch = read_exr(entry / "frames" / "frame_0003.exr")
    fluid = ch["ViewLayer.Fluid.A"] > 0
    assert (ch["ViewLayer.Depth.Z"][fluid] > 0).all()
    n = stack(ch, "ViewLayer.ViewNormal.")[fluid]
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1, atol=5e-4)  # stored as half: within 4.1e-4
    return entry, fluid


def test_render_with_the_metaball_method(tmp_path):
    entry, fluid = _render_single_method(tmp_path, "metaball")
    assert fluid.mean() > 0.05
    assert "metaball" in json.loads((entry / "manifest.json").read_text())["ms_per_frame"]


def test_missing_model_is_a_clear_error(tmp_path, capsys):
    config = _config(tmp_path, str(tmp_path / "nope.pt"))
    assert cli.main(["render", "--config", config, "--scene", "dam_break"]) == 1
    err = capsys.readouterr().err
    assert "nope.pt" in err and "make train" in err


def test_empty_frames_and_blind_cameras_still_render(tmp_path, caplog):
    caplog.set_level("WARNING")
    config = _config(tmp_path, _tiny_checkpoint(tmp_path), method="bilateral", comparison=False)
    scene_dir = tmp_path / "scenes"
    scene_dir.mkdir()
    blind = yaml.safe_load((ROOT / "configs" / "scenes" / "dam_break.yaml").read_text())
    blind["cameras"]["static"] = {"eye": [0.8, 0.5, 5.0], "target": [0.8, 0.5, 9.0]}  # looking away
    (scene_dir / "dam_break.yaml").write_text(yaml.safe_dump(blind))
    body = yaml.safe_load(open(config))
    body["scene_dir"] = str(scene_dir)
    body["evaluate"]["imported_scenes"] = []
    open(config, "w").write(yaml.safe_dump(body))
    assert cli.main(["render", "--config", config, "--scene", "dam_break"]) == 0
    assert "sees no fluid in 2 frames" in caplog.text
    (entry,) = (tmp_path / "data" / "render").iterdir()
    assert len(list((entry / "frames").glob("*.exr"))) == 2


def test_an_empty_particle_frame_renders_background_and_the_rest_render(tmp_path, caplog):
    from pipeline.frames import save_frame

    caplog.set_level("WARNING")
    config = _config(tmp_path, _tiny_checkpoint(tmp_path), method="nrf", comparison=False)
    assert cli.main(["simulate", "--config", config, "--scene", "dam_break"]) == 0
    (sim,) = (tmp_path / "data" / "simulate").iterdir()
    save_frame(sim / "frame_0003.npz", np.zeros((0, 3), np.float32), None)
    _record(sim, "frame_0003.npz")  # as if the simulation had written it (else it is redone as damaged)
    assert cli.main(["render", "--config", config, "--scene", "dam_break"]) == 0
    assert "sees no fluid in 1 frames (first: 3)" in caplog.text
    (entry,) = (tmp_path / "data" / "render").iterdir()
    first = read_exr(entry / "frames" / "frame_0001.exr")
    empty = read_exr(entry / "frames" / "frame_0003.exr")
    assert first["ViewLayer.Fluid.A"].any() and not empty["ViewLayer.Fluid.A"].any()
    assert np.isfinite(empty["ViewLayer.Combined.R"]).all()


@pytest.mark.slow
def test_evaluate_smoke(tmp_path):
    config = _config(tmp_path, _tiny_checkpoint(tmp_path))
    body = yaml.safe_load(open(config))
    body["evaluate"]["sizes"] = [64, 96]
    body["evaluate"]["methods"] = ["gaussian", "bilateral", "nrf", "aniso", "aniso_nrf", "refined", "metaball"]
    open(config, "w").write(yaml.safe_dump(body))
    assert cli.main(["evaluate", "--config", config]) == 0
    (entry,) = (tmp_path / "data" / "evaluate").iterdir()
    report = (entry / "report.md").read_text()
    assert "## 64 x 64" in report and "## 96 x 96" in report and "Refined against the filters" in report
    for method in ("Gaussian", "bilateral", "narrow-range", "ellipsoids", "ellipsoids + narrow-range",
                   "refined (cGAN)", "metaballs (network)", "mesh (reference)"):
        assert method in report
    assert "Metaballs against their own ray-marched surface" in report
    metrics = json.loads((entry / "metrics.json").read_text())
    # held out: both cameras of merging, the orbit of dam_break, both cameras of the imported frame
    assert len(metrics["sequences"]) == 5
    assert set(metrics["sizes"]) == {"64", "96"} and len(metrics["sizes"]["96"]["sequences"]) == 5
    assert {s["size"][0] for s in metrics["sizes"]["96"]["sequences"]} == {96}
    for m in ("gaussian", "bilateral", "nrf", "aniso", "aniso_nrf", "refined", "metaball"):
        row = metrics["overall"][m]
        assert 0 <= row["mean_deg"] <= 180 and 0 <= row["iou"] <= 1 and row["ms_per_frame"] > 0
    own = metrics["overall"]["metaball"]
    assert 0 <= own["own_mean_deg"] <= 180 and 0 <= own["own_iou"] <= 1
    assert 0 <= own["surface_mean_deg"] <= 180, "the ray-marched surface is scored against the mesh too"
    for seq in metrics["sequences"]:  # a per-pixel temporal error wherever there are two frames
        t = seq["methods"]["refined"]["temporal_deg"]
        assert (t == t) == (seq["frames"] > 1) and (t != t or 0 <= t <= 180)
    assert 0 < metrics["overall"]["bilateral"]["temporal_deg"] <= 180 and "| temporal |" in report
    assert (entry / "methods.png").exists() and (entry / "examples.png").exists()


def test_evaluated_sizes_do_not_change_the_views_trained_weights_come_from(tmp_path, monkeypatch):
    """``render.weights: trained`` with ``evaluate.sizes``: the refiner is the one the config's own
    training views make (64 px here), not one trained on an evaluated size's views."""
    from stages import train

    checkpoint = _tiny_checkpoint(tmp_path)
    widths = []

    class Entry:
        def path(self, name):
            return checkpoint

    def ensure(run, force=False):
        widths.append(run.config.dataset.width)
        return Entry()

    monkeypatch.setattr(train, "ensure", ensure)
    config = _config(tmp_path, "trained")
    body = yaml.safe_load(open(config))
    body["evaluate"].update({"sizes": [96], "methods": ["nrf", "refined"], "imported_scenes": []})
    open(config, "w").write(yaml.safe_dump(body))
    assert cli.main(["evaluate", "--config", config]) == 0
    assert widths == [64]


def test_a_render_killed_between_its_exr_and_preview_resumes(tmp_path):
    """Outputs are written on a background thread; a frame counts as done only when its EXR and its
    preview (and comparison) all exist, so a frame whose preview is missing is redone, not stuck."""
    config = _config(tmp_path, _tiny_checkpoint(tmp_path), method="nrf", comparison=False)
    assert cli.main(["render", "--config", config, "--scene", "dam_break"]) == 0
    (entry,) = (tmp_path / "data" / "render").iterdir()
    (entry / "manifest.json").unlink()  # as if killed before the end
    (entry / "preview" / "frame_0003.png").unlink()
    kept = (entry / "frames" / "frame_0001.exr").stat().st_mtime_ns
    assert cli.main(["render", "--config", config, "--scene", "dam_break"]) == 0
    assert (entry / "preview" / "frame_0003.png").exists() and (entry / "manifest.json").exists()
    assert (entry / "frames" / "frame_0001.exr").stat().st_mtime_ns == kept, "finished frames are not redone"


def test_render_with_ellipsoid_splats(tmp_path):
    entry, fluid = _render_single_method(tmp_path, "aniso_nrf")
    assert fluid.any()
    assert "anisotropy" in json.loads((entry / "manifest.json").read_text())["ms_per_frame"]


def test_refiner_trained_on_ellipsoid_splats_renders_from_them(tmp_path):
    """A checkpoint whose config says input_splat: ellipsoid gets ellipsoid-splat inputs (its mask is
    the ellipsoid splat's, which covers more than the spheres')."""
    results = {}
    for splat in ("sphere", "ellipsoid"):
        (tmp_path / splat).mkdir()
        config = _config(tmp_path / splat, _tiny_checkpoint(tmp_path, splat), comparison=False, normal_threshold=0.0)
        assert cli.main(["render", "--config", config, "--scene", "dam_break"]) == 0
        (entry,) = (tmp_path / splat / "data" / "render").iterdir()
        results[splat] = read_exr(entry / "frames" / "frame_0003.exr")["ViewLayer.Mask.X"]
    assert results["ellipsoid"].sum() != results["sphere"].sum()
