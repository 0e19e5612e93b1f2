"""The refiner: shapes, the normal-constraint loss, learning, and exact resume after a kill."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
import yaml

from pipeline.config import TrainConfig
from pipeline.device import native_bfloat16
from pipeline.model.data import InputSpec, prepare
from pipeline.model.losses import normal_constraint_loss
from pipeline.model.networks import Discriminator, Generator
from pipeline.model.trainer import Refiner
from tests.conftest import ROOT, kill_after_writes


@pytest.mark.parametrize("downsamples, size", [(2, (64, 96)), (2, (36, 20)), (3, (48, 8)), (0, (7, 5))])
def test_generator_keeps_any_size_that_is_a_multiple_of_its_stride(downsamples, size):
    g = Generator(5, 8, downsamples, 1).eval()
    x = torch.randn(2, 5, *size)
    y = g(x)
    assert y.shape == (2, 3, *size)
    if downsamples:
        with pytest.raises(ValueError, match="multiple"):
            g(torch.randn(1, 5, size[0] + 1, size[1]))


def test_discriminator_takes_any_crop():
    d = Discriminator(6, 8, 3)
    for s in (32, 48, 64):
        assert d(torch.randn(2, 3, s, s), torch.randn(2, 3, s, s)).shape == (2,)


def _map(lengths: list[float]) -> torch.Tensor:
    """1 x 3 x 1 x k normal map with the given vector lengths along a fixed direction."""
    direction = torch.tensor([0.36, -0.48, 0.8])
    return torch.stack([direction * length for length in lengths], dim=-1)[None, :, None, :]


def test_normal_constraint_is_zero_for_unit_and_zero_vectors():
    assert normal_constraint_loss(_map([1.0, 0.0, 1.0, 0.0])) < 1e-5


@pytest.mark.parametrize("length, grows", [(0.8, True), (0.2, False), (1.3, False), (0.45, False), (0.55, True)])
def test_normal_constraint_is_positive_and_pulls_towards_zero_or_one(length, grows):
    n = _map([length]).requires_grad_(True)
    loss = normal_constraint_loss(n)
    assert loss > 0
    loss.backward()
    # a gradient step changes the length by -lr * (grad . n / |n|)
    radial = float((n.grad * n.detach()).sum() / n.detach().norm())
    assert (radial < 0) == grows


def _ball_frames(size: int = 64):
    """Two real training examples: splatted, bilateral-filtered balls and their mesh targets."""
    from pipeline.camera import Camera, look_at
    from pipeline.config import DatasetConfig
    from pipeline.parallel import Launcher
    from pipeline.screen import ScreenSpace
    from pipeline.surface import reconstruct
    from pipeline.views import screen_space_inputs, target_channels

    r = 0.01
    ax = np.arange(-0.1, 0.1 + 1e-9, 2 * r)
    lattice = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    ss, launch, p = ScreenSpace("cpu"), Launcher("cpu"), DatasetConfig(width=size, height=size)
    frames = []
    for shift in ((0.0, 0.0, 0.0), (0.05, -0.03, 0.0)):
        pts = lattice[np.linalg.norm(lattice, axis=1) <= 0.1] + shift
        pts = pts + np.random.default_rng(len(frames)).uniform(-0.3 * r, 0.3 * r, pts.shape)
        cam = Camera(look_at((0.0, 0.1, 0.6), (0, 0, 0)), 40.0, size, size)
        ch = screen_space_inputs(pts.astype(np.float32), r, cam, p, ss, filters=("bilateral",))
        ch.update(target_channels(reconstruct(pts.astype(np.float32), r, p, launch), cam, launch))
        view = prepare(ch, InputSpec(True, "sphere", "radius", 0.0), cam.focal_px, r, with_target=True)  # 64 px
        frames.append((view.inputs, view.target))
    ss.close()
    launch.close()
    return frames


def test_training_cuts_the_content_loss_by_more_than_half():
    frames = _ball_frames()
    cfg = TrainConfig(gen_base_channels=16, gen_downsamples=2, gen_res_blocks=2, disc_base_channels=8, disc_layers=3,
                      lr_decay=1.0)
    refiner = Refiner(cfg, "cpu", seed=0)
    x = np.stack([f[0] for f in frames])
    y = np.stack([f[1] for f in frames])
    losses = [refiner.train_step(x, y)["loss_content"] for _ in range(200)]
    first, last = np.mean(losses[:10]), np.mean(losses[-10:])
    assert last < 0.5 * first, (first, last)


@pytest.mark.skipif(not native_bfloat16("cpu"), reason="this CPU has no native bfloat16")
def test_bfloat16_training_follows_float32():
    """``train.mixed_precision`` on a CPU with native bf16 trains under bfloat16 autocast with
    float32 weights, and follows float32's losses step for step up to rounding; a missing autocast
    (equal losses), half weights or a wrong dtype fail."""
    frames = _ball_frames()
    x = np.stack([f[0] for f in frames])
    y = np.stack([f[1] for f in frames])
    losses, refiners = {}, {}
    for mixed in (False, True):
        cfg = TrainConfig(gen_base_channels=16, gen_downsamples=2, gen_res_blocks=2, disc_base_channels=8,
                          disc_layers=3, lr_decay=1.0, mixed_precision=mixed)
        refiners[mixed] = Refiner(cfg, "cpu", seed=0)
        losses[mixed] = np.array([refiners[mixed].train_step(x, y)["loss_g"] for _ in range(10)])
    assert refiners[False].autocast_dtype == torch.float32 and refiners[True].autocast_dtype == torch.bfloat16
    assert all(p.dtype == torch.float32 for p in refiners[True].generator.parameters())
    assert not np.array_equal(losses[True], losses[False]), "bfloat16 must actually round"
    np.testing.assert_allclose(losses[True], losses[False], rtol=0.05)


def _tiny_train_config(tmp_path, name: str) -> str:
    body = yaml.safe_load((ROOT / "configs" / "default.yaml").read_text())
    body.update({"scenes": ["dam_break", "merging"], "scene_dir": str(ROOT / "configs" / "scenes"),
                 "data_dir": str(tmp_path / name / "data")})
    body["simulate"].update({"particle_radius": 0.03, "frames": 4})
    body["dataset"] = {"width": 64, "height": 64, "frame_stride": 1, "holdout_scenes": ["merging"]}
    body["train"] = {"epochs": 2, "crop": 32, "batch_size": 2, "crops_per_frame": 2, "gen_base_channels": 8,
                     "gen_res_blocks": 1, "disc_base_channels": 8, "disc_layers": 2, "val_frames": 2, "threads": 1}
    (tmp_path / name).mkdir()
    path = tmp_path / name / "default.yaml"
    path.write_text(yaml.safe_dump(body))
    return str(path)


def _generator_state(tmp_path, name):
    (ckpt,) = (tmp_path / name / "data" / "train").glob("*/last.pt")
    state = torch.load(ckpt, weights_only=True)
    return state["generator"], state["epoch"]


@pytest.mark.slow
def test_resume_after_kill_equals_straight_run(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    straight = _tiny_train_config(tmp_path, "straight")
    killed = _tiny_train_config(tmp_path, "killed")
    run = [sys.executable, "-m", "stages.cli", "train", "--config"]
    assert subprocess.run(run + [straight], cwd=ROOT, env=env, capture_output=True).returncode == 0
    assert kill_after_writes(run + [killed], "*/last.pt") == 1
    train_dir = tmp_path / "killed" / "data" / "train"
    state, epoch = _generator_state(tmp_path, "killed")
    assert epoch == 1, "the kill must land between the two epochs' checkpoints"
    assert subprocess.run(run + [killed], cwd=ROOT, env=env, capture_output=True).returncode == 0
    a, ea = _generator_state(tmp_path, "straight")
    b, eb = _generator_state(tmp_path, "killed")
    assert ea == eb == 2
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert not list(train_dir.parent.rglob("*.tmp-*"))  # the entry and its staged writes


def test_ship_writes_loadable_weights_and_their_card(tmp_path):
    from pipeline.model.inference import load_refiner
    from stages import cli

    config = _tiny_train_config(tmp_path, "ship")
    out = tmp_path / "weights"
    assert cli.main(["ship", "--config", config, "--out", str(out)]) == 0
    refiner = load_refiner(out / "refiner.pt")
    assert refiner.splat == "ellipsoid" and refiner.auxiliary
    card = json.loads((out / "refiner.json").read_text())
    assert card["data"]["input_splat"] == "ellipsoid" and card["epochs_run"] == 2
    assert card["held_out"]["refined"]["mean_deg"] > 0 and len(card["history"]) == 2
    assert (out / "loss_curve.png").stat().st_size > 0
    assert set(torch.load(out / "refiner.pt", weights_only=True)) == {"generator", "generator_args", "config", "epoch",
                                                                      "metrics"}


def test_a_crop_larger_than_the_images_is_an_error(tmp_path, capsys):
    from stages import cli

    config = _tiny_train_config(tmp_path, "crop")
    body = yaml.safe_load(open(config))
    body["train"]["crop"] = 512  # the tiny dataset is 64 x 64, about 180 x 180 at the working scale
    open(config, "w").write(yaml.safe_dump(body))
    assert cli.main(["train", "--config", config]) == 1
    err = capsys.readouterr().err
    assert "train.crop is 512 px but the dataset's views are at most" in err and "at the working scale" in err


def test_a_time_limit_stops_at_an_epoch_and_the_next_run_continues(tmp_path):
    """``train.time_limit_minutes``: a run stops after the first epoch past the limit with its
    checkpoint written and the entry unfinished; the next run resumes and ends where a straight run
    ends, bit for bit."""
    from stages import cli

    straight = _tiny_train_config(tmp_path, "straight")
    chunked = _tiny_train_config(tmp_path, "chunked")
    body = yaml.safe_load(open(chunked))
    body["train"]["time_limit_minutes"] = 1e-6
    open(chunked, "w").write(yaml.safe_dump(body))
    assert cli.main(["train", "--config", chunked]) == 0
    state, epoch = _generator_state(tmp_path, "chunked")
    assert epoch == 1
    (entry,) = (tmp_path / "chunked" / "data" / "train").iterdir()
    assert not (entry / "manifest.json").exists()
    assert cli.main(["train", "--config", chunked]) == 0
    assert (entry / "manifest.json").exists()
    assert cli.main(["train", "--config", straight]) == 0
    a, ea = _generator_state(tmp_path, "straight")
    b, eb = _generator_state(tmp_path, "chunked")
    assert ea == eb == 2
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_init_from_loads_matching_weights_and_names_a_mismatch(tmp_path):
    from pipeline.model.train import TrainingError, init_generator

    cfg = TrainConfig(gen_base_channels=8, gen_res_blocks=1, disc_base_channels=8, disc_layers=2)
    source = Refiner(cfg, "cpu", seed=1)
    path = tmp_path / "source.pt"
    torch.save(source.state(3), path)
    fresh = Refiner(cfg, "cpu", seed=2)
    assert not all(torch.equal(v, source.generator.state_dict()[k]) for k, v in fresh.generator.state_dict().items())
    init_generator(fresh, str(path))
    for k, v in fresh.generator.state_dict().items():
        assert torch.equal(v, source.generator.state_dict()[k]), k
    wider = Refiner(TrainConfig(gen_base_channels=16, gen_res_blocks=1, disc_base_channels=8, disc_layers=2), "cpu")
    with pytest.raises(TrainingError, match="base_channels"):
        init_generator(wider, str(path))
    with pytest.raises(TrainingError, match="no checkpoint"):
        init_generator(wider, str(tmp_path / "missing.pt"))


def test_weights_without_the_density_feature_start_a_refiner_with_it_unchanged(tmp_path):
    """``init_from`` weights of six inputs into a generator that also takes the density feature: the
    feature enters with zero weights, so the generator's output is the source's whatever the
    density, and the spec counts the seventh channel."""
    from pipeline.model.train import init_generator

    small = {"gen_base_channels": 8, "gen_res_blocks": 1, "disc_base_channels": 8, "disc_layers": 2}
    source = Refiner(TrainConfig(**small), "cpu", seed=1)
    path = tmp_path / "source.pt"
    torch.save(source.state(3), path)
    cfg = TrainConfig(**small, density_feature=True)
    assert InputSpec.of(cfg).channels == 7 and InputSpec.of(TrainConfig(**small)).channels == 6
    grown = Refiner(cfg, "cpu", seed=2)
    init_generator(grown, str(path))
    x = torch.randn(1, 6, 32, 32)
    source.generator.eval()
    grown.generator.eval()
    with torch.no_grad():
        want = source.generator(x)
        for density in (torch.zeros(1, 1, 32, 32), torch.rand(1, 1, 32, 32)):
            torch.testing.assert_close(grown.generator(torch.cat([x, density], 1)), want)


def test_the_density_feature_follows_the_view_to_the_working_scale():
    """``prepare`` with the density feature: its seventh channel is tanh(density / 2) over the
    fluid and 0 elsewhere, at the view's own scale and after a rescale (a constant density stays
    that constant on the scaled fluid)."""
    from pipeline.model.data import DENSITY_SCALE, input_channels

    spec = InputSpec(density=True)
    names = input_channels(spec.splat)
    yy, xx = np.mgrid[0:64, 0:64]
    fluid = np.hypot(yy - 32, xx - 32) < 20
    depth = np.where(fluid, 2.0, 0.0).astype(np.float32)
    ch = {names.raw: depth, names.blurred: depth, names.fluid: fluid.astype(np.float32),
          names.density: np.where(fluid, 3.0, 0.0).astype(np.float32),
          **{n: np.where(fluid, v, 0.0).astype(np.float32) for n, v in zip(names.normal, (0.0, 0.0, 1.0), strict=True)}}
    want = np.tanh(DENSITY_SCALE * 3.0)
    for focal_px in (300.0, 3000.0):  # particles of 1.9 px (upscaled to 3) and of 19 px (shrunk to 3)
        view = prepare(ch, spec, focal_px, 0.0125)
        assert view.inputs.shape[0] == 7 and view.scale != 1.0
        np.testing.assert_allclose(view.inputs[6][view.fluid], want, rtol=1e-5)
        assert (view.inputs[6][~view.fluid] == 0).all()
