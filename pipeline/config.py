"""Typed configuration: YAML (``safe_load``) into frozen, documented dataclasses, one per stage.

Every field carries its unit in the docstring below it and its bounds in its ``Field``; pydantic
validates a loaded file strictly (no "5" for 5, no 1 for true, no NaN or infinity, no unknown
keys) and every problem becomes a :class:`ConfigError` naming the file and the key path, so a
typo never silently falls back to a default. Relative paths inside a file resolve against that
file.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import typing
from pathlib import Path
from typing import Any, Literal

from pydantic import ConfigDict, Field, TypeAdapter, ValidationError
from pydantic.dataclasses import dataclass


class ConfigError(ValueError):
    """A configuration problem, located by file and key path."""

    def __init__(self, file: str | Path, key: str, message: str):
        self.file, self.key, self.message = str(file), key, message
        where = f"{file}: {key}" if key else f"{file}"
        super().__init__(f"{where}: {message}")


_RULES = ConfigDict(extra="forbid", allow_inf_nan=False)
"""Every config dataclass: unknown keys and non-finite numbers are errors (files load strictly)."""


Vec3 = tuple[float, float, float]
Method = Literal["gaussian", "bilateral", "nrf", "aniso", "aniso_nrf", "refined", "metaball", "mesh"]
"""The normal-map methods (``pipeline.methods``): screen-space filters of sphere splats, ellipsoid
splats with and without the narrow-range filter, the cGAN refiner, the image-space metaballs of
the pix2pix network (``pipeline.metaball``), and the reference mesh."""
METHODS: tuple[str, ...] = typing.get_args(Method)


# ---------------------------------------------------------------------------------------------
# Scenes (configs/scenes/<name>.yaml)


@dataclass(frozen=True, config=_RULES)
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
    radius: float = Field(0.0, ge=0.0)
    """Sphere: radius (m)."""
    velocity: Vec3 = (0.0, 0.0, 0.0)
    """Initial velocity (m/s)."""


@dataclass(frozen=True, config=_RULES)
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
    radius: float = Field(0.0, ge=0.0)
    """Sphere: radius (m)."""


@dataclass(frozen=True, config=_RULES)
class Emitter:
    """A round nozzle injecting layers of particles with a velocity over a time window."""

    position: Vec3
    """Centre of the nozzle opening (m)."""
    direction: Vec3
    """Direction of the jet (normalised on use)."""
    radius: float = Field(0.05, gt=0.0)
    """Nozzle radius (m)."""
    speed: float = Field(1.5, gt=0.0)
    """Jet speed (m/s)."""
    start: float = Field(0.0, ge=0.0)
    """Time the nozzle opens (s)."""
    end: float = Field(1.0, ge=0.0)
    """Time the nozzle closes (s)."""


@dataclass(frozen=True, config=_RULES)
class StaticCamera:
    """A camera that stays put."""

    eye: Vec3
    """Camera position (m)."""
    target: Vec3
    """Point looked at (m)."""
    fov_deg: float = Field(40.0, gt=0.0, lt=180.0)
    """Vertical field of view (degrees)."""


@dataclass(frozen=True, config=_RULES)
class OrbitCamera:
    """A camera circling a vertical axis through ``target`` over the sequence."""

    target: Vec3
    """Point looked at and orbit centre (m)."""
    distance: float = Field(2.5, gt=0.0)
    """Horizontal distance from the axis (m)."""
    height: float = 1.0
    """Height of the eye above the target (m)."""
    start_deg: float = 0.0
    """Azimuth of the first frame, from +Z towards +X (degrees)."""
    sweep_deg: float = 90.0
    """Azimuth travelled over the whole sequence (degrees)."""
    fov_deg: float = Field(40.0, gt=0.0, lt=180.0)
    """Vertical field of view (degrees)."""


@dataclass(frozen=True, config=_RULES)
class Cameras:
    """The two camera paths every scene defines (the paper renders both)."""

    static: StaticCamera
    """The fixed view."""
    orbit: OrbitCamera
    """The moving view."""


@dataclass(frozen=True, config=_RULES)
class ParticleSource:
    """An external particle sequence used instead of a simulation."""

    pattern: str
    """Frame files: a glob or splashsurf's ``{}`` for the frame number (VTK, VTU, BGEO, PLY or XYZ),
    ordered by frame number; relative to the scene file."""
    particle_radius: float = Field(gt=0.0)
    """Particle radius of the sequence (its units)."""
    fps: float = Field(30.0, gt=0.0)
    """Frame rate of the sequence (frames/s)."""
    up: Literal["y", "z"] = "y"
    """The files' up axis; Z-up data is turned to the pipeline's Y-up."""


@dataclass(frozen=True, config=_RULES)
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


@dataclass(frozen=True, config=_RULES)
class SimulateConfig:
    """Position Based Fluids (Macklin & Mueller 2013) parameters."""

    particle_radius: float = Field(0.0125, gt=0.0)
    """Particle radius r (m); particles start on a lattice of spacing 2r."""
    rest_density: float = Field(1000.0, gt=0.0)
    """Rest density rho_0 (kg/m^3)."""
    kernel_radius_factor: float = Field(4.0, gt=1.0)
    """SPH support h as a multiple of r."""
    frames: int = Field(100, ge=1)
    """Frames to simulate."""
    fps: float = Field(30.0, gt=0.0)
    """Output frame rate (frames/s)."""
    substeps: int = Field(4, ge=1)
    """Solver steps per frame (time step = 1 / (fps * substeps))."""
    iterations: int = Field(4, ge=1)
    """Density-constraint iterations per step."""
    gravity: Vec3 = (0.0, -9.81, 0.0)
    """Gravity (m/s^2)."""
    relaxation: float = Field(100.0, gt=0.0)
    """Constraint-force-mixing epsilon in lambda's denominator (1/m^2 scale, as in the paper)."""
    artificial_pressure_k: float = Field(1e-5, ge=0.0)
    """Tensile-instability correction k (m^2, the scale of lambda; the paper's 0.1 explodes here,
    1e-4 blew up a dam break at frame 26, 1e-5 and 3e-5 stayed stable)."""
    artificial_pressure_n: int = Field(4, ge=1)
    """Exponent n of the artificial pressure."""
    artificial_pressure_dq: float = Field(0.2, gt=0.0, lt=1.0)
    """Reference distance dq as a fraction of h."""
    xsph_viscosity: float = Field(0.01, ge=0.0, le=1.0)
    """XSPH velocity smoothing c (dimensionless)."""
    vorticity_epsilon: float = Field(0.005, ge=0.0)
    """Vorticity confinement strength epsilon (m/s): acceleration = epsilon (N x omega)."""
    max_speed: float = Field(50.0, gt=0.0)
    """Speed above which the run is declared blown up (m/s)."""
    max_neighbours: int = Field(64, ge=8)
    """Capacity of a particle's half neighbour list: the neighbours after it in sorted order, about
    half of all its neighbours (a full neighbourhood at rest density holds about 30)."""
    threads: int = Field(0, ge=0)
    """CPU threads for chunked kernel launches (0: one per core)."""
    pair_passes: Literal["auto", "scatter", "gather"] = "auto"
    """How the solver's pair passes sum: 'scatter' over a half list, each pair once and its share
    added to both ends (on the CPU in race-free phases, bit-identical for a config and thread count;
    on CUDA with float atomics, so GPU runs agree only to rounding); 'gather' over a full list,
    each particle summing its own pairs (no atomics, half the launches, GPU runs repeat exactly;
    twice the pair arithmetic); 'auto': gather on CUDA, scatter on the CPU. Both give the same
    physics, to the rounding of their sums' order."""


