"""8-bit images and videos: PNG files, labelled tiles, contact sheets and H.264 MP4s."""

from __future__ import annotations

import contextlib
import subprocess
from fractions import Fraction
from pathlib import Path

import numpy as np

from pipeline.cache import atomic_path, write_failure

FRAME_PNG_LEVEL = 1
"""zlib level of per-frame PNGs (previews, comparisons). Lossless at any level; 1 took 63 ms for a
512 x 2560 comparison frame where Pillow's default 6 took 176 ms, for a file 15% larger."""


def write_png(path: Path, image: np.ndarray, compress_level: int = FRAME_PNG_LEVEL) -> None:
    """Write an 8-bit RGB(A) image atomically.

    Pillow directly rather than through imageio, whose plugin object, when a write fails (disk
    full), raises again from its destructor and prints a stray traceback."""
    from PIL import Image

    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as fh:
        Image.fromarray(np.ascontiguousarray(image)).save(fh, format="PNG", compress_level=compress_level)


def label(image: np.ndarray, text: str) -> np.ndarray:
    """The image with ``text`` printed in its top-left corner on a dark band."""
    from PIL import Image, ImageDraw

    img = Image.fromarray(np.ascontiguousarray(image[..., :3]))
    draw = ImageDraw.Draw(img)
    box = draw.textbbox((4, 3), text)
    draw.rectangle((0, 0, box[2] + 4, box[3] + 3), fill=(0, 0, 0))
    draw.text((4, 3), text, fill=(255, 255, 255))
    return np.asarray(img)


def contact_sheet(path: Path, tiles: list[Path]) -> None:
    """Stack comparison rows (PNG files) vertically into one sheet."""
    import imageio.v3 as iio

    rows = [iio.imread(p)[..., :3] for p in tiles]
    write_png(path, np.concatenate(rows, axis=0), compress_level=6)  # one image, kept in docs: Pillow's default


X264 = ["-preset", "veryfast", "-crf", "24"]
"""x264 settings of the videos. On the demo's 100 comparison frames (512 x 2560) they encoded in
1.7 s at 36.6 dB PSNR and 1.04 MB, where imageio-ffmpeg's default (medium, crf 25) took 3.5 s for
36.7 dB and 0.97 MB."""


class VideoWriter:
    """An H.264 (yuv420p) MP4 encoded by the ffmpeg bundled in imageio-ffmpeg as its 8-bit RGB frames
    come (``send``), so a renderer's video is made while it renders. The file appears at ``path``
    only when the ``with`` block ends without an error and ffmpeg reports success (a disk that fills
    as it finishes the file leaves nothing behind)."""

    def __init__(self, path: Path, fps: float):
        self.path, self.fps = Path(path), fps
        self._stack = contextlib.ExitStack()
        self._tmp: Path | None = None
        self._ffmpeg: subprocess.Popen | None = None
        self._pad = (0, 0)
        self._errors = ""

    def __enter__(self) -> VideoWriter:
        self._tmp = self._stack.enter_context(atomic_path(self.path))
        return self

    def send(self, image: np.ndarray) -> None:
        """Append a frame (H x W x 3 or 4 uint8; every frame the first one's size)."""
        img = np.asarray(image)[..., :3]
        if self._ffmpeg is None:
            self._start(*img.shape[:2])
        if any(self._pad):
            img = np.pad(img, ((0, self._pad[0]), (0, self._pad[1]), (0, 0)))
        try:
            self._ffmpeg.stdin.write(np.ascontiguousarray(img, np.uint8).data)
        except OSError:  # ffmpeg stopped: it says why when it is waited for
            self._finish()
            raise self._failure() from None

    def _start(self, h: int, w: int) -> None:
        import imageio_ffmpeg

        self._pad = (h % 2, w % 2)  # yuv420p needs even sides
        fps = str(Fraction(self.fps).limit_denominator())
        self._ffmpeg = subprocess.Popen(
            [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-f", "rawvideo", "-vcodec", "rawvideo",
             "-s", f"{w + self._pad[1]}x{h + self._pad[0]}", "-pix_fmt", "rgb24", "-r", fps, "-i", "-",
             "-vcodec", "libx264", "-pix_fmt", "yuv420p", *X264, "-f", "mp4", str(self._tmp)],
            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            start_new_session=True)  # a Ctrl-C reaches this process alone, which then stops ffmpeg

    def _finish(self) -> int:
        """Close ffmpeg's input and wait for it; its exit status."""
        with contextlib.suppress(OSError):
            self._ffmpeg.stdin.close()
        self._errors = self._ffmpeg.stderr.read().decode(errors="replace").strip()
        return self._ffmpeg.wait()

    def _failure(self) -> OSError:
        last = self._errors.splitlines()[-1] if self._errors else "no message"
        return OSError(*write_failure(self._tmp.parent, f"ffmpeg could not encode the video ({last})"),
                       str(self.path))

    def __exit__(self, kind, error, _) -> None:
        with self._stack:  # the temporary file is put in place, or removed after an error
            if kind is not None:
                if self._ffmpeg is not None and self._ffmpeg.poll() is None:
                    self._ffmpeg.kill()
                    self._ffmpeg.wait()
                raise error  # through the temporary file's context, which then removes it
            if self._ffmpeg is None:
                raise ValueError(f"{self.path}: a video needs at least one frame")
            elif self._finish() != 0:
                raise self._failure()


def write_video(path: Path, frames: list[Path], fps: float) -> None:
    """Encode PNG frames as an MP4 (``VideoWriter``)."""
    import imageio.v3 as iio

    if not frames:
        return
    with VideoWriter(path, fps) as video:
        for f in frames:
            video.send(iio.imread(f))


def count_video_frames(path: Path) -> int:
    """Frames in a video, read back by decoding it."""
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    next(reader)  # metadata
    return sum(1 for _ in reader)
