"""Config files into a :class:`pipeline.config.Config`: strict YAML (a duplicated key is an error,
``1e-9`` a number), a ``base:`` file under another, scene files from ``scene_dir``, paths relative to
the file that names them, and the stage's command-line overrides on top."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

import yaml

from pipeline.config import Config, ConfigError, SceneConfig, from_dict


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that rejects a key given twice in one mapping (YAML keeps the last
    silently, so a duplicated setting would quietly override the first), and reads ``1e-9`` as the
    number YAML 1.2 says it is (PyYAML's YAML 1.1 wants ``1.0e-9`` and otherwise makes it text)."""

    yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}

    def construct_mapping(self, node, deep=False):
        seen: dict = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r} (first on line {seen[key] + 1}, again on line "
                    f"{key_node.start_mark.line + 1})", key_node.start_mark)
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"))


def read_yaml(path: Path) -> Any:
    """Load a YAML file safely (no duplicate keys), turning IO and syntax errors into ConfigError."""
    try:
        with open(path, encoding="utf-8") as fh:
            return yaml.load(fh, Loader=_UniqueKeyLoader)  # a SafeLoader: no arbitrary objects
    except FileNotFoundError:
        raise ConfigError(path, "", "file not found") from None
    except IsADirectoryError:
        raise ConfigError(path, "", "is a folder, not a YAML file") from None
    except PermissionError:
        raise ConfigError(path, "", "cannot be read (permission denied)") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(path, "", f"is not UTF-8 text (byte {exc.start}): save it as UTF-8") from None
    except yaml.YAMLError as exc:
        raise ConfigError(path, "", f"invalid YAML: {exc}".replace("\n", " ")) from None


@dataclasses.dataclass(frozen=True)
class Loaded:
    """A loaded pipeline config with its scenes and where it came from."""

    config: Config
    scenes: dict[str, SceneConfig]
    path: Path
    data_dir: Path
    imported: dict[str, SceneConfig] = dataclasses.field(default_factory=dict)
    """Imported particle scenes evaluated besides the held-out sequences (evaluate.imported_scenes)."""

    def scene(self, name: str) -> SceneConfig:
        """The named scene, or a ConfigError listing the configured ones."""
        if name not in self.scenes:
            raise ConfigError(self.path, "scenes", f"scene {name!r} is not configured "
                              f"(configured: {', '.join(self.scenes)})")
        return self.scenes[name]


def _deep_update(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _deep_update(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def load_scene(path: Path) -> SceneConfig:
    """Load one scene file; its source pattern is made absolute against the file's folder."""
    scene = from_dict(SceneConfig, read_yaml(path), path)
    if scene.source is not None:
        pattern = Path(scene.source.pattern)
        if not pattern.is_absolute():
            pattern = (path.parent / pattern).resolve()
        scene = dataclasses.replace(scene, source=dataclasses.replace(scene.source, pattern=str(pattern)))
    if scene.source is None and not scene.fluid and not scene.emitters:
        raise ConfigError(path, "fluid", "a simulated scene needs fluid shapes or emitters")
    if any(a >= b for a, b in zip(scene.domain_lo, scene.domain_hi, strict=True)):
        raise ConfigError(path, "domain_hi", f"must exceed domain_lo {list(scene.domain_lo)} on every axis, "
                          f"got {list(scene.domain_hi)}")
    for i, shape in enumerate(scene.fluid):  # the seeding would clip it to the container without a word
        lo, hi = ((shape.lo, shape.hi) if shape.shape == "box" else
                  ([c - shape.radius for c in shape.center], [c + shape.radius for c in shape.center]))
        if any(a < d - 1e-9 for a, d in zip(lo, scene.domain_lo, strict=True)) or \
                any(b > d + 1e-9 for b, d in zip(hi, scene.domain_hi, strict=True)):
            raise ConfigError(path, f"fluid[{i}]", f"reaches {list(lo)}..{list(hi)}, outside the domain "
                              f"{list(scene.domain_lo)}..{list(scene.domain_hi)}; move it inside or widen the domain")
    return scene


_PATH_KEYS = ("scene_dir", "data_dir")


def read_layered(path: Path, seen: tuple[Path, ...] = ()) -> dict:
    """A config file merged over the file its ``base`` key names (a preset over the default).

    Relative ``scene_dir`` / ``data_dir`` stay relative to the file that sets them.
    """
    path = Path(path).resolve()
    if path in seen:
        raise ConfigError(path, "base", "configs include each other in a cycle")
    raw = read_yaml(path) or {}
    if not isinstance(raw, dict):
        raise ConfigError(path, "", "top level must be a mapping")
    for key in _PATH_KEYS:
        if isinstance(raw.get(key), str):
            raw[key] = str((path.parent / raw[key]).resolve())
    base = raw.pop("base", None)
    if base is None:
        defaults = {f.name: f.default for f in dataclasses.fields(Config)}
        for key in _PATH_KEYS:  # the defaults too are relative to the (base) config file
            raw.setdefault(key, str((path.parent / defaults[key]).resolve()))
        return raw
    if not isinstance(base, str):
        raise ConfigError(path, "base", "must be a path to another config file")
    return _deep_update(read_layered(path.parent / base, (*seen, path)), raw)


def load(path: str | Path, overrides: dict | None = None, only_scene: str | None = None) -> Loaded:
    """Load a pipeline config and its scene files.

    ``overrides`` is a nested mapping applied over the file (tests shrink configs this way);
    ``only_scene`` restricts the run to one configured scene.
    """
    path = Path(path)
    raw = read_layered(path)
    if overrides:
        raw = _deep_update(raw, overrides)
    config = from_dict(Config, raw, path)
    scene_dir = Path(config.scene_dir)
    names = config.scenes
    if only_scene:
        if only_scene not in names:
            raise ConfigError(path, "scenes", f"scene {only_scene!r} is not configured "
                              f"(configured: {', '.join(names)})")
        names = (only_scene,)
    scenes = {}
    for name in names:
        scene_path = scene_dir / f"{name}.yaml"
        if not scene_path.exists():
            raise ConfigError(path, "scenes", f"unknown scene {name!r}: no file {scene_path}")
        scene = load_scene(scene_path)
        if scene.name != name:
            raise ConfigError(scene_path, "name", f"is {scene.name!r} but the file is named {name!r}")
        scenes[name] = scene
    for held in config.dataset.holdout_scenes:
        if held not in config.scenes:
            raise ConfigError(path, "dataset.holdout_scenes", f"{held!r} is not in scenes")
    imported = {}
    for name in config.evaluate.imported_scenes:
        scene_path = scene_dir / f"{name}.yaml"
        if not scene_path.exists():
            raise ConfigError(path, "evaluate.imported_scenes", f"unknown scene {name!r}: no file {scene_path}")
        imported[name] = load_scene(scene_path)
        if imported[name].source is None:
            raise ConfigError(scene_path, "source", "an evaluate.imported_scenes entry must name a particle source")
    return Loaded(config, scenes, path, Path(config.data_dir), imported)