@dataclass(frozen=True, config=_RULES)
class DatasetConfig:
    """Screen-space inputs and mesh targets (stage 2)."""

    width: int = Field(256, ge=8)
    """Image width (px)."""
    height: int = Field(256, ge=8)
    """Image height (px)."""
    frame_stride: int = Field(2, ge=1)
    """Use every n-th simulated frame."""
    max_frames: int = Field(0, ge=0)
    """Use at most this many frames per scene (0: all)."""
    filter_mode: Literal["fast", "exact"] = "fast"
    """'fast': the bilateral filter as two separable passes (cost linear in its radius) and
    narrow-range passes with at most ``nrf_max_taps`` taps a side (cost independent of the
    projected particle size); 'exact': the brute-force 2D bilateral window and narrow-range passes
    that read every pixel of their radius (the filters before 2026-11, slow at high resolution)."""
    nrf_max_taps: int = Field(16, ge=1)
    """'fast' mode: most taps on each side of a narrow-range pass; wider kernels sample every k-th
    pixel (the 2D clean-up pass removes the pixel-scale noise this leaves)."""
    bilateral_sigma_px_scale: float = Field(1.5, gt=0.0)
    """Bilateral spatial sigma as a multiple of the projected particle radius (px / px). 1.5 with a
    range of 10 radii had the lowest error against the mesh over sphere and ellipsoid splats of
    three training scenes at 256 and 512 px (``benchmarks/tune_bilateral.py``; 2 / 6 before)."""
    bilateral_range_radii: float = Field(10.0, gt=0.0)
    """Bilateral range sigma in particle radii (depth units / r)."""
    bilateral_max_radius_px: int = Field(100, ge=1)
    """Cap on the bilateral kernel radius (px; the separable passes cost linear in it, and a cap
    below twice the spatial sigma would make the filter depend on the resolution)."""
    bilateral_max_taps: int = Field(16, ge=0)
    """'fast' mode: most taps on each side of a bilateral pass; a wider kernel's taps each average
    the fluid pixels of their stretch, so the cost stops growing with the projected particle size
    (0: one tap per pixel of the radius)."""
    gaussian_sigma_px: float = Field(3.0, gt=0.0)
    """Sigma of the naive fixed-size Gaussian depth blur, the weakest baseline (px)."""
    nrf_delta_radii: float = Field(10.5, gt=0.0)
    """Narrow-range delta in particle radii (Truong's reference value)."""
    nrf_mu_radii: float = Field(1.0, gt=0.0)
    """Narrow-range mu in particle radii."""
    nrf_radius_scale: float = Field(4.0, gt=0.0)
    """Narrow-range kernel radius as a multiple of the projected particle radius (px / px)."""
    nrf_max_radius_px: int = Field(100, ge=1)
    """Cap on the narrow-range kernel radius (px)."""
    nrf_iterations: int = Field(3, ge=1)
    """Alternating separable passes of the narrow-range filter."""
    nrf_cleanup_radius_px: int = Field(4, ge=0)
    """Radius of the final 2D clean-up pass (px)."""
    aniso_smoothing: float = Field(0.9, ge=0.0, le=1.0)
    """Laplacian smoothing lambda of the particle centres (Yu & Turk)."""
    aniso_kr: float = Field(4.0, ge=1.0)
    """Largest-to-smallest eigenvalue ratio cap k_r."""
    aniso_ks: float = Field(1400.0, gt=0.0)
    """Eigenvalue scale k_s."""
    aniso_kn: float = Field(0.5, gt=0.0)
    """Isotropic kernel scale for isolated particles k_n."""
    aniso_neps: int = Field(25, ge=1)
    """Neighbour count below which a particle stays a sphere (N_eps)."""
    aniso_kernel_radius: float = Field(5.0, gt=0.0)
    """Density kernel radius h as a multiple of r; neighbours for the covariance lie within 2h."""
    iso_level: float = Field(0.5, gt=0.0)
    """Iso value of the normalised density (1 is a particle's rest density)."""
    grid_cells_per_radius: float = Field(1.5, gt=0.0)
    """Density grid resolution (cells per particle radius)."""
    max_grid_cells: int = Field(320, ge=16)
    """Cap on the grid size per axis (cells); the paper used about 270."""
    marching_cubes: Literal["auto", "skimage", "warp"] = "auto"
    """Marching cubes of the mesh target: scikit-image on the host, or Warp's kernels on the grid's
    device ('auto': Warp on CUDA, scikit-image on the CPU, where it is the faster)."""
    target: Literal["mesh", "raytrace"] = "mesh"
    """The reference surface: 'mesh' (marching cubes of the density on a grid, ray-cast) or
    'raytrace' (each pixel's ray marched through the density to the iso-level, no grid)."""
    raytrace_step_radii: float = Field(0.5, gt=0.0)
    """'raytrace': march step along the ray, in particle radii (a crossing is then bisected)."""
    raytrace_bisections: int = Field(10, ge=0)
    """'raytrace': bisection steps that refine each crossing (each halves the depth error)."""
    keep_meshes: bool = False
    """Also write the target meshes (PLY) for inspection."""
    validation_camera: Literal["orbit", "static", "none"] = "orbit"
    """Camera path whose frames form each scene's validation split ('none': all train)."""
    holdout_scenes: tuple[str, ...] = ()
    """Scenes kept entirely out of training (their frames are all validation)."""
    workers: int = Field(0, ge=0)
    """Parallel frame workers (0: one per core)."""
    random_views: int = Field(0, ge=0)
    """Extra training views per frame from random cameras (``pipeline.camera.random_view``), written
    under ``random/``: the ellipsoid splat's inputs and the target at a random size, distance,
    elevation and field of view, so the refiner sees the particle sizes, distances and
    resolutions users bring (0: only the scene's two camera paths)."""
    random_view_spheres: bool = False
    """Random views also carry the sphere splat and its bilateral filter (``Z``, ``A``,
    ``bilateral.*``), the training input of a refiner on spheres (``train.input_splat: sphere``, the
    input ablation); off, only the ellipsoid splat the shipped refiner reads."""
    random_radius_px: tuple[float, float] = (1.0, 12.0)
    """Random views: range of the projected particle radius at the view's centre (px, log-uniform)."""
    random_size: tuple[int, int] = (256, 1024)
    """Random views: range of the square image side (px)."""
    random_fov_deg: tuple[float, float] = (25.0, 65.0)
    """Random views: range of the vertical field of view (degrees)."""
    random_elevation_deg: tuple[float, float] = (0.0, 75.0)
    """Random views: range of the camera's elevation above the look-at particle (degrees)."""
    view_seed: int = 0
    """Seed of the random views (with the scene name, frame and view number)."""


