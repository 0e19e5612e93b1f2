"""The metaball method end to end: the working frame, augmentation, training that resumes, the
generator as a normal source, and the stages that build, train and ship it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import yaml

from pipeline.camera import Camera, look_at
from pipeline.config import METHODS, ConfigError, MetaballConfig
from pipeline.config_files import load
from pipeline.metaball import encode_targets, paper_camera
from pipeline.metaball.dataset import training_pair, write_view
from pipeline.metaball.inference import MetaballNet
from pipeline.metaball.train import SHIPPED_WEIGHTS, augment, fit
from pipeline.metaball.views import fluid_view, random_ball_set, working_view
from pipeline.parallel import Launcher
from stages import cli
from tests.conftest import ROOT

SMALL = MetaballConfig(base_channels=4, disc_base_channels=4, batch_size=2, epochs=2, step=0.01, crop=32,
                       anisotropic=False, ball_radius_radii=1.0, splat_radius=1.5)


@pytest.fixture(scope="module")
def launch():
    out = Launcher("cpu")
    yield out
    out.close()


def _balls(n: int = 12, seed: int = 3) -> tuple[np.ndarray, float]:
    rng = np.random.default_rng(seed)
    return rng.uniform(-0.06, 0.06, (n, 3)) + np.array([0.0, 0.0, -1.0]), 0.02


def test_the_working_frame_does_not_depend_on_the_scene_scale(launch):
    """The same balls three times larger and three times further away (the world scaled about the
    eye) give the same inputs, codes and normals; the depth comes back in the scene's units."""
    x, r = _balls()
    eye = np.array([0.05, 0.04, -0.72])
    cam = Camera(look_at(eye, (0.0, 0.0, -1.0)), 40.0, 128, 128)
    a = fluid_view(x, r, cam, SMALL)
    b = fluid_view(eye + 3.0 * (x - eye), 3.0 * r, cam, SMALL)
    np.testing.assert_allclose(a.positions, b.positions, atol=1e-9)
    np.testing.assert_allclose(a.circles(launch), b.circles(launch), atol=1e-6)
    np.testing.assert_allclose(a.inputs("spheres", launch), b.inputs("spheres", launch), atol=1e-5)
    np.testing.assert_allclose(a.inputs("field", launch), b.inputs("field", launch), atol=1e-4)
    ta, tb = a.targets(launch), b.targets(launch)
    assert ta["mask"].sum() > 30 and (ta["mask"] == tb["mask"]).mean() > 0.999
    both = (ta["mask"] > 0) & (tb["mask"] > 0)
    np.testing.assert_allclose(ta["normals"][both], tb["normals"][both], atol=1e-3)
    np.testing.assert_allclose(3.0 * ta["depth"][both], tb["depth"][both], rtol=1e-4)
    # the surface lies in front of the nearest centre by about a ball radius: depths are the scene's
    nearest = float((-cam.to_view(x)[:, 2]).min())
    assert nearest - 3 * r < ta["depth"][both].min() < nearest
    codes = a.depth_code(ta["depth"][both])
    np.testing.assert_allclose(a.depth_of(codes), ta["depth"][both], rtol=1e-5)


