"""Bad configs give a one-line error naming the file and key, exit code 2, and write nothing."""

from __future__ import annotations

import pytest
import yaml

from pipeline.config import ConfigError
from pipeline.config_files import load
from stages import cli


def _run(path, capsys):
    code = cli.main(["simulate", "--config", str(path)])
    return code, capsys.readouterr().err


def _edit(path, fn):
    body = yaml.safe_load(path.read_text())
    fn(body)
    path.write_text(yaml.safe_dump(body))


@pytest.mark.parametrize("edit, key, words", [
    (lambda b: b["simulate"].update(particle_radiuss=0.01), "simulate.particle_radiuss", "unknown key"),
    (lambda b: b["simulate"].update(frames="many"), "simulate.frames", "must be an integer"),
    (lambda b: b["simulate"].update(particle_radius=-0.01), "simulate.particle_radius", "must be > 0"),
    (lambda b: b.update(scenes=["no_such_scene"]), "scenes", "unknown scene 'no_such_scene'"),
    (lambda b: b.update(device="tpu"), "device", "must be one of"),
    (lambda b: b.update(render={"comparison": 1}), "render.comparison", "must be true or false, got 1"),
    (lambda b: b["simulate"].update(frames=2.5), "simulate.frames", "must be an integer, got 2.5"),
    (lambda b: b["simulate"].update(gravity=[0, -9.8]), "simulate.gravity", "has too few elements"),
    (lambda b: b.update(seed="7"), "seed", "must be an integer, got '7'"),
])
def test_bad_config_exits_2_naming_file_and_key(tiny_dam, capsys, edit, key, words):
    _edit(tiny_dam, edit)
    code, err = _run(tiny_dam, capsys)
    assert code == 2
    assert str(tiny_dam) in err and f": {key}:" in err and words in err
    assert len(err.strip().splitlines()) == 1
    assert not (tiny_dam.parent / "data").exists(), "nothing may be written"


def test_bad_scene_file_names_scene_file(tiny_dam):
    scene_file = tiny_dam.parent / "scenes" / "tiny_dam.yaml"
    _edit(scene_file, lambda s: s["fluid"][0].update(shape="cone"))
    with pytest.raises(ConfigError) as err:
        load(tiny_dam)
    assert str(scene_file) in str(err.value) and "fluid[0].shape" in str(err.value)
    _edit(scene_file, lambda s: s["fluid"][0].update(shape="box", lox=[0, 0, 0]))
    with pytest.raises(ConfigError, match=r"fluid\[0\]\.lox: unknown key \(known: center, hi, lo, radius"):
        load(tiny_dam)


def test_repository_configs_load():
    from tests.conftest import ROOT

    for name in ("default.yaml", "paper.yaml"):
        loaded = load(ROOT / "configs" / name)
        assert len(loaded.scenes) >= 6


def test_exponents_without_a_point_are_numbers(tiny_dam):
    """YAML 1.1 (PyYAML) reads ``1e-2`` as text; the loader reads it as YAML 1.2 does, a number."""
    tiny_dam.write_text(tiny_dam.read_text().replace("particle_radius: 0.0125", "particle_radius: 125e-4"))
    assert "125e-4" in tiny_dam.read_text()
    assert load(tiny_dam).config.simulate.particle_radius == 0.0125


@pytest.mark.parametrize("damage, words", [
    (lambda p: p.write_bytes(b"seed: 1\n# caf\xe9\n"), "is not UTF-8 text (byte"),
    (lambda p: (p.unlink(), p.mkdir()), "is a folder, not a YAML file"),
])
def test_an_unreadable_config_file_is_one_line_naming_it(tiny_dam, capsys, damage, words):
    damage(tiny_dam)
    code, err = _run(tiny_dam, capsys)
    assert code == 2 and str(tiny_dam) in err and words in err
    assert len(err.strip().splitlines()) == 1


def test_a_fluid_body_outside_its_domain_names_the_scene_file(tiny_dam):
    scene_file = tiny_dam.parent / "scenes" / "tiny_dam.yaml"
    _edit(scene_file, lambda s: s["fluid"][0].update(hi=[0.2, 0.9, 0.3]))  # above the 0.5 m domain
    with pytest.raises(ConfigError, match=r"fluid\[0\]: reaches .* outside the domain") as err:
        load(tiny_dam)
    assert str(scene_file) in str(err.value)
    _edit(scene_file, lambda s: (s["fluid"][0].update(hi=[0.2, 0.3, 0.3]), s.update(domain_hi=[0.6, 0.0, 0.3])))
    with pytest.raises(ConfigError, match=r"domain_hi: must exceed domain_lo"):
        load(tiny_dam)


def test_frames_that_cannot_fit_on_the_disk_are_refused_before_the_first(tiny_dam, capsys):
    _edit(tiny_dam, lambda b: b["simulate"].update(frames=10**12))
    code, err = _run(tiny_dam, capsys)
    assert code != 0 and "simulate.frames: 1,000,000,000,000 more frames of scene 'tiny_dam'" in err
    assert "GB free; lower simulate.frames" in err and len(err.strip().splitlines()) == 1
    assert not list((tiny_dam.parent / "data").rglob("frame_*.npz"))