@dataclass(frozen=True, config=_RULES)
class TrainConfig:
    """cGAN refiner of Choi et al. 2021 (stage 3)."""

    epochs: int = Field(20, ge=1)
    """Training epochs (the paper: 100)."""
    batch_size: int = Field(8, ge=1)
    """Images per batch."""
    crop: int = Field(128, ge=16)
    """Random crop side (px; a multiple of the generator stride)."""
    crops_per_frame: int = Field(1, ge=1)
    """Random crops drawn from each training frame per epoch."""
    lr: float = Field(2e-4, gt=0.0)
    """Initial Adam learning rate."""
    beta1: float = Field(0.5, ge=0.0, lt=1.0)
    """Adam beta1."""
    lr_decay: float = Field(0.95, gt=0.0, le=1.0)
    """Learning-rate factor applied after each epoch."""
    lambda_content: float = Field(100.0, ge=0.0)
    """Weight lambda_C of the content loss."""
    lambda_normal: float = Field(10.0, ge=0.0)
    """Weight lambda_N of the normal-constraint loss (0 disables it)."""
    lambda_adversarial: float = Field(1.0, ge=0.0)
    """Weight of the adversarial term."""
    content_loss: Literal["l1", "l2"] = "l1"
    """Content loss norm (the paper prefers L1)."""
    auxiliary_features: bool = True
    """Feed raw and blurred depth with the normal (5 input channels) or the normal alone (3)."""
    input_features: Literal["radius", "frame"] = "radius"
    """How the depth features are made scale-free (``pipeline.model.data``): 'radius' expresses depth
    differences in particle radii (raw minus filtered depth, and the filtered depth's relief against
    its neighbourhood) and adds the projected radius in pixels, so a fluid seen from further away or
    at another resolution gives the same inputs; 'frame' normalises raw and filtered depth by the
    frame's mean and spread (the weights shipped before 2026-12)."""
    layers: bool = True
    """With ``input: spheres``: the channels of what lies behind the front splat (``behind``,
    ``thickness``); False zeroes them (the ablation of the depth separation)."""
    working_radius_px: float = Field(3.0, ge=0.0)
    """Frames whose median projected particle radius is larger than this are scaled down to it
    before the generator (inputs area-averaged) and its output scaled back up, so the network always
    sees particles of about this size (px; 0: never rescale). Recorded in the checkpoint."""
    residual: bool = True
    """The generator adds its output to the input normal (it learns a correction of the filtered
    normals) instead of producing the normal from scratch."""
    rotations: bool = True
    """Augment crops by quarter turns (a camera roll), turning the view-space normals with the image,
    besides left-right flips."""
    init_from: str = ""
    """Start the generator from these weights instead of random ones: 'shipped' (the package's
    weights) or a checkpoint path; the architecture must match ('': random initialisation).
    Fine-tunes the shipped refiner on a dataset of your own."""
    time_limit_minutes: float = Field(0.0, ge=0.0)
    """Stop after the epoch that passes this much training time, with ``last.pt`` written, so a long
    training runs as resumable chunks (a GPU machine lent for minutes at a time; 0: no limit). The
    stage then reports the epochs done and the next run resumes."""
    density_feature: bool = False
    """Give the generator the ellipsoid splat's density feature too (``model.data.density_feature``:
    the mesh's density at the drawn particles' kernel centres, which tells the spray and sheets the
    mesh leaves open). Recorded in the checkpoint; ``init_from`` weights without it start with the
    feature's input weights at zero."""
    input_splat: Literal["sphere", "ellipsoid"] = "ellipsoid"
    """Which splat the generator's input is made of: the particles' anisotropic ellipsoids (the
    dataset's ``aniso_bilateral`` and ``aniso`` channels) or spheres (``bilateral`` and ``Z``).
    Trained alike for 15 epochs, the ellipsoid input measured 9.46 deg mean held-out error
    against 10.99 for spheres (configs/ablations/*_input.yaml)."""
    train_scenes: tuple[str, ...] = ()
    """Scenes to train on (empty: every configured scene not held out)."""
    validation_scenes: tuple[str, ...] = ()
    """Held-out scenes whose frames choose the best checkpoint each epoch (empty: every held-out
    scene's); ``evaluate`` leaves them out of its report, so the reported scenes never steered the
    training."""
    gen_base_channels: int = Field(24, ge=4)
    """Generator channels at full resolution."""
    gen_downsamples: int = Field(2, ge=0, le=5)
    """Stride-2 stages in the generator (its stride is 2^this)."""
    gen_res_blocks: int = Field(4, ge=0)
    """Residual blocks at the bottleneck."""
    disc_base_channels: int = Field(16, ge=4)
    """Discriminator channels of its first convolution."""
    disc_layers: int = Field(4, ge=1, le=7)
    """Stride-2 convolutions in the discriminator before its fully connected layer."""
    val_frames: int = Field(16, ge=1)
    """Validation frames evaluated each epoch (spread over the held-out split)."""
    mixed_precision: bool = True
    """Autocast: float16 on CUDA, bfloat16 on a CPU with native bf16 (AVX512-BF16 or AMX), float32
    elsewhere (``pipeline.model.trainer.autocast_dtype``)."""
    threads: int = Field(0, ge=0)
    """torch CPU threads (0: one per core)."""
    data: Literal["memory", "disk"] = "memory"
    """Where training crops come from: 'memory' decodes every training frame up front (about 33 MiB
    per 1024 x 1024 frame, ~94 GiB at the paper's scale); 'disk' reads crops lazily from the
    dataset EXRs in DataLoader workers, so memory stays bounded (``loader_workers`` x
    ``cached_frames`` frames). The two draw different (equally distributed) crops, see
    docs/training_at_scale.md."""
    loader_workers: int = Field(2, ge=0)
    """DataLoader worker processes per training process that decode EXRs ('disk' data; 0: read in
    the training process)."""
    cached_frames: int = Field(4, ge=0)
    """Decoded frames each reader keeps for its next crops ('disk' data; 0: decode every time)."""


