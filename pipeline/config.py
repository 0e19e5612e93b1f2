"""Typed configuration: YAML (``safe_load``) into frozen dataclasses, one per stage.

Every field carries its unit in the docstring below it. Loading rejects unknown keys, wrong types
and out-of-range values with a :class:`ConfigError` naming the file and the key path, so a typo
never silently falls back to a default. Relative paths inside a file resolve against that file.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml


class ConfigError(ValueError):
    """A configuration problem, located by file and key path."""

    def __init__(self, file: str | Path, key: str, message: str):
        self.file, self.key, self.message = str(file), key, message
        where = f"{file}: {key}" if key else f"{file}"
        super().__init__(f"{where}: {message}")


def _f(default: Any = dataclasses.MISSING, *, gt=None, ge=None, le=None, lt=None, factory=None):
    """A dataclass field with optional numeric bounds checked at load time."""
    meta = {k: v for k, v in dict(gt=gt, ge=ge, le=le, lt=lt).items() if v is not None}
    if factory is not None:
        return field(default_factory=factory, metadata=meta)
    return field(default=default, metadata=meta)


Vec3 = tuple[float, float, float]


# ---------------------------------------------------------------------------------------------
# Scenes (configs/scenes/<name>.yaml)


@dataclass(frozen=True)
class FluidShape:
    """An initial block of fluid filled with particles on a cubic lattice."""

    shape: Literal["box", "sphere"]
    """Which primitive."""
    lo: Vec3 = (0.0, 0.0, 0.0)
    """Box: minimum corner (m)."""
    hi: Vec3 = (0.0, 0.0, 0.0)
    """Box: maximum corner (m)."""
    center: Vec3 = (0.0, 0.0, 0.0)
    """Sphere: centre (m)."""
    radius: float = _f(0.0, ge=0.0)
    """Sphere: radius (m)."""
    velocity: Vec3 = (0.0, 0.0, 0.0)
    """Initial velocity (m/s)."""


@dataclass(frozen=True)
class Obstacle:
    """A static solid the fluid flows around."""

    shape: Literal["box", "sphere"]
    """Which primitive."""
    lo: Vec3 = (0.0, 0.0, 0.0)
    """Box: minimum corner (m)."""
    hi: Vec3 = (0.0, 0.0, 0.0)
    """Box: maximum corner (m)."""
    center: Vec3 = (0.0, 0.0, 0.0)
    """Sphere: centre (m)."""
    radius: float = _f(0.0, ge=0.0)
    """Sphere: radius (m)."""


@dataclass(frozen=True)
class Emitter:
    """A round nozzle injecting layers of particles with a velocity over a time window."""

    position: Vec3
    """Centre of the nozzle opening (m)."""
    direction: Vec3
    """Direction of the jet (normalised on use)."""
    radius: float = _f(0.05, gt=0.0)
    """Nozzle radius (m)."""
    speed: float = _f(1.5, gt=0.0)
    """Jet speed (m/s)."""
    start: float = _f(0.0, ge=0.0)
    """Time the nozzle opens (s)."""
    end: float = _f(1.0, ge=0.0)
    """Time the nozzle closes (s)."""


@dataclass(frozen=True)
class StaticCamera:
    """A camera that stays put."""

    eye: Vec3
    """Camera position (m)."""
    target: Vec3
    """Point looked at (m)."""
    fov_deg: float = _f(40.0, gt=0.0, lt=180.0)
    """Vertical field of view (degrees)."""


@dataclass(frozen=True)
class OrbitCamera:
    """A camera circling a vertical axis through ``target`` over the sequence."""

    target: Vec3
    """Point looked at and orbit centre (m)."""
    distance: float = _f(2.5, gt=0.0)
    """Horizontal distance from the axis (m)."""
    height: float = 1.0
    """Height of the eye above the target (m)."""
    start_deg: float = 0.0
    """Azimuth of the first frame, from +Z towards +X (degrees)."""
    sweep_deg: float = 90.0
    """Azimuth travelled over the whole sequence (degrees)."""
    fov_deg: float = _f(40.0, gt=0.0, lt=180.0)
    """Vertical field of view (degrees)."""


@dataclass(frozen=True)
class Cameras:
    """The two camera paths every scene defines (the paper renders both)."""

    static: StaticCamera
    """The fixed view."""
    orbit: OrbitCamera
    """The moving view."""


@dataclass(frozen=True)
class ParticleSource:
    """An external particle sequence used instead of a simulation."""

    pattern: str
    """Glob of frame files (VTK, BGEO, PLY or XYZ), sorted by name; relative to the scene file."""
    particle_radius: float = _f(gt=0.0)
    """Particle radius of the sequence (its units)."""
    fps: float = _f(30.0, gt=0.0)
    """Frame rate of the sequence (frames/s)."""


@dataclass(frozen=True)
class SceneConfig:
    """One scene: a simulation set-up or an imported sequence, plus its cameras."""

    name: str
    """Scene name (also its cache and output folder name)."""
    cameras: Cameras
    """Static and orbiting camera."""
    domain_lo: Vec3 = (0.0, 0.0, 0.0)
    """Container minimum corner (m); y is up."""
    domain_hi: Vec3 = (1.6, 1.2, 0.8)
    """Container maximum corner (m)."""
    fluid: tuple[FluidShape, ...] = ()
    """Initial fluid bodies."""
    obstacles: tuple[Obstacle, ...] = ()
    """Static solids."""
    emitters: tuple[Emitter, ...] = ()
    """Nozzles."""
    source: ParticleSource | None = None
    """Set for an imported sequence: no simulation is run."""


# ---------------------------------------------------------------------------------------------
# Stages


@dataclass(frozen=True)
class SimulateConfig:
    """Position Based Fluids (Macklin & Mueller 2013) parameters."""

    particle_radius: float = _f(0.0125, gt=0.0)
    """Particle radius r (m); particles start on a lattice of spacing 2r."""
    rest_density: float = _f(1000.0, gt=0.0)
    """Rest density rho_0 (kg/m^3)."""
    kernel_radius_factor: float = _f(4.0, gt=1.0)
    """SPH support h as a multiple of r."""
    frames: int = _f(100, ge=1)
    """Frames to simulate."""
    fps: float = _f(30.0, gt=0.0)
    """Output frame rate (frames/s)."""
    substeps: int = _f(4, ge=1)
    """Solver steps per frame (time step = 1 / (fps * substeps))."""
    iterations: int = _f(4, ge=1)
    """Density-constraint iterations per step."""
    gravity: Vec3 = (0.0, -9.81, 0.0)
    """Gravity (m/s^2)."""
    relaxation: float = _f(100.0, gt=0.0)
    """Constraint-force-mixing epsilon in lambda's denominator (1/m^2 scale, as in the paper)."""
    artificial_pressure_k: float = _f(1e-5, ge=0.0)
    """Tensile-instability correction k (m^2, the scale of lambda; the paper's 0.1 explodes here,
    1e-4 blew up a dam break at frame 26, 1e-5 and 3e-5 stayed stable)."""
    artificial_pressure_n: int = _f(4, ge=1)
    """Exponent n of the artificial pressure."""
    artificial_pressure_dq: float = _f(0.2, gt=0.0, lt=1.0)
    """Reference distance dq as a fraction of h."""
    xsph_viscosity: float = _f(0.01, ge=0.0, le=1.0)
    """XSPH velocity smoothing c (dimensionless)."""
    vorticity_epsilon: float = _f(0.005, ge=0.0)
    """Vorticity confinement strength epsilon (m/s): acceleration = epsilon (N x omega)."""
    max_speed: float = _f(50.0, gt=0.0)
    """Speed above which the run is declared blown up (m/s)."""
    max_neighbours: int = _f(64, ge=8)
    """Capacity of a particle's half neighbour list: the neighbours after it in sorted order, about
    half of all its neighbours (a full neighbourhood at rest density holds about 30)."""
    threads: int = _f(0, ge=0)
    """CPU threads for chunked kernel launches (0: one per core)."""