def test_ellipsoidal_balls_reach_the_working_frame_turned_and_scaled_with_it(launch):
    """Anisotropic metaballs: their world shape maps follow the balls into the camera's frame, so
    the same ellipsoids three times larger and further away give the same field input and normals,
    and the working view's surface is the world ellipsoids' surface seen by the camera."""
    from pipeline.ellipsoids import Ellipsoids
    from pipeline.metaball import metaball_targets

    x, r = _balls(20)
    rng = np.random.default_rng(8)
    turns = np.linalg.qr(rng.normal(size=(20, 3, 3)))[0]
    shapes = np.diag(1.0 / np.array([1.5, 0.5, 1.0])) @ np.swapaxes(turns, 1, 2) / r
    eye = np.array([0.05, 0.04, -0.72])
    cam = Camera(look_at(eye, (0.0, 0.0, -1.0)), 40.0, 128, 128)
    m = MetaballConfig(step=0.01, ball_radius_radii=1.0)
    a = fluid_view(x, r, cam, m, Ellipsoids(x, shapes, np.full(20, 1.5 * r)))
    b = fluid_view(eye + 3.0 * (x - eye), 3.0 * r, cam, m,
                   Ellipsoids(eye + 3.0 * (x - eye), shapes / 3.0, np.full(20, 4.5 * r)))
    np.testing.assert_allclose(a.shapes, b.shapes, rtol=1e-9)
    np.testing.assert_allclose(a.inputs("field", launch), b.inputs("field", launch), atol=1e-4)
    ta = a.targets(launch, own_size=True)
    world = metaball_targets(x, r, cam, a.params.__class__(step=0.01 * r / m.working_ball_radius, depth_near=0.01,
                                                           depth_far=10.0), launch, shapes=shapes)
    both = (ta["mask"] > 0) & (world["mask"] > 0)
    assert both.sum() > 100 and (ta["mask"] == world["mask"]).mean() > 0.995
    # the same surface but where a grazing ray's steps fall differently (1 pixel in thousands)
    assert np.isclose(ta["depth"][both], world["depth"][both], rtol=1e-3).mean() > 0.999
    assert np.median(np.degrees(np.arccos(np.clip((ta["normals"] * world["normals"]).sum(-1)[both], -1, 1)))) < 0.1


def test_the_working_scale_draws_every_resolution_at_one_ball_size(launch):
    """The same view at 128, 256 and 512 px reaches the network as one image: the median ball at most
    ``working_radius_px`` and more than half an octave below it, the inputs equal; a view of balls under
    that size is drawn larger, at most 4 times."""
    x, r = _balls(40)
    eye = np.array([0.05, 0.04, -0.72])
    views = [fluid_view(x, r, Camera(look_at(eye, (0.0, 0.0, -1.0)), 40.0, n, n), SMALL) for n in (128, 256, 512)]
    assert [v.size for v in views] == [(128, 128), (256, 256), (512, 512)]
    sizes = {(v.camera.height, v.camera.width) for v in views}
    assert len(sizes) == 1
    c = views[0].camera
    r_px = np.median(c.focal_px * views[0].radii / -views[0].positions[:, 2])
    assert SMALL.working_radius_px / 2**0.5 < r_px <= SMALL.working_radius_px
    first = views[0].inputs("spheres", launch)
    for v in views[1:]:
        np.testing.assert_allclose(v.inputs("spheres", launch), first, atol=1e-5)
    far = fluid_view(x, r, Camera(look_at(eye - np.array([0.0, 0.0, 30.0]), (0.0, 0.0, -1.0)), 40.0, 64, 64), SMALL)
    assert far.camera.height == 4 * 64


def test_the_sphere_input_shows_the_ball_behind_and_how_far(launch):
    """One ball 3 radii behind another on the axis: the front sphere's disc is covered, with the relief
    of a sphere (its centre nearer than its rim); at the centre pixel the back ball is entered 3 radii
    after the front one (behind = 1 - 3/8) and the ray leaves it 5 radii after (thickness 5/8); a
    lone ball shows nothing behind and a thickness of its diameter."""
    from pipeline.metaball import sphere_input, sphere_layers
    from pipeline.metaball.views import params_of

    cam = Camera(np.eye(4), 30.0, 65, 65)
    p = SMALL
    r = 0.05
    def splat(centres):
        return sphere_input(sphere_layers(np.array(centres), r, cam, params_of(p), launch))

    two = splat([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0 - 3 * r]])
    one = splat([[0.0, 0.0, -1.0]])
    c = 32
    disc = cam.focal_px * r / 1.0
    assert one[0, c, c] == 1 and one[0, c, c + int(disc) + 2] == 0 and one[0, c, c + int(disc) - 1] == 1
    assert one[4, c, c] < one[4, c, c + int(disc) - 1], "the sphere's centre is nearer than its rim"
    assert one[5, c, c] == 0 and two[5, c, c] == pytest.approx(1 - 3 / 8, abs=2e-3)
    assert one[6, c, c] == pytest.approx(2 / 8, abs=2e-3) and two[6, c, c] == pytest.approx(5 / 8, abs=2e-3)
    # the front sphere's normal: facing the camera at the centre, outwards at the rim, unit length
    n = 2.0 * one[1:4] - 1.0
    np.testing.assert_allclose(n[:, c, c], [0.0, 0.0, 1.0], atol=0.02)
    assert n[0, c, c + int(disc) - 1] > 0.6 and n[1, c - int(disc) + 1, c] > 0.6
    np.testing.assert_allclose(np.linalg.norm(n[:, one[0] > 0], axis=0), 1.0, atol=1e-4)


