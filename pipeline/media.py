"""8-bit images and videos: PNG files, labelled tiles, contact sheets and H.264 MP4s."""

from __future__ import annotations

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


def write_video(path: Path, frames: list[Path], fps: float) -> None:
    """Encode PNG frames as H.264 (yuv420p) with the ffmpeg bundled in imageio-ffmpeg."""
    import imageio.v3 as iio
    import imageio_ffmpeg

    if not frames:
        return
    first = iio.imread(frames[0])[..., :3]
    h, w = first.shape[:2]
    pad_h, pad_w = h % 2, w % 2  # yuv420p needs even sides
    with atomic_path(Path(path)) as tmp:
        writer = imageio_ffmpeg.write_frames(str(tmp), (w + pad_w, h + pad_h), fps=fps, codec="libx264",
                                             pix_fmt_out="yuv420p", quality=None, output_params=[*X264, "-f", "mp4"],
                                             macro_block_size=1, ffmpeg_log_level="quiet")
        try:
            writer.send(None)
            for f in frames:
                img = iio.imread(f)[..., :3]
                if pad_h or pad_w:
                    img = np.pad(img, ((0, pad_h), (0, pad_w), (0, 0)))
                writer.send(np.ascontiguousarray(img))
            writer.close()
        except OSError:
            # imageio-ffmpeg reports the whole ffmpeg command instead of the cause: find it
            raise OSError(*write_failure(Path(tmp).parent, "ffmpeg could not encode the video"), str(path)) from None


def count_video_frames(path: Path) -> int:
    """Frames in a video, read back by decoding it."""
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    next(reader)  # metadata
    return sum(1 for _ in reader)
