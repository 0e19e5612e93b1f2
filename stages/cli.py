"""``deep-ssfr``: the command line of every stage (the make targets call it), each with ``--help``;
``render PATTERN`` renders a user's own sequence. Failures end in one line, exit 2 or 1."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path
from typing import Annotated, Literal

import typer

from pipeline.methods import METHODS
from stages.common import StageOptions, make_run, stage_main

app = typer.Typer(name="deep-ssfr", no_args_is_help=True, add_completion=False, rich_markup_mode=None,
                  help="Screen-space fluid rendering with a cGAN normal-map refiner: simulate, build the dataset, "
                       "train, render and evaluate, each cached under the config's data_dir.")
Config = Annotated[str, typer.Option(help="pipeline YAML")]
Scene = Annotated[str, typer.Option(help="run only this configured scene")]
Force = Annotated[bool, typer.Option("--force", help="recompute even if cached")]
Verify = Annotated[bool, typer.Option("--verify", help="check cached outputs against their recorded hashes too")]
DEFAULT_CONFIG = StageOptions.config
STAGES = {
    "simulate": "Run PBF for each configured scene (or import its particle files) into the cache.",
    "dataset": "Screen-space inputs and reference targets of every frame and camera, as EXR.",
    "train": "Train the refiner on the cached dataset (resumes; more epochs continue a run).",
    "evaluate": "Every method against the reference surface on held-out sequences: report.md and figures.",
    "demo": "The whole job on the small default: simulate, refine with the shipped weights, shade, write.",
}


def _run(stage: str, opts: StageOptions, *extra, module: str = "") -> None:
    """Run ``stages.<stage>`` (or ``module``) at the error boundary: its ``main(opts, *extra)``, else
    its ``ensure`` for every configured scene; exit with the stage's code when it failed."""
    module = importlib.import_module(module or f"stages.{stage}")

    def each_scene() -> None:
        run = make_run(opts)
        for scene in run.loaded.scenes.values():
            module.ensure(run, scene, force=run.force)

    code = stage_main(stage, (lambda: module.main(opts, *extra)) if hasattr(module, "main") else each_scene)
    if code:
        raise typer.Exit(code)


def _stage_command(stage: str, doc: str):
    def command(config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False):
        _run(stage, StageOptions(config, scene, force, verify))

    command.__doc__ = doc
    return command


for _name, _doc in STAGES.items():
    app.command(_name)(_stage_command(_name, _doc))


@app.command()
def ship(config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False,
         out: Annotated[str, typer.Option(help="write the weights, card and curve here, not over the shipped")] = ""):
    """Make the config's best trained checkpoint the shipped weights, with its card."""
    _run("ship", StageOptions(config, scene, force, verify), out)


@app.command()
def export(config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False,
           format: Annotated[Literal["ply", "vtk"], typer.Option(help="file format")] = "ply"):
    """PLY or legacy VTK copies of each cached particle sequence, for other tools."""
    _run("export", StageOptions(config, scene, force, verify), format)


@app.command("cache")
def cache_command(action: Annotated[Literal["ls", "clean"], typer.Argument(help="list or delete the entries")],
                  config: Config = DEFAULT_CONFIG):
    """List or delete the cache entries under the config's data_dir."""
    if code := stage_main("cache", lambda: importlib.import_module("stages.cache").main(action, config)):
        raise typer.Exit(code)


P = "(with PATTERN)"


@app.command()
def render(
    pattern: Annotated[str | None, typer.Argument(help="particle files: a glob, or {} for the frame number "
                                                       "(out/fluid_{}.vtk); none: the config's scenes")] = None,
    radius: Annotated[float | None, typer.Option(help=f"particle radius in the files' units {P}")] = None,
    out: Annotated[Path | None, typer.Option(help=f"folder for frame_NNNN.exr, videos, camera.json {P}")] = None,
    size: Annotated[str, typer.Option(help=f"image size WIDTHxHEIGHT {P}")] = "512x512",
    frames: Annotated[str, typer.Option(help=f"frame numbers START:END, both inclusive, either optional {P}")] = ":",
    camera: Annotated[str, typer.Option(help=f"auto (frame the sequence), orbit, or a camera JSON file {P}")] = "auto",
    up: Annotated[Literal["y", "z"], typer.Option(help=f"the files' up axis {P}")] = "y",
    fps: Annotated[float, typer.Option(help=f"frame rate of the sequence and its videos {P}")] = 30.0,
    method: Annotated[Literal[METHODS], typer.Option(help=f"normal-map method {P}")] = "refined",
    config: Config = DEFAULT_CONFIG, scene: Scene = "", force: Force = False, verify: Verify = False,
):
    """Render the config's scenes, or your own particle sequence (PATTERN), to EXR frames and videos."""
    opts = StageOptions(config, scene, force, verify)
    if pattern is None:
        _run("render", opts)
    else:
        from stages.sequence import Request

        _run("render", opts, Request(pattern, radius, out, size, frames, camera, up, fps, method),
             module="stages.sequence")


def main(argv: list[str] | None = None) -> int:
    """Run the command line on ``argv`` (default: the process's) and return its exit code."""
    try:
        typer.main.get_command(app).main(args=argv, prog_name="deep-ssfr", standalone_mode=True)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
