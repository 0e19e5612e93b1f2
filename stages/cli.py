"""``deep-ssfr``: every stage a command with ``--help``; errors: one line. The one entry point: the console
script, the make targets, ``python -m stages.cli`` (torchrun, tests) all come here."""

from __future__ import annotations

import ctypes
import importlib
import os
import sys
from pathlib import Path
from typing import Annotated, Literal

RUNTIME_ENV = {
    # Idle OpenMP threads sleep instead of spinning (read when torch loads its OpenMP runtime): the
    # renderer's EXR writer, Warp's launcher threads and torch share the cores, and torch's spinning
    # threads took them from the others. A refined 1080p frame of 38k particles: 826 -> 694 ms, its
    # network 252 -> 113 ms (benchmarks/bench_scale.py).
    "OMP_WAIT_POLICY": "PASSIVE",
    # numpy asks for transparent huge pages on every array of 4 MB or more. Where the kernel compacts
    # memory for such a request (THP defrag 'madvise', the usual default) and a VM backs the huge
    # pages lazily, each fresh page costs far more than its 4 KB pages would: a kept 33 MB copy took
    # 60 ms instead of 14 on this 2-core VM. A refined 1080p frame: 38k particles 548 -> 456 ms,
    # 303k 790 -> 760, 1M the same; a 4K frame's arrays of 130 MB fault faster in huge pages
    # (3.6 against 4.3 s): set it to 1 for 4K sequences.
    "NUMPY_MADVISE_HUGEPAGE": "0",
}
"""Environment every ``deep-ssfr`` process runs with, read by the libraries as they load (so set
before any import of numpy or torch); a value already set wins."""
for _name, _value in RUNTIME_ENV.items():
    os.environ.setdefault(_name, _value)

MALLOC_MMAP_THRESHOLD = 32 << 20
"""Allocations up to this size come from malloc's heap rather than a mapping of their own: a 1080p
map (8 MB a float32 channel, 25 MB a vec3) does, a 4K one (33 MB and up) keeps its own, which held
a 4K frame's peak at 3.6-3.8 GB (64 MB here: 4.0 GB)."""
MALLOC_TRIM_THRESHOLD = 1 << 30
"""Freed heap memory malloc keeps for the next allocations before it returns any to the system."""


def keep_freed_memory() -> None:
    """Let glibc's malloc reuse the memory of freed image-sized arrays instead of mapping fresh pages
    for each: a frame allocates and frees dozens of full-frame maps, and every fresh page faults on
    first touch. bench_scale's 38k frame at 1080p: 498 -> 440 ms, the 1M frame 1279 -> 1216 ms (means
    of four runs each). By default glibc maps each block over 128 kB on its own (raising that bar to
    the largest one freed, at most 32 MB) and gives freed heap back past twice the bar. Does nothing
    where the C library is not glibc."""
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return
    m_trim_threshold, m_mmap_threshold = -1, -3  # malloc.h
    mallopt(m_mmap_threshold, MALLOC_MMAP_THRESHOLD)
    mallopt(m_trim_threshold, MALLOC_TRIM_THRESHOLD)


keep_freed_memory()

import typer  # noqa: E402

from pipeline.config import METHODS  # noqa: E402
from pipeline.executor import cluster_scope  # noqa: E402
from stages.common import StageOptions, stage_main  # noqa: E402

app = typer.Typer(name="deep-ssfr", no_args_is_help=True, add_completion=False, rich_markup_mode=None,
                  help="Screen-space fluid rendering with a cGAN normal-map refiner: simulate, build the dataset, "
                       "train, render and evaluate, each cached under the config's data_dir.")
Config, DEFAULT_CONFIG = Annotated[str, typer.Option(help="pipeline YAML")], StageOptions.config
Scene = Annotated[str, typer.Option(help="run only this configured scene")]
Force = Annotated[bool, typer.Option("--force", help="recompute even if cached")]
Verify = Annotated[bool, typer.Option("--verify", help="check cached outputs against their recorded hashes too")]
Executor = Annotated[Literal["", "local", "ray"], typer.Option(help="frames here or on a Ray cluster ('': config)")]
STAGES = {
    "simulate": "Run PBF for each configured scene (or import its particle files) into the cache.",
    "dataset": "Screen-space inputs and reference targets of every frame and camera, as EXR.",
    "train": "Train the refiner on the cached dataset (resumes; more epochs continue a run).",
    "evaluate": "Every method against the reference surface on held-out sequences: report.md and figures.",
    "metaball-dataset": "Circle inputs and ray-marched metaball G-buffers of the training scenes, as EXR.",
    "metaball-train": "Train the image-space metaball pix2pix network (resumes; more epochs continue a run).",
    "demo": "The whole job on the small default: simulate, refine with the shipped weights, shade, write.",
}


def _run(stage: str, opts: StageOptions, *extra, module: str = "") -> None:
    """Run ``stages.<stage>`` (or ``module``) at the error boundary: its ``main(opts, *extra)``; exit
    with the stage's code when it failed."""
    module = importlib.import_module(module or f"stages.{stage.replace('-', '_')}")

    def body() -> None:
        with cluster_scope():  # one Ray cluster for the whole command, not one a scene or size
            module.main(opts, *extra)

    if code := stage_main(stage, body):
        raise typer.Exit(code)