@dataclass(frozen=True, config=_RULES)
class RenderConfig:
    """Deferred shading and outputs (stage 4)."""

    width: int = Field(512, ge=8, le=16384)
    """Output width (px)."""
    height: int = Field(512, ge=8, le=16384)
    """Output height (px)."""
    camera: Literal["static", "orbit"] = "static"
    """Camera path to render."""
    method: Method = "refined"
    """Normal-map source."""
    weights: str = "shipped"
    """Generator: 'shipped' (in the package), 'trained' (this config's best checkpoint, training
    it if needed) or a checkpoint path (relative to the working directory)."""
    refiner_precision: Literal["auto", "float32", "bfloat16"] = "auto"
    """The refiner's arithmetic: 'auto' is bfloat16 where the hardware has it natively (a CPU with
    AVX512-BF16 or AMX, a GPU with bf16; the network 2.2x faster on the CPU, the same error as
    float32 on the validation scene) and float32 elsewhere."""
    frame_stride: int = Field(1, ge=1)
    """Render every n-th frame."""
    max_frames: int = Field(0, ge=0)
    """Render at most this many frames (0: all)."""
    normal_threshold: float = Field(0.4, ge=0.0, le=1.0)
    """Drop refined pixels whose normal is shorter than this (the paper's noise removal, at 0.5
    there; 0.4 kept more of the mesh's rim at the same IoU on the validation scene)."""
    fluid_color: Vec3 = (0.3, 0.68, 0.82)
    """Transmittance per metre of the fluid (linear RGB, Beer-Lambert)."""
    absorption: float = Field(5.5, ge=0.0)
    """Absorption strength multiplying -log(fluid_color) (1/m)."""
    ior: float = Field(1.33, gt=1.0)
    """Index of refraction (water 1.33)."""
    refraction_strength: float = Field(0.5, ge=0.0)
    """Multiplier of the refraction offset: the background is looked up where the view ray, bent by
    Snell's law at the surface, leaves the fluid's thickness (1: physical, 0: none; the default
    halves it, as screen-space normals are bumpier than the surface they stand for)."""
    diffuse_weight: float = Field(0.05, ge=0.0)
    """Weight of the Lambertian term tinted by the fluid colour (scattering inside the fluid)."""
    specular: Literal["blinn", "ggx"] = "ggx"
    """Specular model."""
    roughness: float = Field(0.08, gt=0.0, le=1.0)
    """GGX roughness (alpha = roughness^2) or Blinn exponent from it."""
    light_dir: Vec3 = (0.4, 0.8, 0.45)
    """Direction towards the sun (world space)."""
    light_intensity: float = Field(3.0, ge=0.0)
    """Sun radiance scale."""
    environment: str = ""
    """Latitude-longitude HDR map (.exr or Radiance .hdr, row 0 looking up) for reflections, the
    sky and what the fluid refracts ('': a procedural daylight sky)."""
    environment_rotation_deg: float = 0.0
    """Turn of the environment map about the world's up axis (degrees, counter-clockwise seen
    from above)."""
    environment_strength: float = Field(1.0, ge=0.0)
    """Multiplier of the environment's radiance (map or procedural sky)."""
    background: Literal["scene", "none"] = "scene"
    """Behind the fluid: 'scene' (floor, walls, obstacles and the environment; the beauty is opaque)
    or 'none' (the fluid over transparent black; it still refracts and reflects the environment)."""
    min_facing: float = Field(0.2, ge=0.0, lt=1.0)
    """Smallest cosine between a shaded normal and the view direction: screen-space normals that
    face away or graze (noise at silhouettes and depth discontinuities) are bent towards the
    viewer up to this, instead of mirroring the ground as dark speckles."""
    exposure: float = 0.0
    """Exposure for previews (stops)."""
    video_fps: float = Field(30.0, gt=0.0)
    """Preview video frame rate (frames per second), also the rate that turns particle velocities
    (m/s) into motion vectors (pixels per frame) unless the renderer is given the sequence's."""
    motion_vectors: bool = True
    """Compute the motion-vector pass from the particle velocities and the camera's motion (off: the
    pass holds zeros; saves about 12 ms a frame at 512x512 on 2 CPU cores)."""
    exr_half: Literal["none", "colour", "all_but_depth", "all"] = "all_but_depth"
    """Channels stored as 16-bit half floats: 'all_but_depth' (every pass but the depth, which half
    would round to centimetres at 10 m; normals keep 0.02 degree, motion 1/32 px at 64 px), 'colour'
    (the beauty and fluid RGBA and the 0/1 mask), 'all' or 'none'. Half data writes in 0.6x the
    time of 32-bit (ZIP)."""
    exr_compression: Literal["zip", "zstd", "piz", "dwaa", "dwab", "none"] = "zip"
    """EXR compression: 'zip', 'zstd' and 'piz' are lossless; 'zstd' writes a 1080p frame in about
    half zip's CPU time, 10% smaller, but only OpenEXR 3.5 (2026) and later read it: check your
    compositor first. 'dwaa' and 'dwab' are lossy on every channel named R, G, B or Y (colour, but
    also the Y of normals and motion): for review copies."""
    sensor_width_mm: float = Field(36.0, gt=0.0)
    """Sensor width (mm, spanning the image's longer side) of the focal length in the EXR header."""
    comparison: bool = False
    """Also render bilateral, narrow-range, metaballs and the mesh, and write the side-by-side
    comparison (bilateral | nrf | refined | metaball | mesh): several times a frame's cost ('make
    demo' turns it on)."""