@pytest.mark.parametrize("turns,mirror", [(1, False), (2, False), (0, True), (3, True)])
def test_augmentation_equals_rendering_the_turned_balls(launch, turns, mirror):
    """Turning and mirroring a view's arrays (the encoded normals with them) gives what rendering the
    balls turned about the view axis, or mirrored, gives."""
    rng = np.random.default_rng(5)
    positions, radii, colours = random_ball_set(rng, 20)
    cam = paper_camera(48, 48)
    m = MetaballConfig(step=0.02)

    def render(p):
        view = working_view(p, radii, cam, m)
        t = view.targets(launch, colours)
        t["depth"] = t["depth"] * view.scale
        return np.concatenate([view.circles(launch, colours), view.inputs("spheres", launch)]), \
            encode_targets(t, view.params)

    x, y = render(positions)
    turned = positions.copy()
    for _ in range(turns):
        turned[:, :2] = np.stack([-turned[:, 1], turned[:, 0]], axis=1)
    if mirror:
        turned[:, 0] = -turned[:, 0]
    want_x, want_y = render(turned)
    got_x, got_y = augment(x, y, turns, mirror, (slice(5, 8),))  # the sphere normals after 4 circle channels
    np.testing.assert_allclose(got_x, want_x, atol=2e-4)
    surface = (want_y[4:7].max(0) > 0) & (got_y[4:7].max(0) > 0)
    assert surface.mean() > 0.05 and (surface == (want_y[4:7].max(0) > 0)).mean() > 0.995
    np.testing.assert_allclose(got_y[4:7][:, surface], want_y[4:7][:, surface], atol=2e-3)


@pytest.fixture(scope="module")
def views(tmp_path_factory, launch):
    """Four random-set views (a 256 x 256 camera drawn at the working scale)."""
    folder = tmp_path_factory.mktemp("metaball_views")
    cam = paper_camera(256, 256)
    paths = []
    for k in range(4):
        positions, radii, colours = random_ball_set(np.random.default_rng([9, k]), 12)
        path = folder / f"set_{k}.exr"
        share = write_view(path, working_view(positions, radii, cam, SMALL), cam, launch, float(np.median(radii)),
                           SMALL.input, colours)
        assert 0 < share < 1
        paths.append(path)
    return paths