def _stage_command(stage: str, doc: str):
    def command(config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False,
                executor: Executor = ""):
        _run(stage, StageOptions(config, scene, force, verify, executor))

    command.__doc__ = doc
    return command


for _name, _doc in STAGES.items():
    app.command(_name)(_stage_command(_name, _doc))


@app.command()
def ship(config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False,
         out: Annotated[str, typer.Option(help="write the weights, card and curve here, not over the shipped")] = ""):
    """Make the config's best trained checkpoint the shipped weights, with its card."""
    _run("ship", StageOptions(config, scene, force, verify), out)


@app.command("metaball-ship")
def metaball_ship(config: Config = DEFAULT_CONFIG, force: Force = False, verify: Verify = False,
                  out: Annotated[str, typer.Option(help="write the weights, card and curve here, not over the "
                                                        "shipped")] = ""):
    """Make the config's best trained metaball generator the shipped one, with its card."""
    _run("metaball-ship", StageOptions(config, "", force, verify), out)


@app.command()
def export(config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False,
           format: Annotated[Literal["ply", "vtk"], typer.Option(help="file format")] = "ply"):
    """PLY or legacy VTK copies of each cached particle sequence, for other tools."""
    _run("export", StageOptions(config, scene, force, verify), format)


@app.command()
def refine(pattern: Annotated[str, typer.Argument(help="EXRs with the generator's input channels (a glob or {})")],
           out: Annotated[Path, typer.Option(help="folder for the refined normal EXRs")],
           weights: Annotated[str, typer.Option(help="'shipped' or a checkpoint")] = "shipped", force: Force = False,
           threshold: Annotated[float, typer.Option(help="drop normals shorter than this (noise)")] = 0.5,
           radius: Annotated[float, typer.Option(help="particle radius, when the EXRs' headers lack "
                                                      "particleRadius")] = 0.0,
           fov: Annotated[float, typer.Option(help="vertical field of view (degrees), when the headers lack the "
                                                   "camera")] = 0.0):
    """Refine your own screen-space EXRs into refined normal EXRs (N.X N.Y N.Z, mask)."""
    _run("refine", StageOptions(force=force), pattern, out, weights, threshold, radius, fov)


@app.command("cache")
def cache_command(action: Annotated[Literal["ls", "clean"], typer.Argument(help="list or delete the entries")],
                  config: Config = DEFAULT_CONFIG):
    """List or delete the cache entries under the config's data_dir."""
    _run("cache", StageOptions(config), action)


@app.command()
def render(
    pattern: Annotated[str | None, typer.Argument(help="particle files: a glob, or {} for the frame number "
                                                       "(out/fluid_{}.vtk); none: the config's scenes")] = None,
    radius: Annotated[float | None, typer.Option(help="PATTERN: particle radius in the files' units")] = None,
    out: Annotated[Path | None, typer.Option(help="PATTERN: folder for frame_NNNN.exr, videos, camera.json")] = None,
    size: Annotated[str, typer.Option(help="PATTERN: image size WIDTHxHEIGHT (default: the camera file's, "
                                           "else 512x512)")] = "",
    fps: Annotated[float, typer.Option(help="PATTERN: frames per second")] = 30.0,
    frames: Annotated[str, typer.Option(help="PATTERN: frame numbers START:END, inclusive, either optional")] = ":",
    camera: Annotated[str, typer.Option(help="PATTERN: auto (frame the sequence), orbit, or a camera JSON")] = "auto",
    up: Annotated[Literal["y", "z"], typer.Option(help="PATTERN: the files' up axis")] = "y",
    method: Annotated[Literal[METHODS], typer.Option(help="PATTERN: normal-map method")] = "refined",
    background: Annotated[Literal["scene", "none"], typer.Option(help="PATTERN: 'none': fluid over transparent "
                                                                      "black")] = "scene",
    compare: Annotated[bool, typer.Option("--compare", help="PATTERN: also render bilateral, narrow-range, "
                                                            "metaballs and the mesh, for a comparison video "
                                                            "(about 7x the time)")] = False,
    config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False,
    executor: Executor = "",
):
    """Render the config's scenes, or your own particle sequence (PATTERN), to EXR frames and videos."""
    from stages.sequence import Request

    request = [Request(pattern, radius, out, size, frames, camera, up, fps, method, background, compare)] \
        if pattern else []
    _run("render", StageOptions(config, scene, force, verify, executor), *request,
         module="stages.sequence" if request else "")


def main(argv: list[str] | None = None) -> int:
    """Run the command line on ``argv`` (default: the process's) and return its exit code."""
    try:
        typer.main.get_command(app).main(args=argv, prog_name="deep-ssfr", standalone_mode=True)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return 0


if __name__ == "__main__":  # python -m stages.cli STAGE ..., as torchrun starts the training
    sys.exit(main())
