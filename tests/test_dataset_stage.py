"""Smoke test of the dataset stage on the real default config, shrunk: 2 frames at 64x64."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from pipeline.exr import read_exr, read_exr_header
from stages import cli
from tests.conftest import ROOT


def shrunk_default(tmp_path, frames: int = 4, size: int = 64, **extra) -> str:
    body = yaml.safe_load((ROOT / "configs" / "default.yaml").read_text())
    body["scene_dir"] = str(ROOT / "configs" / "scenes")
    body["data_dir"] = str(tmp_path / "data")
    body["simulate"].update({"particle_radius": 0.03, "frames": frames})
    body["dataset"] = {"width": size, "height": size, "frame_stride": 2, "keep_meshes": True, **extra}
    path = tmp_path / "default_small.yaml"
    path.write_text(yaml.safe_dump(body))
    return str(path)


def test_dataset_smoke_all_scenes(tmp_path):
    config = shrunk_default(tmp_path)
    assert cli.main(["dataset", "--config", config]) == 0
    entries = sorted((tmp_path / "data" / "dataset").iterdir())
    assert len(entries) == len(yaml.safe_load(open(config))["scenes"]) == 12
    for entry in entries:
        manifest = json.loads((entry / "manifest.json").read_text())
        records = manifest["frames"]
        assert len(records) == 4  # 2 frames x 2 cameras
        assert {r["split"] for r in records} == {"train", "val"}
        assert all(r["camera"] == "orbit" for r in records if r["split"] == "val")
        for r in records:
            ch = read_exr(entry / r["file"])
            for name in ("Z", "A", "thickness", "bilateral.N.X", "nrf.Z", "gaussian.N.Z", "target.N.Y",
                         "target.Z", "target.A"):
                assert ch[name].shape == (64, 64) and np.isfinite(ch[name]).all()
            fluid = ch["A"] > 0
            assert abs(r["fluid_share"] - fluid.mean()) < 1e-4
            assert read_exr_header(entry / r["file"])["fluidShare"] == r["fluid_share"]
            n = np.stack([ch[f"bilateral.N.{a}"] for a in "XYZ"], -1)
            assert np.allclose(np.linalg.norm(n[fluid], axis=-1), 1, atol=1e-3)
            assert not n[~fluid].any()
        assert len(list((entry / "meshes").glob("*.ply"))) == 2
    # a re-run is a hit: nothing is rewritten
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "data").rglob("*.exr")}
    assert cli.main(["dataset", "--config", config]) == 0
    assert stamps == {p: p.stat().st_mtime_ns for p in (tmp_path / "data").rglob("*.exr")}


def test_dataset_param_change_recomputes_only_downstream(tmp_path):
    config = shrunk_default(tmp_path)
    args = ["--config", config, "--scene", "dam_break"]
    assert cli.main(["dataset", *args]) == 0
    sims = sorted((tmp_path / "data" / "simulate").iterdir())
    body = yaml.safe_load(open(config))
    body["dataset"]["bilateral_range_radii"] = 3.0
    open(config, "w").write(yaml.safe_dump(body))
    sim_stamp = (sims[0] / "manifest.json").stat().st_mtime_ns
    assert cli.main(["dataset", *args]) == 0
    assert sorted((tmp_path / "data" / "simulate").iterdir()) == sims
    assert (sims[0] / "manifest.json").stat().st_mtime_ns == sim_stamp
    assert len(list((tmp_path / "data" / "dataset").iterdir())) == 2
    # an upstream change re-runs both
    body["simulate"]["xsph_viscosity"] = 0.03
    open(config, "w").write(yaml.safe_dump(body))
    assert cli.main(["dataset", *args]) == 0
    assert len(list((tmp_path / "data" / "simulate").iterdir())) == 2
    assert len(list((tmp_path / "data" / "dataset").iterdir())) == 3


def test_imported_sequence_goes_through_the_dataset(tmp_path):
    from tests.conftest import PARTICLES

    scene = {"name": "bunny", "source": {"pattern": str(PARTICLES / "bunny_frame_14_7705_particles.vtk"),
                                         "particle_radius": 0.025},
             "cameras": {"static": {"eye": [0.0, 1.5, 3.0], "target": [0.0, 1.2, -0.1]},
                         "orbit": {"target": [0.0, 1.2, -0.1], "distance": 3.0, "height": 0.4}}}
    (tmp_path / "scenes").mkdir()
    (tmp_path / "scenes" / "bunny.yaml").write_text(yaml.safe_dump(scene))
    (tmp_path / "c.yaml").write_text(yaml.safe_dump({"scenes": ["bunny"], "scene_dir": "scenes", "data_dir": "data",
                                                     "dataset": {"width": 64, "height": 64}}))
    assert cli.main(["dataset", "--config", str(tmp_path / "c.yaml")]) == 0
    (entry,) = (tmp_path / "data" / "dataset").iterdir()
    ch = read_exr(entry / "static" / "frame_0001.exr")
    assert ch["A"].mean() > 0.05 and ch["target.A"].mean() > 0.05


def test_random_views_cover_the_configured_ranges_and_skip_evaluated_scenes(tmp_path):
    """Random training views: each frame gets ``random_views`` of them, square, a multiple of 32 px
    within the size range, their header says the camera and the particle radius, and the particles
    project within the radius range; a held-out scene that is only evaluated gets none, the scene
    that validates does."""
    from pipeline.exr import read_exr_header
    from pipeline.model.data import view_geometry
    from pipeline.model.scale import median_radius_px

    config = shrunk_default(tmp_path, random_views=3, random_size=[64, 192], random_radius_px=[1.0, 4.0],
                            holdout_scenes=["merging", "validation_drop"], validation_camera="none")
    body = yaml.safe_load(open(config))
    body["scenes"] = ["splash_drops", "merging", "validation_drop"]
    body["train"]["validation_scenes"] = ["validation_drop"]
    open(config, "w").write(yaml.safe_dump(body))
    assert cli.main(["dataset", "--config", config]) == 0
    radii = []
    for entry in sorted((tmp_path / "data" / "dataset").iterdir()):
        records = json.loads((entry / "manifest.json").read_text())["frames"]
        randoms = [r for r in records if r["camera"] == "random"]
        if entry.name.startswith("merging"):
            assert not randoms and not (entry / "random").exists()
            continue
        assert len(randoms) == 2 * 3 and {r["split"] for r in randoms} == {"train"}
        for r in randoms:
            ch = read_exr(entry / r["file"])
            side = ch["aniso.Z"].shape[0]
            assert ch["aniso.Z"].shape == (side, side) and side % 32 == 0 and 64 <= side <= 192
            assert {"aniso_bilateral.N.X", "target.N.Z", "aniso.A"} <= set(ch) and "nrf.Z" not in ch
            focal_px, radius = view_geometry(read_exr_header(entry / r["file"]))
            assert radius == pytest.approx(0.03)
            # the field of view is drawn from 25-65 degrees
            assert side / 2 / np.tan(np.radians(32.5)) - 1e-3 <= focal_px <= side / 2 / np.tan(np.radians(12.5)) + 1e-3
            if r["fluid_share"] > 0.02:
                radii.append(median_radius_px(ch["aniso.Z"], focal_px, radius))
    assert radii and 0.6 <= min(radii) and max(radii) <= 6.0


def test_random_views_carry_the_sphere_splat_when_a_refiner_on_spheres_trains(tmp_path, capsys):
    """With ``random_view_spheres`` the random views also hold the sphere splat's bilateral input (the
    input ablation's training data) and the evaluated-only scenes keep the entries of the recipe
    without it; training on spheres without it stops with the key to set."""
    config = shrunk_default(tmp_path, random_views=1, holdout_scenes=["merging"], validation_camera="none")
    body = yaml.safe_load(open(config))
    body["scenes"] = ["splash_drops", "merging"]
    body["train"]["input_splat"] = "sphere"
    open(config, "w").write(yaml.safe_dump(body))
    assert cli.main(["dataset", "--config", config]) == 0
    before = sorted(p.name for p in (tmp_path / "data" / "dataset").iterdir())
    assert cli.main(["train", "--config", config]) == 2  # a config error, before any training
    assert "dataset.random_view_spheres: must be true" in capsys.readouterr().err
    body["dataset"]["random_view_spheres"] = True
    open(config, "w").write(yaml.safe_dump(body))
    assert cli.main(["dataset", "--config", config]) == 0
    after = sorted(p.name for p in (tmp_path / "data" / "dataset").iterdir())
    assert [n for n in after if n.startswith("merging")] == [n for n in before if n.startswith("merging")]
    (entry,) = [p for p in (tmp_path / "data" / "dataset").iterdir() if p.name not in before]
    randoms = [r for r in json.loads((entry / "manifest.json").read_text())["frames"] if r["camera"] == "random"]
    assert randoms
    for r in randoms:
        ch = read_exr(entry / r["file"])
        assert {"Z", "A", "bilateral.Z", "bilateral.N.X", "aniso_bilateral.N.X"} <= set(ch) and "nrf.Z" not in ch
        fluid = ch["A"] > 0
        n = np.stack([ch[f"bilateral.N.{a}"] for a in "XYZ"], -1)
        assert np.allclose(np.linalg.norm(n[fluid], axis=-1), 1, atol=1e-3) and not n[~fluid].any()


def test_one_worker_writing_in_the_background_gives_the_files_of_two(tmp_path):
    """With one worker (as on a GPU) the views are written on a background thread while the next ones
    are made; the files must be byte for byte those of two workers writing their own."""
    files = {}
    for workers in (1, 2):
        root = tmp_path / f"w{workers}"
        root.mkdir()
        config = shrunk_default(root, workers=workers, random_views=1)
        assert cli.main(["dataset", "--config", config, "--scene", "dam_break"]) == 0
        (entry,) = (root / "data" / "dataset").iterdir()
        files[workers] = {p.relative_to(entry): p.read_bytes() for p in sorted(entry.rglob("*.exr"))}
    assert len(files[1]) == 6  # 2 frames x (2 camera paths + 1 random view)
    assert files[1] == files[2]


def test_a_failed_frame_stops_the_frames_in_flight_at_their_next_step(tmp_path, monkeypatch):
    """When one frame fails (or Ctrl-C arrives), the frame another worker is building stops before
    its next view instead of writing all of them, so the stage ends within a view's time; what it
    wrote stays, and a resume builds the rest."""
    import time

    import pipeline.dataset as dataset
    from pipeline.config import DatasetConfig
    from pipeline.config_files import load

    scene = load(ROOT / "configs" / "default.yaml").scene("dam_break")
    g = np.arange(8) * 0.06
    block = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + np.array([0.4, 0.1, 0.2])
    inputs = dataset.screen_space_inputs

    def slow_inputs(*args, **kwargs):
        time.sleep(1.0)
        return inputs(*args, **kwargs)

    def load_frame(frame: int) -> np.ndarray:
        if frame == 1:
            time.sleep(0.3)  # the other worker is inside its first view by now
            raise RuntimeError("frame 1 is damaged")
        return block

    monkeypatch.setattr(dataset, "screen_space_inputs", slow_inputs)
    p = DatasetConfig(width=32, height=32, workers=2, random_views=2)
    start = time.monotonic()
    with pytest.raises(RuntimeError, match="frame 1 is damaged"):
        dataset.build_dataset(tmp_path, scene, p, [1, 2], load_frame, 0.03, "cpu")
    took = time.monotonic() - start
    written = sorted(tmp_path.rglob("*.exr"))
    assert len(written) <= 1, "frame 2 went on through its views after frame 1 failed"
    assert took < 3.5, f"{took:.1f} s: one view takes 1 s, all four of frame 2's 4 s"
    monkeypatch.setattr(dataset, "screen_space_inputs", inputs)
    dataset.build_dataset(tmp_path, scene, p, [2], load_frame, 0.03, "cpu")
    assert len(sorted(tmp_path.rglob("*.exr"))) == 4  # two cameras and two random views