def test_training_resumes_as_a_straight_run_would_and_the_generator_predicts(tmp_path, views, launch):
    straight = tmp_path / "straight"
    resumed = tmp_path / "resumed"
    straight.mkdir()
    resumed.mkdir()
    fit(straight, SMALL, 0, views[:3], views[3:], "cpu")
    fit(resumed, MetaballConfig(**{**SMALL.__dict__, "epochs": 1}), 0, views[:3], views[3:], "cpu")
    fit(resumed, SMALL, 0, views[:3], views[3:], "cpu")
    a = torch.load(straight / "last.pt", weights_only=True)
    b = torch.load(resumed / "last.pt", weights_only=True)
    assert a["epoch"] == b["epoch"] == 2
    for k, v in a["generator"].items():
        assert torch.equal(v, b["generator"][k]), k
    history = [json.loads(line) for line in (straight / "metrics.jsonl").read_text().splitlines()]
    assert [h["epoch"] for h in history] == [1, 2] and 0 <= history[-1]["val"]["iou"] <= 1
    assert (straight / "loss_curve.png").exists()
    # a new run can start from it (the next session goes on), not from another architecture's
    from pipeline.metaball.train import build_generator, generator_args, init_generator
    fresh = build_generator(generator_args(SMALL))
    init_generator(fresh, MetaballConfig(**{**SMALL.__dict__, "init_from": str(straight / "best.pt")}))
    for k, v in torch.load(straight / "best.pt", weights_only=True)["generator"].items():
        assert torch.equal(fresh.state_dict()[k], v), k
    with pytest.raises(RuntimeError, match="holds a generator"):
        init_generator(fresh, MetaballConfig(**{**SMALL.__dict__, "base_channels": 8,
                                                "init_from": str(straight / "best.pt")}))
    # the generator as the metaball method: any image size (drawn at the working scale, resampled back)
    net = MetaballNet(straight / "best.pt")
    assert net.config == SMALL
    x, r = _balls()
    cam = Camera(look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0)), 40.0, 300, 200)
    out = net.gbuffers(x, r, cam, launch)
    assert out["normals"].shape == (200, 300, 3) and out["depth"].shape == (200, 300)
    shown = out["mask"] > 0
    np.testing.assert_allclose(np.linalg.norm(out["normals"][shown], axis=-1), 1.0, atol=1e-4)
    assert (out["depth"][~shown] == 0).all() and (out["depth"][shown] > 0).all()


def test_training_pair_encodes_what_was_rendered(views):
    x, y = training_pair(views[0], SMALL)
    assert x.shape[0] == 7 and y.shape[0] == 7 and x.shape[1:] == y.shape[1:] and x.shape[1] < 256
    surface = y[4:7].max(0) > 0
    assert ((y[3] < 1) == surface).all(), "depth code 1 exactly where the ray met nothing"
    assert 0 <= y.min() and y.max() <= 1 and 0 <= x.min() - -1 and x.max() <= 1
    assert ((x[0] > 0) & surface).sum() > 0.5 * surface.sum(), "the splat and the surface overlap"


def test_the_field_input_gives_the_blended_surface_orientation(launch):
    """On a block of fluid-spaced balls, the field's normal a Newton step from the front of the larger
    spheres is within a few degrees of the ray-marched surface's, where the spheres' own normals are
    tens of degrees off (the blend smooths them away); so on the block's ellipsoids."""
    from pipeline.config import DatasetConfig
    from pipeline.surface import particle_ellipsoids

    g = np.arange(8) * 0.04
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + np.array([-0.14, -0.14, -1.2])
    cam = Camera(look_at((0.5, 0.4, 0.0), (0.0, 0.0, -1.06)), 40.0, 256, 256)
    ellipsoids = particle_ellipsoids(x.astype(np.float32), 0.02, DatasetConfig(), launch)
    spheres = {"anisotropic": False, "ball_radius_radii": 1.0}
    errors = {}
    for name, m in {"field": MetaballConfig(splat_radius=1.5, **spheres), "ellipsoids": MetaballConfig(),
                    "spheres": MetaballConfig(input="spheres", splat_radius=1.0, **spheres)}.items():
        view = fluid_view(x, 0.02, cam, m, ellipsoids)
        target, layers = view.targets(launch), view.layers(launch)
        both = (target["mask"] > 0) & (layers["front"] > 0)
        assert both.sum() > 0.9 * (target["mask"] > 0).sum()
        cos = (layers["normals"] * target["normals"]).sum(-1)[both]
        errors[name] = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).mean())
    assert errors["field"] < 5.0 and errors["ellipsoids"] < 5.0 and errors["spheres"] > 20.0, errors