@dataclass(frozen=True, config=_RULES)
class EvaluateConfig:
    """Held-out metrics (the evaluate stage)."""

    methods: tuple[Method, ...] = ("gaussian", "bilateral", "nrf", "aniso", "aniso_nrf", "refined", "metaball")
    """Methods compared with the mesh reference ('metaball' also against its own ray-marched surface)."""
    frames_per_sequence: int = Field(0, ge=0)
    """Frames evaluated per held-out sequence, evenly spread over it (0: all)."""
    imported_scenes: tuple[str, ...] = ()
    """Imported particle scenes also evaluated."""
    sizes: tuple[int, ...] = ()
    """Square image sides (px) to evaluate at, each from its own dataset views (empty: the
    dataset's width and height); the report has a table per size."""


@dataclass(frozen=True, config=_RULES)
class MetaballConfig:
    """Image-space metaballs (Horvath 2019; docs/metaball.md): the field fluid particles make as
    metaballs, the dataset of circle inputs and ray-marched targets, and the pix2pix training.

    A view is scaled about its camera (which leaves the image unchanged) so that every ball has the
    radius ``working_ball_radius``; its depth code starts ``depth_margin`` in front of the nearest
    ball centre and spans ``depth_span`` (the thesis' 7 to 25 units). Lengths below are in those
    working units unless they say radii."""

    ball_radius_radii: float = Field(1.4, gt=0.0)
    """A particle's metaball radius in particle radii (an isolated ball's surface has radius
    ball radius / sqrt(iso_level)). 1.4 on the ellipsoids and 1.0 on spheres came closest to the
    mesh on the validation scene (docs/metaball.md)."""
    anisotropic: bool = True
    """The balls are the particles' ellipsoids: the mesh's anisotropic kernels (Yu & Turk: smoothed
    centres, flattened along the surface; ``dataset.aniso_*``) scaled by ``ball_radius_radii``, so
    the blended surface follows the mesh's instead of bulging between particles. False: spheres at
    the particles (the thesis')."""
    iso_level: float = Field(1.0, gt=0.0)
    """Iso-level of the surface sum r^2 / d^2 = iso_level (the thesis' 1)."""
    kernel_radius_radii: float = Field(4.0, ge=0.0)
    """Where each ball's term tapers to zero, in ball radii (0: the thesis' infinite support)."""
    working_ball_radius: float = Field(0.1, gt=0.0)
    """Ball radius every view is scaled to (working units)."""
    depth_margin: float = Field(0.5, ge=0.0)
    """Depth code 0 lies this far in front of the nearest ball centre (working units)."""
    depth_span: float = Field(18.0, gt=0.0)
    """Depth code 1 lies this far behind code 0 (working units; the thesis' 25 - 7)."""
    step: float = Field(0.005, gt=0.0)
    """Smallest ray-march step near the surface (working units; half-radius / 10 by default)."""
    bisections: int = Field(8, ge=0)
    """Halvings of the step that brackets the surface."""
    outline_width: float = Field(0.05, gt=0.0, le=0.5)
    """Outline width in the circle input, a share of the circle's diameter (the thesis' 0.05)."""
    outline_min_px: float = Field(1.0, ge=0.0)
    """Narrowest outline (px), so that small circles still show."""
    input: Literal["field", "spheres", "circles"] = "field"
    """What the generator sees: the balls as exactly splatted spheres with the layer behind them
    (``sphere_input``) whose normals are the metaball field's at the front sphere (``field``) or the
    spheres' own (``spheres``), or the thesis' circle outlines with a centre-depth code (``circles``)."""
    splat_radius: float = Field(0.8, gt=0.0)
    """Radius of the splatted spheres, in minimal radii (an isolated ball's surface). On spheres the
    blend swells the surface beyond the balls, so a larger sphere (1.5) starts nearer to it; the
    ellipsoids' surface lies inside their bounding spheres, where 0.8 started nearest on the
    validation scene (docs/metaball.md)."""
    field_steps: int = Field(2, ge=0)
    """With ``input: field``: Newton steps along each ray from the front sphere towards the
    iso-surface before the field's normal is taken (each costs one more field sample a pixel)."""
    layers: bool = True
    """With a sphere input: the channels of what lies behind the front splat (``behind``,
    ``thickness``); False zeroes them (the ablation of the depth separation)."""
    working_radius_px: float = Field(1.5, ge=0.0)
    """Views are drawn at the image scale where the median ball's projected radius is within half an
    octave below this (px), and the maps resampled back (0: the view's own size, the thesis')."""
    architecture: Literal["resnet", "unet"] = "resnet"
    """Generator: the refiner's ResNet (two halvings, residual blocks; any side a multiple of 4) or the
    thesis' eight-level U-Net (sides multiples of 256)."""
    res_blocks: int = Field(4, ge=0)
    """Residual blocks of the ResNet generator."""
    residual: bool = True
    """With a sphere input and the ResNet: the generator's normal is the input's plus a learnt
    correction (it starts as its input; the other maps are predicted outright)."""
    crop: int = Field(128, ge=0, multiple_of=4)
    """Training crop side (px, random, where the target shows surface; the U-Net needs multiples of
    256); 0: whole views, which must then all have one size."""
    size: int = Field(256, ge=256, multiple_of=256)
    """Square side (px) of the training views' cameras (before the working scale)."""
    frame_stride: int = Field(4, ge=1)
    """Every n-th simulated frame of a training scene gives views."""
    max_frames: int = Field(0, ge=0)
    """At most this many frames per scene (0: all)."""
    views_per_frame: int = Field(2, ge=0)
    """Random cameras per frame (``dataset.random_radius_px``, ``random_fov_deg`` and
    ``random_elevation_deg`` ranges)."""
    random_sets: int = Field(0, ge=0)
    """Random ball sets as in the thesis (up to ``max_balls`` balls of random size and colour in front
    of the camera, each rendered ``repeats`` times with small offsets), besides the fluid views."""
    repeats: int = Field(3, ge=1)
    """Renderings of each random set."""
    max_balls: int = Field(145, ge=1)
    """Most balls in a random set (the thesis' 145)."""
    seed: int = 0
    """Seed of the random cameras and ball sets."""
    base_channels: int = Field(16, ge=4)
    """Generator width (U-Net 16: 3.4 M parameters, 13.6 MB; the thesis' 32 is over the 20 MB limit)."""
    upsample: Literal["transpose", "resize"] = "transpose"
    """Decoder up-sampling: the thesis' transposed convolutions or resize and convolve."""
    disc_base_channels: int = Field(32, ge=4)
    """PatchGAN width (the thesis' 64)."""
    disc_kernel: int = Field(4, ge=2)
    """PatchGAN kernel (the thesis' 8; 4 is pix2pix's and 6x cheaper on a CPU)."""
    gan_weight: float = Field(1.0, ge=0.0)
    """Weight of the adversarial term (the thesis states 500 with L1 0.5; pix2pix uses 1 with 100)."""
    l1_weight: float = Field(100.0, ge=0.0)
    """Weight of the L1 term."""
    learning_rate: float = Field(2e-4, gt=0.0)
    """Adam learning rate of both networks (the thesis' 0.0002)."""
    beta1: float = Field(0.5, ge=0.0, lt=1.0)
    """Adam beta1 (the thesis' 0.5)."""
    batch_size: int = Field(4, ge=2)
    """Views per step (at least 2: batch norm)."""
    epochs: int = Field(10, ge=1)
    """Passes over the training views; more continue a finished run."""
    time_limit_minutes: float = Field(0.0, ge=0.0)
    """Stop after the epoch that passes this much training time (0: none); the next run resumes."""
    weights: str = "shipped"
    """Generator for render and evaluate: 'shipped', 'trained' (this config's, training it if needed)
    or a checkpoint path."""
    init_from: str = ""
    """A new run starts from this generator ('shipped' or a checkpoint path of the same architecture
    and input), so training goes on across sessions and code changes; '' starts from scratch."""
    target_stride: int = Field(4, ge=1)
    """Evaluate compares the metaball method with its own ray-marched target on every n-th frame it
    evaluates (the march costs seconds a view at 1024 px on a CPU)."""