@dataclass(frozen=True)
class DatasetConfig:
    """Screen-space inputs and mesh targets (stage 2)."""

    width: int = _f(256, ge=8)
    """Image width (px)."""
    height: int = _f(256, ge=8)
    """Image height (px)."""
    frame_stride: int = _f(2, ge=1)
    """Use every n-th simulated frame."""
    max_frames: int = _f(0, ge=0)
    """Use at most this many frames per scene (0: all)."""
    filter_mode: Literal["fast", "exact"] = "fast"
    """'fast': the bilateral filter as two separable passes (cost linear in its radius) and
    narrow-range passes with at most ``nrf_max_taps`` taps a side (cost independent of the
    projected particle size); 'exact': the brute-force 2D bilateral window and narrow-range passes
    that read every pixel of their radius (the filters before 2026-11, slow at high resolution)."""
    nrf_max_taps: int = _f(16, ge=1)
    """'fast' mode: most taps on each side of a narrow-range pass; wider kernels sample every k-th
    pixel (the 2D clean-up pass removes the pixel-scale noise this leaves)."""
    bilateral_sigma_px_scale: float = _f(2.0, gt=0.0)
    """Bilateral spatial sigma as a multiple of the projected particle radius (px / px)."""
    bilateral_range_radii: float = _f(6.0, gt=0.0)
    """Bilateral range sigma in particle radii (depth units / r)."""
    bilateral_max_radius_px: int = _f(24, ge=1)
    """Cap on the bilateral kernel radius (px)."""
    gaussian_sigma_px: float = _f(3.0, gt=0.0)
    """Sigma of the naive fixed-size Gaussian depth blur, the weakest baseline (px)."""
    nrf_delta_radii: float = _f(10.5, gt=0.0)
    """Narrow-range delta in particle radii (Truong's reference value)."""
    nrf_mu_radii: float = _f(1.0, gt=0.0)
    """Narrow-range mu in particle radii."""
    nrf_radius_scale: float = _f(4.0, gt=0.0)
    """Narrow-range kernel radius as a multiple of the projected particle radius (px / px)."""
    nrf_max_radius_px: int = _f(100, ge=1)
    """Cap on the narrow-range kernel radius (px)."""
    nrf_iterations: int = _f(3, ge=1)
    """Alternating separable passes of the narrow-range filter."""
    nrf_cleanup_radius_px: int = _f(4, ge=0)
    """Radius of the final 2D clean-up pass (px)."""
    aniso_smoothing: float = _f(0.9, ge=0.0, le=1.0)
    """Laplacian smoothing lambda of the particle centres (Yu & Turk)."""
    aniso_kr: float = _f(4.0, ge=1.0)
    """Largest-to-smallest eigenvalue ratio cap k_r."""
    aniso_ks: float = _f(1400.0, gt=0.0)
    """Eigenvalue scale k_s."""
    aniso_kn: float = _f(0.5, gt=0.0)
    """Isotropic kernel scale for isolated particles k_n."""
    aniso_neps: int = _f(25, ge=1)
    """Neighbour count below which a particle stays a sphere (N_eps)."""
    aniso_kernel_radius: float = _f(5.0, gt=0.0)
    """Density kernel radius h as a multiple of r; neighbours for the covariance lie within 2h."""
    iso_level: float = _f(0.5, gt=0.0)
    """Iso value of the normalised density (1 is a particle's rest density)."""
    grid_cells_per_radius: float = _f(1.5, gt=0.0)
    """Density grid resolution (cells per particle radius)."""
    max_grid_cells: int = _f(320, ge=16)
    """Cap on the grid size per axis (cells); the paper used about 270."""
    target: Literal["mesh", "raytrace"] = "mesh"
    """The reference surface: 'mesh' (marching cubes of the density on a grid, ray-cast) or
    'raytrace' (each pixel's ray marched through the density to the iso-level, no grid)."""
    raytrace_step_radii: float = _f(0.5, gt=0.0)
    """'raytrace': march step along the ray, in particle radii (a crossing is then bisected)."""
    raytrace_bisections: int = _f(10, ge=0)
    """'raytrace': bisection steps that refine each crossing (each halves the depth error)."""
    keep_meshes: bool = False
    """Also write the target meshes (PLY) for inspection."""
    validation_camera: Literal["orbit", "static", "none"] = "orbit"
    """Camera path whose frames form each scene's validation split ('none': all train)."""
    holdout_scenes: tuple[str, ...] = ()
    """Scenes kept entirely out of training (their frames are all validation)."""
    workers: int = _f(0, ge=0)
    """Parallel frame workers (0: one per core)."""


