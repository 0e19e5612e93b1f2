"""``deep-ssfr``: the command line of every stage (the make targets call it).

``deep-ssfr render PATTERN --radius R --out DIR`` renders a user's own particle sequence in one
command; without PATTERN, ``render`` renders the config's scenes like the other stages. Each
command prints ``--help``; failures end in one line on stderr and exit 2 (config) or 1 (the rest).
"""

from __future__ import annotations

import sys
from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from stages.common import StageOptions, make_run, stage_main

app = typer.Typer(name="deep-ssfr", no_args_is_help=True, add_completion=False, rich_markup_mode=None,
                  help="Screen-space fluid rendering with a cGAN normal-map refiner: simulate, build the dataset, "
                       "train, render and evaluate, each cached under the config's data_dir.")

Config = Annotated[str, typer.Option(help="pipeline YAML")]
Scene = Annotated[str, typer.Option(help="run only this configured scene")]
Force = Annotated[bool, typer.Option("--force", help="recompute even if cached")]
Verify = Annotated[bool, typer.Option("--verify", help="check cached outputs against their recorded hashes, "
                                                       "not only their sizes")]
DEFAULT_CONFIG = StageOptions.config


def _finish(stage: str, body) -> None:
    """Run a stage body at the error boundary; exit with its code when it failed."""
    code = stage_main(stage, body)
    if code:
        raise typer.Exit(code)


def _main(stage: str, opts: StageOptions, *extra) -> None:
    """A stage whose module has ``main(opts, *extra)``."""
    import importlib

    module = importlib.import_module(f"stages.{stage}")
    _finish(stage, lambda: module.main(opts, *extra))


def _each_scene(stage: str, opts: StageOptions) -> None:
    """A stage whose work is its ``ensure`` for every configured scene."""
    import importlib

    module = importlib.import_module(f"stages.{stage}")

    def body() -> None:
        run = make_run(opts)
        for scene in run.loaded.scenes.values():
            module.ensure(run, scene, force=run.force)

    _finish(stage, body)


@app.command()
def simulate(config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False):
    """Run PBF for each configured scene (or import its particle files) into the cache."""
    _each_scene("simulate", StageOptions(config, scene, force, verify))


@app.command()
def dataset(config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False):
    """Screen-space inputs and reference targets of every frame and camera, as EXR."""
    _each_scene("dataset", StageOptions(config, scene, force, verify))


@app.command()
def train(config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False):
    """Train the refiner on the cached dataset (resumes; more epochs continue a run)."""
    _main("train", StageOptions(config, scene, force, verify))


@app.command()
def ship(config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False,
         out: Annotated[str, typer.Option(help="write refiner.pt, refiner.json and loss_curve.png here instead "
                                               "of replacing the shipped weights")] = ""):
    """Make the config's best trained checkpoint the shipped weights, with its card."""
    _main("ship", StageOptions(config, scene, force, verify), out)


@app.command()
def render(
    pattern: Annotated[str | None, typer.Argument(
        help="a particle sequence: a glob or splashsurf's {} for the frame number (out/fluid_{}.vtk); "
             "without it, the config's scenes are rendered")] = None,
    radius: Annotated[float | None, typer.Option(help="particle radius, in the files' units (PATTERN)")] = None,
    out: Annotated[Path | None, typer.Option(help="output folder of frame_NNNN.exr, the videos and "
                                                  "camera.json (PATTERN)")] = None,
    size: Annotated[str, typer.Option(help="image size WxH (PATTERN)")] = "512x512",
    frames: Annotated[str, typer.Option(help="frame numbers START:END, inclusive; either may be left out "
                                             "(PATTERN)")] = ":",
    camera: Annotated[str, typer.Option(help="auto (frame the whole sequence), orbit (circle it) or a camera "
                                             "JSON file (PATTERN)")] = "auto",
    up: Annotated[str, typer.Option(help="the files' up axis: y or z (PATTERN)")] = "y",
    fps: Annotated[float, typer.Option(help="frame rate of the sequence and its videos (PATTERN)")] = 30.0,
    method: Annotated[str, typer.Option(help="normal-map method (PATTERN)")] = "refined",
    config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False,
):
    """Render the config's scenes, or a particle sequence of your own (PATTERN), to EXR frames, a
    preview video and a comparison video."""
    opts = StageOptions(config, scene, force, verify)
    if pattern is None:
        _main("render", opts)
        return
    from stages import sequence

    request = sequence.Request(pattern, radius, out, size, frames, camera, up, fps, method)
    _finish("render", lambda: sequence.main(opts, request))


@app.command()
def evaluate(config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False):
    """Every method against the reference surface on held-out sequences: report.md and figures."""
    _main("evaluate", StageOptions(config, scene, force, verify))


class ExportFormat(str, Enum):
    ply = "ply"
    vtk = "vtk"


@app.command()
def export(config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False,
           format: Annotated[ExportFormat, typer.Option(help="file format")] = ExportFormat.ply):
    """PLY or legacy VTK copies of each cached particle sequence, for other tools."""
    _main("export", StageOptions(config, scene, force, verify), format.value)


@app.command()
def demo(config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False):
    """The whole job on the small default: simulate, refine with the shipped weights, shade, write."""
    _main("demo", StageOptions(config, scene, force, verify))


class CacheAction(str, Enum):
    ls = "ls"
    clean = "clean"


@app.command("cache")
def cache_command(action: Annotated[CacheAction, typer.Argument(help="ls: list the entries; clean: delete them")],
                  config: Config = DEFAULT_CONFIG):
    """List or delete the cache entries under the config's data_dir."""
    from stages import cache as stage

    _finish("cache", lambda: stage.main(action.value, config))


def main(argv: list[str] | None = None) -> int:
    """Run the command line on ``argv`` (default: the process's) and return its exit code."""
    try:
        typer.main.get_command(app).main(args=argv, prog_name="deep-ssfr", standalone_mode=True)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return 0


def entry() -> None:
    """The ``deep-ssfr`` console script."""
    sys.exit(main())


if __name__ == "__main__":
    entry()