@dataclass(frozen=True, config=_RULES)
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
    executor: Literal["local", "ray"] = "local"
    """Where the per-frame work of dataset, render and evaluate runs: in this process, or sharded
    over a Ray cluster (every node must see data_dir); the outputs are the same either way."""
    ray_address: str = ""
    """Ray cluster to join with executor 'ray' ('': start a local one on this machine)."""
    simulate: SimulateConfig = Field(default_factory=SimulateConfig)
    """Stage 1."""
    dataset: DatasetConfig = Field(default_factory=DatasetConfig)
    """Stage 2."""
    train: TrainConfig = Field(default_factory=TrainConfig)
    """Stage 3."""
    render: RenderConfig = Field(default_factory=RenderConfig)
    """Stage 4."""
    evaluate: EvaluateConfig = Field(default_factory=EvaluateConfig)
    """Metrics."""
    metaball: MetaballConfig = Field(default_factory=MetaballConfig)
    """Image-space metaballs (the second method)."""


# ---------------------------------------------------------------------------------------------
# Loading


@functools.cache
def _adapter(cls: type) -> TypeAdapter:
    return TypeAdapter(cls)


def _key(loc: tuple, prefix: str = "") -> str:
    """``fluid[0].shape`` from pydantic's location tuple."""
    key = prefix
    for part in loc:
        key += f"[{part}]" if isinstance(part, int) else (f".{part}" if key else str(part))
    return key