def test_metaball_is_a_method_and_bad_method_names_are_config_errors(tmp_path):
    assert "metaball" in METHODS
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"base": str(ROOT / "configs" / "default.yaml"),
                                    "evaluate": {"methods": ["refined", "metaballs"]}}))
    with pytest.raises(ConfigError, match="evaluate.methods"):
        load(path)


def test_the_shipped_metaball_weights_load_with_their_card():
    net = MetaballNet(SHIPPED_WEIGHTS)
    card = json.loads(SHIPPED_WEIGHTS.with_suffix(".json").read_text())
    assert SHIPPED_WEIGHTS.stat().st_size < 20 * 2**20
    assert card["generator_args"]["base_channels"] == net.config.base_channels
    assert card["validation"]["mean_deg"] < 20 and card["data"]["training_views"] > 0
    assert card["generator_args"]["kind"] == "resnet" and net.config.input == "field"


def test_metaball_stages_build_train_and_ship(tmp_path):
    """metaball-dataset renders only training and validation scenes, metaball-train trains on them,
    metaball-ship writes weights and a card."""
    body = yaml.safe_load((ROOT / "configs" / "default.yaml").read_text())
    body.update({"scenes": ["dam_break", "merging"], "scene_dir": str(ROOT / "configs" / "scenes"),
                 "data_dir": str(tmp_path / "data")})
    body["simulate"].update({"particle_radius": 0.03, "frames": 2})
    body["dataset"] = {"holdout_scenes": ["merging"], "random_radius_px": [2, 4]}
    body["train"] = {"validation_scenes": ["merging"]}
    body["metaball"] = {"base_channels": 4, "disc_base_channels": 4, "batch_size": 2, "epochs": 1, "step": 0.02,
                        "frame_stride": 2, "views_per_frame": 1, "random_sets": 1, "repeats": 2, "max_balls": 8,
                        "crop": 32}
    config = tmp_path / "small.yaml"
    config.write_text(yaml.safe_dump(body))
    assert cli.main(["metaball-dataset", "--config", str(config)]) == 0
    built = sorted(p.name.split("-")[0] for p in (tmp_path / "data" / "metaball_dataset").iterdir())
    assert built == ["dam_break", "merging", "random_sets"]
    out = tmp_path / "shipped"
    assert cli.main(["metaball-ship", "--config", str(config), "--out", str(out)]) == 0
    card = json.loads((out / "metaball.json").read_text())
    assert card["data"]["training_views"] == 1 + 2 and card["data"]["validation_views"] == 1
    assert MetaballNet(out / "metaball.pt").config.base_channels == 4


def test_missing_or_damaged_metaball_weights_are_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="make metaball-train"):
        MetaballNet(tmp_path / "nope.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(RuntimeError, match="cannot read metaball weights"):
        MetaballNet(bad)


def test_the_residual_generator_starts_as_its_field_input():
    """With ``residual_at`` the untrained generator returns the input's normal channels as its normal
    outputs (on and off the splat, where the input's -1 is the empty target's), and a trained step
    changes them; the other outputs go through tanh as without it."""
    from pipeline.metaball.train import build_generator, generator_args

    m = MetaballConfig(base_channels=4)
    args = generator_args(m)
    assert args["residual_at"] == [1, 4]
    assert "residual_at" not in generator_args(MetaballConfig(base_channels=4, input="circles"))
    g = build_generator(args).eval()
    x = torch.rand(1, 7, 16, 16) * 2 - 1
    y = g(x)
    assert y.shape == (1, 7, 16, 16)
    torch.testing.assert_close(y[:, 4:7], x[:, 1:4])
    torch.testing.assert_close(y[:, :4], torch.zeros(1, 4, 16, 16))
    g.train()
    loss = (g(x)[:, 4:7] - 0.5).abs().mean()
    loss.backward()
    torch.optim.SGD(g.parameters(), 0.1).step()
    assert not torch.allclose(g.eval()(x)[:, 4:7], x[:, 1:4])