@dataclass(frozen=True)
class TrainConfig:
    """cGAN refiner of Choi et al. 2021 (stage 3)."""

    epochs: int = _f(20, ge=1)
    """Training epochs (the paper: 100)."""
    batch_size: int = _f(8, ge=1)
    """Images per batch."""
    crop: int = _f(128, ge=16)
    """Random crop side (px; a multiple of the generator stride)."""
    crops_per_frame: int = _f(1, ge=1)
    """Random crops drawn from each training frame per epoch."""
    lr: float = _f(2e-4, gt=0.0)
    """Initial Adam learning rate."""
    beta1: float = _f(0.5, ge=0.0, lt=1.0)
    """Adam beta1."""
    lr_decay: float = _f(0.95, gt=0.0, le=1.0)
    """Learning-rate factor applied after each epoch."""
    lambda_content: float = _f(100.0, ge=0.0)
    """Weight lambda_C of the content loss."""
    lambda_normal: float = _f(10.0, ge=0.0)
    """Weight lambda_N of the normal-constraint loss (0 disables it)."""
    lambda_adversarial: float = _f(1.0, ge=0.0)
    """Weight of the adversarial term."""
    content_loss: Literal["l1", "l2"] = "l1"
    """Content loss norm (the paper prefers L1)."""
    auxiliary_features: bool = True
    """Feed raw and blurred depth with the normal (5 input channels) or the normal alone (3)."""
    input_splat: Literal["sphere", "ellipsoid"] = "ellipsoid"
    """Which splat the generator's input is made of: the particles' anisotropic ellipsoids (the
    dataset's ``aniso_bilateral`` and ``aniso`` channels) or spheres (``bilateral`` and ``Z``).
    Trained alike for 15 epochs, the ellipsoid input measured 9.46 deg mean held-out error
    against 10.99 for spheres (configs/ablations/*_input.yaml)."""
    train_scenes: tuple[str, ...] = ()
    """Scenes to train on (empty: every configured scene not held out)."""
    gen_base_channels: int = _f(24, ge=4)
    """Generator channels at full resolution."""
    gen_downsamples: int = _f(2, ge=0, le=5)
    """Stride-2 stages in the generator (its stride is 2^this)."""
    gen_res_blocks: int = _f(4, ge=0)
    """Residual blocks at the bottleneck."""
    disc_base_channels: int = _f(16, ge=4)
    """Discriminator channels of its first convolution."""
    disc_layers: int = _f(4, ge=1, le=7)
    """Stride-2 convolutions in the discriminator before its fully connected layer."""
    val_frames: int = _f(16, ge=1)
    """Validation frames evaluated each epoch (spread over the held-out split)."""
    mixed_precision: bool = True
    """Use autocast on CUDA (ignored on the CPU)."""
    threads: int = _f(0, ge=0)
    """torch CPU threads (0: one per core)."""