def _known_keys(cls: type, loc: tuple) -> list[str]:
    """Field names of the dataclass found by walking ``loc`` (without its last part) from ``cls``."""
    tp: Any = cls
    for part in loc[:-1]:
        if isinstance(part, int):  # an element of a tuple of dataclasses, unwrapped below already
            continue
        tp = typing.get_type_hints(tp)[part]
        inner = [a for a in typing.get_args(tp) if dataclasses.is_dataclass(a)]  # tuple[X, ...], X | None
        tp = inner[0] if inner else tp
    return sorted(f.name for f in dataclasses.fields(tp)) if dataclasses.is_dataclass(tp) else []


_MESSAGES = {
    "int_type": "must be an integer", "float_type": "must be a number", "bool_type": "must be true or false",
    "string_type": "must be a string", "finite_number": "must be a finite number", "tuple_type": "must be a list",
    "dataclass_type": "must be a mapping", "greater_than": "must be > {gt}", "greater_than_equal": "must be >= {ge}",
    "less_than": "must be < {lt}", "less_than_equal": "must be <= {le}",
}


def _message(cls: type, err: dict) -> tuple[tuple, str]:
    """(location, readable message) of one pydantic error."""
    loc, kind, ctx = tuple(err["loc"]), err["type"], err.get("ctx") or {}
    if kind == "unexpected_keyword_argument":
        return loc, f"unknown key (known: {', '.join(_known_keys(cls, loc))})"
    if kind == "missing":
        if loc and isinstance(loc[-1], int):
            return loc[:-1], "has too few elements"
        return loc, "missing required key"
    if kind == "too_long":
        return loc, "has too many elements"
    got = f", got {err['input']!r}" if "input" in err and not isinstance(err["input"], dict) else ""
    if kind == "literal_error":
        return loc, f"must be one of {ctx.get('expected', '')}{got}"
    return loc, _MESSAGES.get(kind, err["msg"]).format(**ctx) + got


def from_dict(cls: type, data: Any, file: str | Path = "<dict>", prefix: str = ""):
    """Build dataclass ``cls`` from loaded YAML, strictly: unknown keys, wrong types and values out
    of bounds raise ``ConfigError`` naming the file and the key path of the first problem."""
    data = {} if data is None else data
    try:
        text = json.dumps(data, default=str)
    except ValueError as exc:  # a self-referencing YAML anchor
        raise ConfigError(file, prefix, f"cannot be read as plain data ({exc})") from None
    try:
        return _adapter(cls).validate_json(text, strict=True)
    except ValidationError as exc:
        loc, message = _message(cls, exc.errors()[0])
        raise ConfigError(file, _key(loc, prefix), message) from None


def to_dict(obj: Any) -> Any:
    """Plain JSON/YAML-ready values of a config dataclass (tuples become lists)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple | list):
        return [to_dict(v) for v in obj]
    return obj
