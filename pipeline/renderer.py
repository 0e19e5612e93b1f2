"""A particle sequence to shaded EXR frames, previews, a video and a side-by-side comparison.

Into one folder: ``frames/frame_0001.exr`` (the passes of ``methods.RenderedFrame``),
``preview/frame_0001.png``, ``<name>_<method>.mp4`` and, with ``render.comparison``,
``compare/frame_0001.png``, ``<name>_comparison.mp4`` and ``<name>_comparison_sheet.png``
(bilateral | narrow-range | refined | mesh). A frame counts as done when all its files exist, so
a killed run resumes after the last whole frame. Used by the render stage and the CLI.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pipeline.camera import Camera
from pipeline.config import Config
from pipeline.device import warp_device
from pipeline.exr import write_exr
from pipeline.frames import frame_name, spread
from pipeline.media import contact_sheet, label, write_png, write_video
from pipeline.methods import NAMES, RenderedFrame, normal_source, shade_frame
from pipeline.parallel import Launcher
from pipeline.screen import ScreenSpace
from pipeline.shading import Shader, load_environment, tonemap
from pipeline.shading.background import BackgroundRenderer, Surroundings
from pipeline.timing import Timings
from pipeline.writer import BackgroundWriter

log = logging.getLogger("deep_ssfr")
COMPARED = ("bilateral", "nrf", "refined", "mesh")


class SequenceRenderer:
    """Renders the frames of one sequence with ``render.method`` (and the compared methods) into
    ``folder``, timing each step; ``close()`` (or ``with``) releases the device buffers."""

    def __init__(self, folder: Path, name: str, around: Surroundings, config: Config, device: str, refiner=None):
        self.folder, self.name, self.config = Path(folder), name, config
        p = config.render
        self.methods = [p.method] + [m for m in COMPARED if p.comparison and m != p.method]
        if "refined" in self.methods and refiner is None:
            raise ValueError("the refined method needs a generator")
        self.refiner = refiner
        wdev = warp_device(device)
        self.ss, self.launch = ScreenSpace(wdev), Launcher(wdev)
        self.shader = Shader(wdev, environment=load_environment(p.environment) if p.environment else None)
        self.background = BackgroundRenderer(around, p, p.width, p.height)
        self.timings = Timings()

    def outputs(self, frame: int) -> list[str]:
        """The files a finished frame has, relative to the folder."""
        out = [f"frames/{frame_name(frame, 'exr')}", f"preview/{frame_name(frame, 'png')}"]
        return out + ([f"compare/{frame_name(frame, 'png')}"] if self.config.render.comparison else [])

    def done(self, frame: int) -> bool:
        """Whether every output of a frame exists."""
        return all((self.folder / o).exists() for o in self.outputs(frame))

    def shade(self, positions: np.ndarray, radius: float, camera: Camera) -> dict[str, RenderedFrame]:
        """Every method's rendered passes of one frame (the main method timed)."""
        p = self.config.render
        with self.timings("background"):
            bg, bg_depth = self.background.render(camera)
            bg = self.shader.fill_sky(bg, bg_depth, camera, p)
        shaded, frame_cache = {}, {}
        for method in self.methods:
            t = self.timings if method == p.method else Timings()
            src = normal_source(method, positions, radius, camera, self.config.dataset, self.ss, self.launch,
                                self.refiner, p.normal_threshold, t, frame_cache)
            shaded[method] = shade_frame(src, bg, bg_depth, camera, p, self.shader, t)
        return shaded

    def write(self, frame: int, shaded: dict[str, RenderedFrame], timings: Timings) -> None:
        """The EXR, preview and comparison of one frame (on the writer thread)."""
        p = self.config.render
        main = shaded[p.method]
        exr, preview, *compare = (self.folder / o for o in self.outputs(frame))
        with timings("exr_write"):
            write_exr(exr, main.channels())
        write_png(preview, tonemap(main.beauty, p.exposure))
        if compare:
            tiles = [label(tonemap(shaded[m].beauty, p.exposure), NAMES[m]) for m in COMPARED]
            write_png(compare[0], np.concatenate(tiles, axis=1))

    def render(self, frames: list[int], load: Callable[[int], tuple[np.ndarray, np.ndarray | None]], radius: float,
               camera_at: Callable[[int], Camera]) -> list[str]:
        """Render the frames not yet done, then the videos; returns the files of the whole sequence.

        ``load(frame)`` gives a frame's positions and velocities (or None), ``camera_at(i)`` the
        camera of the i-th frame."""
        p = self.config.render
        no_fluid: list[int] = []
        write_timings = Timings()
        with BackgroundWriter() as writer:
            for i, frame in enumerate(tqdm(frames, desc=f"render {self.name}", unit="frame")):
                if self.done(frame):
                    continue
                positions, _ = load(frame)
                shaded = self.shade(positions, radius, camera_at(i))
                if not shaded[p.method].mask.any():
                    no_fluid.append(frame)
                writer.submit(self.write, frame, shaded, write_timings)
        self.timings.merge(write_timings)
        if no_fluid:
            log.warning("render %s: the camera sees no fluid in %d frames (first: %d); they show the background "
                        "only", self.name, len(no_fluid), no_fluid[0])
        return self.videos(frames)

    def videos(self, frames: list[int]) -> list[str]:
        """The preview video (and the comparison video and sheet) of all frames; the sequence's files."""
        p = self.config.render
        files = [f"frames/{frame_name(f, 'exr')}" for f in frames]
        video = f"{self.name}_{p.method}.mp4"
        write_video(self.folder / video, [self.folder / f"preview/{frame_name(f, 'png')}" for f in frames],
                    p.video_fps)
        files.append(video)
        if p.comparison:
            compares = [self.folder / f"compare/{frame_name(f, 'png')}" for f in frames]
            write_video(self.folder / f"{self.name}_comparison.mp4", compares, p.video_fps)
            contact_sheet(self.folder / f"{self.name}_comparison_sheet.png", spread(compares, 4))
            files += [f"{self.name}_comparison.mp4", f"{self.name}_comparison_sheet.png"]
        return files

    def close(self) -> None:
        """Release the rasteriser and device buffers."""
        self.background.close()
        self.ss.close()
        self.launch.close()
        self.shader.close()

    def __enter__(self) -> SequenceRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
