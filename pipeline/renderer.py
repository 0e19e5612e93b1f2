"""A particle sequence to shaded EXR frames, previews, a video and a side-by-side comparison.

Into one folder: ``frames/frame_0001.exr`` (the passes of ``methods.RenderedFrame`` named
``ViewLayer.<Pass>.<Channel>``, the camera in the header: docs/compositing.md),
``preview/frame_0001.png``, ``<name>_<method>.mp4`` and, with ``render.comparison``,
``compare/frame_0001.png``, ``<name>_comparison.mp4`` and ``<name>_comparison_sheet.png``
(bilateral | narrow-range | refined | metaballs | mesh). A frame counts as done when all its files exist, so
a killed run resumes after the last whole frame. Used by the render stage and the CLI.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
import warp as wp
from tqdm import tqdm

from pipeline.camera import Camera
from pipeline.config import Config, RenderConfig
from pipeline.device import warp_device
from pipeline.executor import run_sharded
from pipeline.frames import frame_name, spread
from pipeline.media import VideoWriter, contact_sheet, label, write_png, write_video
from pipeline.methods import (
    NAMES,
    SPHERE_FILTERS,
    RenderedFrame,
    motion_pass,
    normal_source,
    shade_frame,
    sphere_filters_of,
)
from pipeline.parallel import Launcher
from pipeline.screen import ScreenSpace
from pipeline.screen.motion import camera_motion, particle_motion
from pipeline.shading import Shader, load_environment, tonemap
from pipeline.shading.background import BackgroundRenderer, Surroundings
from pipeline.timing import Timings
from pipeline.vectors import host
from pipeline.writer import BackgroundWriter

log = logging.getLogger("deep_ssfr")
COMPARED = ("bilateral", "nrf", "refined", "metaball", "mesh")


class SequenceRenderer:
    """Renders the frames of one sequence with ``render.method`` (and the compared methods) into
    ``folder``, timing each step; ``close()`` (or ``with``) releases the device buffers.

    ``on_device`` (default: on a GPU) keeps a frame's maps on the device as torch tensors between
    its steps (the sky, the refined method's maps, the motion splat) and brings only the passes to
    the host; on the CPU's tensors it renders what the host way does (tested)."""

    def __init__(self, folder: Path, name: str, around: Surroundings, config: Config, device: str, refiner=None,
                 metaball=None, on_device: bool | None = None):
        self.folder, self.name, self.config = Path(folder), name, config
        p = config.render
        self.methods = [p.method] + [m for m in COMPARED if p.comparison and m != p.method]
        if "refined" in self.methods and refiner is None:
            raise ValueError("the refined method needs a generator")
        if "metaball" in self.methods and metaball is None:
            raise ValueError("the metaball method needs a metaball generator")
        self.refiner, self.metaball = refiner, metaball
        wdev = warp_device(device)
        self.ss, self.launch = ScreenSpace(wdev), Launcher(wdev)
        self.on_device = not self.launch.cpu if on_device is None else on_device
        self.shader = Shader(wdev, environment=load_environment(p.environment) if p.environment else None)
        self.around, self.background = around, None  # the rasteriser, made when the first frame needs it
        # pyrender rasterises on a thread of its own, where its GL context lives: its import (about a
        # second) and each new camera's background (0.2-0.3 s at 1080p) run beside the frame's work
        self._rasteriser = None
        if p.background == "scene":
            self._rasteriser = ThreadPoolExecutor(1, thread_name_prefix="background")
            self._rasteriser.submit(importlib.import_module, "pyrender")
        self._backdrop: tuple | None = None  # the last camera's background and its depth
        self._seen: tuple | None = None  # the last frame's camera and the particles seen in front
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
        view = (camera.view.tobytes(), camera.fov_y_deg, camera.width, camera.height)
        stale = self._backdrop is None or self._backdrop[0] != view  # a still camera's is made once
        rasterised = self._rasteriser.submit(self._rasterise, camera) if stale and self._rasteriser else None
        sources, frame_cache = {}, {SPHERE_FILTERS: sphere_filters_of(self.methods)}
        for method in self.methods:
            t = self.timings if method == p.method else Timings()
            sources[method] = (t, normal_source(method, positions, radius, camera, self.config.dataset, self.ss,
                                                self.launch, self.refiner, p.normal_threshold, t, frame_cache,
                                                self.metaball, self.on_device))
        with self.timings("background"):
            if stale:
                if rasterised is not None:
                    bg, bg_depth = rasterised.result()
                else:  # nothing behind the fluid: it refracts the environment alone
                    shape = (p.height, p.width)
                    bg, bg_depth = np.zeros((*shape, 3), np.float32), np.zeros(shape, np.float32)
                self._backdrop = (view, self.shader.fill_sky(bg, bg_depth, camera, p, on_device=self.on_device),
                                  bg_depth)
            bg, bg_depth = self._backdrop[1:]
        shaded = {method: shade_frame(src, bg, bg_depth, camera, p, self.shader, t)
                  for method, (t, src) in sources.items()}
        seen = frame_cache.get("seen_kernels")
        self._seen = (seen[0], seen[2]) if seen is not None else None
        return shaded

    def _rasterise(self, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """pyrender's background (linear colour, depth) from ``camera``, on the rasteriser's thread."""
        if self.background is None:
            p = self.config.render
            self.background = BackgroundRenderer(self.around, p, p.width, p.height)
        return self.background.render(camera)

    def motion(self, frame: RenderedFrame, positions: np.ndarray, velocities: np.ndarray | None, radius: float,
               camera: Camera, fps: float, prev: tuple[Camera, int] | None, nxt: tuple[Camera, int] | None) -> None:
        """Fill ``frame.motion``: the particles' screen motion where the fluid shows, the camera's
        elsewhere (``prev``/``nxt``: the neighbouring rendered frames' cameras and frame gaps)."""
        with self.timings("motion"):
            if self._seen is not None and self._seen[0] is camera:
                # the particles the anisotropy found in front: the surface shows no other but at a few
                # pixels of steep edges (0.02% of a test block's), for a fifth of a million's cost
                positions = np.asarray(positions)[self._seen[1]]
                velocities = None if velocities is None else np.asarray(velocities)[self._seen[1]]
            if self.on_device:  # each particle's motion made on the device (1M particles: 0.15 s on a host)
                on = wp.device_to_torch(self.launch.device)
                positions = torch.as_tensor(positions, device=on)
                velocities = None if velocities is None else torch.as_tensor(velocities, device=on)
            per_particle = particle_motion(positions, velocities, camera, fps, prev, nxt)
            visible = frame.fluid[..., 3] > 0
            # on a GPU the particles' motion and the rim fill stay there; one download for the EXR
            fluid_motion, covered = self.ss.motion(positions, per_particle, radius, camera,
                                                   np.where(visible, frame.depth, 0.0), on_device=self.on_device)
            frame.motion = host(motion_pass(frame.fluid[..., 3], fluid_motion, covered,
                                            camera_motion(frame.depth, camera, prev, nxt, self.launch, self.on_device)))

    def write(self, frame: int, camera: Camera, fps: float, shaded: dict[str, RenderedFrame],
              timings: Timings, videos: list[VideoWriter]) -> None:
        """The EXR, preview and comparison of one frame (on the writer thread), and the frame of each
        video being encoded as the frames come (``videos``: ``video_names``' order, or none)."""
        p = self.config.render
        main = shaded[p.method]
        exr, preview, *compare = (self.folder / o for o in self.outputs(frame))
        with timings("exr_write"):
            main.write(exr, p, camera, fps, frame)
        main_tile = tonemap(main.beauty, p.exposure)  # the preview, and the main method's comparison tile
        write_png(preview, main_tile)
        if videos:
            videos[0].send(main_tile)
        if compare:
            tiles = [label(main_tile if m == p.method else tonemap(shaded[m].beauty, p.exposure), NAMES[m])
                     for m in COMPARED]
            row = np.concatenate(tiles, axis=1)
            write_png(compare[0], row)
            if videos:
                videos[1].send(row)

    def render(self, frames: list[int], load: Callable[[int], tuple[np.ndarray, np.ndarray | None]], radius: float,
               camera_at: Callable[[int], Camera], fps: float | None = None, subset: list[int] | None = None,
               videos: bool = True) -> list[str]:
        """Render the frames not yet done, then the videos; returns the files of the whole sequence.

        ``load(frame)`` gives a frame's positions and velocities (m/s, or None), ``camera_at(i)``
        the camera of the i-th frame, ``fps`` the sequence's frames per second, which turns
        velocities into motion vectors in pixels per frame (default ``render.video_fps``).
        ``subset`` (positions in ``frames``) renders only those, without ``videos`` (a shard)."""
        p = self.config.render
        fps = fps or p.video_fps
        no_fluid: list[int] = []
        no_velocity = False
        write_timings = Timings()
        # a run that renders every frame in order encodes its videos as it goes (on the writer thread
        # and ffmpeg's, in the time the frames leave free); a resumed run or a shard encodes the PNGs
        encode = videos and subset is None and bool(frames) and not any(self.done(f) for f in frames)
        with contextlib.ExitStack() as stack:
            streams = [stack.enter_context(VideoWriter(self.folder / v, p.video_fps))
                       for v in video_names(self.name, p)] if encode else []
            writer = stack.enter_context(BackgroundWriter())  # drained before the videos close
            order = range(len(frames)) if subset is None else subset
            todo = [i for i in order if not self.done(frames[i])]
            # each frame's particles are read while the one before renders (a 1M-particle frame's
            # cached copy: 12-35 ms); a damaged one still fails when its turn comes
            loader = stack.enter_context(ThreadPoolExecutor(1, thread_name_prefix="load"))
            stack.callback(loader.shutdown, cancel_futures=True)
            loaded = loader.submit(load, frames[todo[0]]) if todo else None
            for k, i in enumerate(tqdm(todo, total=len(order), initial=len(order) - len(todo),
                                       desc=f"render {self.name}", unit="frame")):
                frame = frames[i]
                positions, velocities = loaded.result()
                loaded = loader.submit(load, frames[todo[k + 1]]) if k + 1 < len(todo) else None
                camera = camera_at(i)
                shaded = self.shade(positions, radius, camera)
                main = shaded[p.method]
                if not main.mask.any():
                    no_fluid.append(frame)
                if p.motion_vectors:
                    if velocities is None and len(positions) and not no_velocity:
                        no_velocity = True
                        log.warning("render %s: frame %d has no particle velocities; its motion vectors show "
                                    "only the camera's motion (0 for a still camera)", self.name, frame)
                    prev = (camera_at(i - 1), frame - frames[i - 1]) if i > 0 else None
                    nxt = (camera_at(i + 1), frames[i + 1] - frame) if i + 1 < len(frames) else None
                    self.motion(main, positions, velocities, radius, camera, fps, prev, nxt)
                writer.submit(self.write, frame, camera, fps, shaded, write_timings, streams)
        self.timings.merge(write_timings)
        if no_fluid:
            log.warning("render %s: the camera sees no fluid in %d frames (first: %d); they show the background "
                        "only", self.name, len(no_fluid), no_fluid[0])
        return write_videos(self.folder, self.name, frames, p, encoded=encode) if videos else []

    def close(self) -> None:
        """Release the rasteriser (on its thread, where its GL context lives) and device buffers."""
        if self._rasteriser is not None:  # after whatever it has begun
            self._rasteriser.submit(lambda: self.background and self.background.close()).result()
            self._rasteriser.shutdown()
        self.ss.close()
        self.launch.close()
        self.shader.close()

    def __enter__(self) -> SequenceRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def video_names(name: str, p: RenderConfig) -> list[str]:
    """The sequence's videos: the preview's, and with ``render.comparison`` the comparison's."""
    return [f"{name}_{p.method}.mp4", *([f"{name}_comparison.mp4"] if p.comparison else [])]


def write_videos(folder: Path, name: str, frames: list[int], p: RenderConfig, encoded: bool = False) -> list[str]:
    """The preview video (and the comparison video and sheet) of all frames, the videos from the PNGs
    unless they were ``encoded`` while rendering; the sequence's files."""
    stills = ["preview", "compare"]
    if not encoded:
        for video, kind in zip(video_names(name, p), stills, strict=False):
            write_video(folder / video, [folder / f"{kind}/{frame_name(f, 'png')}" for f in frames], p.video_fps)
    if p.comparison:
        contact_sheet(folder / f"{name}_comparison_sheet.png",
                      spread([folder / f"compare/{frame_name(f, 'png')}" for f in frames], 4))
    sheet = [f"{name}_comparison_sheet.png"] if p.comparison else []
    return [f"frames/{frame_name(f, 'exr')}" for f in frames] + video_names(name, p) + sheet


def render_sequence(folder: Path, name: str, around: Surroundings, config: Config, device: str, refiner,
                    frames: list[int], load: Callable[[int], tuple[np.ndarray, np.ndarray | None]], radius: float,
                    camera_at: Callable[[int], Camera], fps: float | None = None,
                    metaball=None) -> tuple[list[str], Timings]:
    """Render a sequence into ``folder`` here, or with ``config.executor='ray'`` as one shard of
    frames per CPU (or GPU) of the Ray cluster (each task its own renderer; the videos are made here once
    all frames are back). Returns the sequence's files and the timings."""
    def shard(subset: list[int] | None) -> tuple[list[str], Timings]:
        with SequenceRenderer(folder, name, around, config, device, refiner, metaball) as renderer:
            files = renderer.render(frames, load, radius, camera_at, fps, subset, videos=subset is None)
        return files, renderer.timings

    if config.executor == "local":
        return shard(None)
    timings = Timings()
    for _, t in run_sharded(shard, len(frames), config.executor, config.ray_address, device):
        timings.merge(t)
    return write_videos(Path(folder), name, frames, config.render), timings
