"""Particle sequences on disk: a file pattern gives the frame files, ordered by frame number.

A pattern is one of
- splashsurf's form, one ``{}`` in the file name standing for the frame number (``out/fluid_{}.vtk``),
  which matches unpadded and zero-padded numbers alike (``fluid_7.vtk``, ``fluid_0007.vtk``); the rest
  of the pattern is taken literally;
- a glob (``out/fluid_*.vtk``, ``out/fluid_????.bgeo``): the frame number is the run of digits, in the
  file name, that holds the last digit the wildcards match;
- one plain path: a one-frame sequence, numbered by the last run of digits in its name (else 0).

Frames are ordered by number, never by name (``f_2`` before ``f_10``). Numbers may advance by a step
(0, 10, 20: the greatest common divisor of the differences); numbers absent at that step between the
first and last frame are gaps, kept in ``missing`` and logged as one warning. Frames may hold different
particle counts. All files must share one format.
"""

from __future__ import annotations

import glob
import itertools
import logging
import math
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pipeline.particles import READ_FORMATS, ParticleFormatError, ParticleFrame, particle_format, read_particles

log = logging.getLogger(__name__)

_DIGITS = re.compile(r"\d+")


def _has_wildcards(text: str) -> bool:
    """Whether ``text`` holds a glob wildcard (``*``, ``?`` or ``[``)."""
    return any(c in text for c in "*?[")


class ParticleSequenceError(ParticleFormatError):
    """A pattern gives no usable sequence; the message names the pattern."""


@dataclass(frozen=True)
class ParticleSequence:
    """The frame files of one particle sequence, ordered by frame number."""

    pattern: str
    """The pattern the files were found by."""
    numbers: tuple[int, ...]
    """Frame numbers, ascending."""
    paths: tuple[Path, ...]
    """One file per frame number, in the same order."""
    step: int
    """Step between consecutive frame numbers (1 for a single frame)."""
    missing: tuple[int, ...]
    """Frame numbers absent, at ``step``, between the first and the last frame."""
    file_format: str
    """The files' format key, e.g. ``.vtk`` (see ``particle_format``)."""

    def __len__(self) -> int:
        """Number of frames."""
        return len(self.numbers)

    def path(self, number: int) -> Path:
        """The file of frame ``number``."""
        try:
            return self.paths[self.numbers.index(number)]
        except ValueError:
            raise ParticleSequenceError(f"{self.pattern}: no frame {number} "
                                        f"(frames {_compact(self.numbers)})") from None

    def read(self, number: int, up: str = "y") -> ParticleFrame:
        """Read frame ``number``; ``up="z"`` converts Z-up data to the pipeline's Y-up."""
        return read_particles(self.path(number), up=up)

    @property
    def name(self) -> str:
        """A folder-safe name: the first file's name without digits and extension (``fluid_0007.vtk``
        -> ``fluid``)."""
        stem = re.sub(r"\d+", "", self.paths[0].name.split(".")[0])
        return re.sub(r"[^A-Za-z0-9]+", "_", stem).strip("_") or "sequence"

    def median_radius(self, up: str = "y") -> float | None:
        """The median per-particle radius (Houdini's ``pscale``) of the first frame, if it has one."""
        radii = self.read(self.numbers[0], up=up).radii
        return None if radii is None or not len(radii) else float(np.median(radii))

    def select(self, start: int | None = None, end: int | None = None) -> ParticleSequence:
        """The frames numbered ``start`` to ``end``, both inclusive; None leaves that side open."""
        if start is not None and end is not None and start > end:
            raise ParticleSequenceError(f"{self.pattern}: frame range {start}:{end} is empty (start > end)")
        lo = self.numbers[0] if start is None else start
        hi = self.numbers[-1] if end is None else end
        keep = [i for i, n in enumerate(self.numbers) if lo <= n <= hi]
        if not keep:
            raise ParticleSequenceError(f"{self.pattern}: frame range {_range_text(start, end)} selects no frame "
                                        f"(frames {self.numbers[0]} to {self.numbers[-1]} exist)")
        numbers = tuple(self.numbers[i] for i in keep)
        return replace(self, numbers=numbers, paths=tuple(self.paths[i] for i in keep),
                       missing=tuple(n for n in self.missing if numbers[0] < n < numbers[-1]))


def find_sequence(pattern: str | Path, start: int | None = None, end: int | None = None) -> ParticleSequence:
    """The frames matching ``pattern`` (``{}`` placeholder, glob or one path, which is frame 1), numbered
    ``start`` to ``end``."""
    pattern = str(pattern)
    matches = _match(pattern)
    if not matches:
        folder = Path(pattern).parent
        where = "" if folder.is_dir() or _has_wildcards(str(folder)) else f"; folder {folder} does not exist"
        raise ParticleSequenceError(f"{pattern}: no file matches the pattern{where}")
    formats: dict[str, list[Path]] = {}
    for _, path in sorted(matches):
        formats.setdefault(particle_format(path) or "(no extension)", []).append(path)
    if len(formats) > 1:
        counts = ", ".join(f"{len(files)} {fmt} (e.g. {files[0].name})" for fmt, files in sorted(formats.items()))
        raise ParticleSequenceError(f"{pattern}: the pattern matches files of several formats: {counts}; "
                                    f"narrow it to one extension")
    (file_format,) = formats
    if file_format not in READ_FORMATS:
        raise ParticleSequenceError(f"{pattern}: matches {file_format} files, not a particle format "
                                    f"(supported: {', '.join(READ_FORMATS)})")
    by_number: dict[int, Path] = {}
    for number, path in matches:
        if number in by_number:
            raise ParticleSequenceError(f"{pattern}: frame {number} matches two files, {by_number[number]} "
                                        f"and {path}; make the pattern match one of them")
        by_number[number] = path
    numbers = tuple(sorted(by_number))
    paths = tuple(by_number[n] for n in numbers)
    step = math.gcd(*(b - a for a, b in itertools.pairwise(numbers))) or 1
    present = set(numbers)
    missing = tuple(n for n in range(numbers[0], numbers[-1] + 1, step) if n not in present)
    sequence = ParticleSequence(pattern, numbers, paths, step, missing, file_format)
    if start is not None or end is not None:
        sequence = sequence.select(start, end)
    if sequence.missing:
        log.warning("%s: %d frame(s) missing between %d and %d: %s", pattern, len(sequence.missing),
                    sequence.numbers[0], sequence.numbers[-1], _compact(sequence.missing))
    return sequence