@dataclass(frozen=True)
class RenderConfig:
    """Deferred shading and outputs (stage 4)."""

    width: int = _f(256, ge=8)
    """Output width (px)."""
    height: int = _f(256, ge=8)
    """Output height (px)."""
    camera: Literal["static", "orbit"] = "static"
    """Camera path to render."""
    method: Literal["refined", "gaussian", "bilateral", "nrf", "aniso", "aniso_nrf", "mesh"] = "refined"
    """Normal-map source."""
    weights: str = "shipped"
    """Generator: 'shipped' (in the package), 'trained' (this config's best checkpoint, training
    it if needed) or a checkpoint path (relative to the working directory)."""
    frame_stride: int = _f(1, ge=1)
    """Render every n-th frame."""
    max_frames: int = _f(0, ge=0)
    """Render at most this many frames (0: all)."""
    normal_threshold: float = _f(0.5, ge=0.0, le=1.0)
    """Drop refined pixels whose normal is shorter than this (the paper's noise removal)."""
    fluid_color: Vec3 = (0.55, 0.78, 0.95)
    """Transmittance per metre of the fluid (linear RGB, Beer-Lambert)."""
    absorption: float = _f(4.0, ge=0.0)
    """Absorption strength multiplying -log(fluid_color) (1/m)."""
    ior: float = _f(1.33, gt=1.0)
    """Index of refraction (water 1.33)."""
    refraction_strength: float = _f(0.08, ge=0.0)
    """Screen-space refraction offset per metre of thickness (fraction of the image width)."""
    diffuse_weight: float = _f(0.1, ge=0.0)
    """Weight of the Lambertian term tinted by the fluid colour (scattering inside the fluid)."""
    specular: Literal["blinn", "ggx"] = "ggx"
    """Specular model."""
    roughness: float = _f(0.08, gt=0.0, le=1.0)
    """GGX roughness (alpha = roughness^2) or Blinn exponent from it."""
    light_dir: Vec3 = (0.4, 0.8, 0.45)
    """Direction towards the sun (world space)."""
    light_intensity: float = _f(3.0, ge=0.0)
    """Sun radiance scale."""
    environment: str = ""
    """HDR lat-long EXR map for reflections ('' : procedural sky)."""
    exposure: float = 0.0
    """Exposure for previews (stops)."""
    video_fps: float = _f(30.0, gt=0.0)
    """Preview video frame rate."""
    comparison: bool = True
    """Also write the side-by-side comparison (bilateral | nrf | refined | mesh)."""


@dataclass(frozen=True)
class EvaluateConfig:
    """Held-out metrics (the evaluate stage)."""

    methods: tuple[str, ...] = ("gaussian", "bilateral", "nrf", "aniso", "aniso_nrf", "refined")
    """Methods compared with the mesh reference."""
    frames_per_sequence: int = _f(0, ge=0)
    """Frames evaluated per held-out sequence, evenly spread over it (0: all)."""
    imported_scenes: tuple[str, ...] = ()
    """Imported particle scenes also evaluated."""