def numbered_files(pattern: str | Path) -> list[tuple[int, Path]]:
    """(frame number, file) of every file a pattern matches (``{}``, glob or one path; any file
    type), in frame-number order."""
    return sorted(_match(str(pattern)))


def parse_frame_range(text: str | None) -> tuple[int | None, int | None]:
    """``"10:20"`` -> (10, 20), ``"10:"`` -> (10, None), ``":20"``, ``"7"`` -> (7, 7), None or ``""`` -> all."""
    if text is None or not text.strip():
        return None, None
    start, sep, end = text.strip().partition(":")
    try:
        lo = int(start) if start.strip() else None
        hi = (int(end) if end.strip() else None) if sep else lo
    except ValueError:
        raise ValueError(f"frame range {text!r}: expected START:END with whole frame numbers "
                         f"(either may be left out), or one frame number") from None
    if lo is not None and hi is not None and lo > hi:
        raise ValueError(f"frame range {text!r}: start {lo} is after end {hi}")
    return lo, hi


def _match(pattern: str) -> list[tuple[int, Path]]:
    """(frame number, path) of every file the pattern matches, unordered."""
    folder, name = Path(pattern).parent, Path(pattern).name
    if "{}" in pattern:
        if "{}" not in name or name.count("{}") > 1 or "{}" in str(folder):
            raise ParticleSequenceError(f"{pattern}: the pattern must hold one {{}} for the frame number, "
                                        f"in the file name")
        before, after = name.split("{}")
        number = re.compile(re.escape(before) + r"(\d+)" + re.escape(after))
        candidates = glob.glob(os.path.join(glob.escape(str(folder)), glob.escape(before) + "*" + glob.escape(after)))
        found = [(m, Path(c)) for c in candidates if (m := number.fullmatch(Path(c).name))]
        return [(int(m.group(1)), path) for m, path in found if path.is_file()]
    if _has_wildcards(pattern):
        wildcards = _wildcard_regex(name)
        return [(_glob_frame_number(pattern, wildcards, Path(c).name), Path(c))
                for c in glob.glob(pattern) if Path(c).is_file()]
    path = Path(pattern)
    if path.is_dir():
        raise ParticleSequenceError(f"{pattern} is a folder: give its files, e.g. {path / '*.vtk'} or "
                                    f"{path / 'fluid_{}.vtk'} ({{}} stands for the frame number)")
    # one named file is frame 1: digits in a name need not be a frame number (octo_880k.vtk)
    return [(1, path)] if path.is_file() else []


def _wildcard_regex(name: str) -> re.Pattern[str]:
    """A regex for a glob file name in which each wildcard (``*``, ``?``, ``[...]``) is a group."""
    parts, i = [], 0
    while i < len(name):
        c = name[i]
        close = name.find("]", i + 2) if c == "[" else -1
        if c == "*":
            parts.append("(.*)")
        elif c == "?":
            parts.append("(.)")
        elif close > 0:
            body = name[i + 1:close]
            parts.append("([" + ("^" + body[1:] if body.startswith("!") else body) + "])")
            i = close
        else:
            parts.append(re.escape(c))
        i += 1
    return re.compile("".join(parts))


def _glob_frame_number(pattern: str, wildcards: re.Pattern[str], name: str) -> int:
    """The digit run in ``name`` that holds the last digit matched by a wildcard of the pattern."""
    m = wildcards.fullmatch(name)
    spans = [m.span(g) for g in range(1, wildcards.groups + 1)] if m else []
    digits = [i for lo, hi in spans for i in range(lo, hi) if name[i].isdigit()]
    if not digits:
        raise ParticleSequenceError(f"{pattern}: cannot tell the frame number of {name}: the file name's "
                                    f"wildcards match no digits; put {{}} where the frame number stands")
    run = next(r for r in _DIGITS.finditer(name) if r.start() <= max(digits) < r.end())
    return int(run.group())


def _compact(numbers: Iterable[int], limit: int = 12) -> str:
    """Ascending numbers as ranges, ``1-3, 7, 9-12``; more than ``limit`` ranges end in ``(+N more)``."""
    ranges: list[list[int]] = []
    for n in numbers:
        if ranges and n == ranges[-1][1] + 1:
            ranges[-1][1] = n
        else:
            ranges.append([n, n])
    text = [f"{a}" if a == b else f"{a}-{b}" for a, b in ranges]
    more = f", (+{len(text) - limit} more)" if len(text) > limit else ""
    return ", ".join(text[:limit]) + more


def _range_text(start: int | None, end: int | None) -> str:
    """``start:end`` with open sides left blank."""
    return f"{'' if start is None else start}:{'' if end is None else end}"