@dataclass(frozen=True)
class Config:
    """The whole pipeline configuration (configs/*.yaml)."""

    scenes: tuple[str, ...]
    """Scene names; each is configs/scenes/<name>.yaml (or under scene_dir)."""
    seed: int = 0
    """Seed of every random choice (simulation jitter, crops, initialisation)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Compute device ('auto': CUDA when Warp and torch see one); DEEP_SSFR_DEVICE overrides."""
    scene_dir: str = "scenes"
    """Folder of scene files, relative to the config file that sets it."""
    data_dir: str = "../data"
    """Cache root, relative to the config file that sets it."""
    simulate: SimulateConfig = _f(factory=SimulateConfig)
    """Stage 1."""
    dataset: DatasetConfig = _f(factory=DatasetConfig)
    """Stage 2."""
    train: TrainConfig = _f(factory=TrainConfig)
    """Stage 3."""
    render: RenderConfig = _f(factory=RenderConfig)
    """Stage 4."""
    evaluate: EvaluateConfig = _f(factory=EvaluateConfig)
    """Metrics."""


# ---------------------------------------------------------------------------------------------
# Loading


def _check_bounds(value: float, meta: dict, file, key: str) -> None:
    for op, bound in meta.items():
        ok = {"gt": value > bound, "ge": value >= bound, "lt": value < bound, "le": value <= bound}[op]
        if not ok:
            sym = {"gt": ">", "ge": ">=", "lt": "<", "le": "<="}[op]
            raise ConfigError(file, key, f"must be {sym} {bound}, got {value}")


def _convert(tp: Any, value: Any, file, key: str) -> Any:
    """Convert a YAML value to the annotated type, or raise naming the key."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _convert(inner[0], value, file, key)
    if origin is Literal:
        if value not in args:
            raise ConfigError(file, key, f"must be one of {list(args)}, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(file, key, f"must be a list, got {type(value).__name__}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, file, f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(file, key, f"must have {len(args)} elements, got {len(value)}")
        return tuple(_convert(a, v, file, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True)))
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, value, file, key)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(file, key, f"must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(file, key, f"must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(file, key, f"must be a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(file, key, f"must be a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(file, key, f"must be a string, got {value!r}")
        return value
    raise TypeError(f"unsupported config type {tp}")


def from_dict(cls: type, data: Any, file: str | Path = "<dict>", prefix: str = ""):
    """Build dataclass ``cls`` from a mapping, rejecting unknown keys and checking types/bounds."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(file, prefix, f"must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for k in data:
        if k not in fields:
            raise ConfigError(file, f"{prefix}.{k}" if prefix else str(k),
                              f"unknown key (known: {', '.join(sorted(fields))})")
    kwargs = {}
    for name, f in fields.items():
        key = f"{prefix}.{name}" if prefix else name
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(file, key, "missing required key")
            continue
        value = _convert(hints[name], data[name], file, key)
        if isinstance(value, int | float) and not isinstance(value, bool):
            _check_bounds(value, dict(f.metadata), file, key)
        kwargs[name] = value
    return cls(**kwargs)


def to_dict(obj: Any) -> Any:
    """Plain JSON/YAML-ready values of a config dataclass (tuples become lists)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple | list):
        return [to_dict(v) for v in obj]
    return obj


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that rejects a key given twice in one mapping (YAML keeps the last
    silently, so a duplicated setting would quietly override the first)."""

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


def read_yaml(path: Path) -> Any:
    """Load a YAML file safely (no duplicate keys), turning IO and syntax errors into ConfigError."""
    try:
        with open(path, encoding="utf-8") as fh:
            return yaml.load(fh, Loader=_UniqueKeyLoader)  # a SafeLoader: no arbitrary objects
    except FileNotFoundError:
        raise ConfigError(path, "", "file not found") from None
    except yaml.YAMLError as exc:
        raise ConfigError(path, "", f"invalid YAML: {exc}".replace("\n", " ")) from None


@dataclass(frozen=True)
class Loaded:
    """A loaded pipeline config with its scenes and where it came from."""

    config: Config
    scenes: dict[str, SceneConfig]
    path: Path
    data_dir: Path
    imported: dict[str, SceneConfig] = field(default_factory=dict)
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
        for key, default in (("scene_dir", "scenes"), ("data_dir", "../data")):
            raw.setdefault(key, str((path.parent / default).resolve()))
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
