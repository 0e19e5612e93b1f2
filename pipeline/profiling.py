"""Where a GPU frame's time goes: torch's profiler around a loop, and a reading of its trace.

``profiled()`` records a block with torch's profiler: the host's torch operations and, on a GPU,
every kernel, copy and fill on the device (Warp's too: the profiler listens to the driver's
launches as well as the runtime's), with the ``Timings`` steps that ran inside as named ranges.
``summarize()`` reads the trace into the figures that say what to change: how much of the
window the device was busy, how often and how long the host waited for it, what the copies
moved, which steps queued which device time, and the costliest kernels. Saved traces
(``.trace.json.gz``, for chrome://tracing or Perfetto) can be read again later:

    python -m pipeline.profiling render_stage.trace.json.gz [--units 5 --unit frame]
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import re
import tempfile
from bisect import bisect_right
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from pipeline import timing
from pipeline.timing import synchronize

DEVICE_CATEGORIES = ("kernel", "gpu_memcpy", "gpu_memset")
LAUNCH_CATEGORIES = ("cuda_runtime", "cuda_driver")
HOST_WAIT = re.compile(r"Synchronize|^cu(da)?Memcpy(?!.*Async)")
"""Runtime and driver calls that make the host wait for the device: the synchronisations, and the
copies without ``Async`` (``cudaMemcpy``, ``cuMemcpyDtoH_v2``). An ``Async`` copy into pageable
memory waits too, but its name does not say so; its time shows in the copies' figures."""
LAUNCHES = re.compile(r"^(cudaLaunchKernel|cuLaunchKernel|cudaGraphLaunch|cuGraphLaunch)")
COPY_DIRECTION = re.compile(r"\b([HDP]to[HDP])\b")
WINDOW_PREFIX = "profiled: "
GAP_US = 100.0
"""Device idle stretches this long (microseconds) or longer are counted as gaps: shorter ones are
the launch latency between queued kernels, longer ones a device waiting for the host."""


@dataclass
class Trace:
    """A recorded block: its trace events (Chrome's trace format) and the units of work it held."""

    name: str
    events: list[dict] = field(default_factory=list)
    units: int = 1
    unit: str = "frame"

    def summary(self) -> str:
        """The trace read into figures per unit (``summarize``)."""
        return summarize(self.events, self.units, self.unit, self.name)

    def save(self, folder: str | Path) -> tuple[Path, Path]:
        """Write ``NAME.trace.json.gz`` (the whole trace) and ``NAME.txt`` (its summary) into
        ``folder``, each through a temporary file; returns the two paths."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        trace, text = folder / f"{self.name}.trace.json.gz", folder / f"{self.name}.txt"
        for path, write in ((trace, self._write_trace), (text, lambda p: p.write_text(self.summary() + "\n"))):
            tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
            write(tmp)
            tmp.replace(path)
        return trace, text

    def report(self, folder: str | Path, note: str) -> str:
        """Save the trace and its summary into ``folder`` (``save``) and return what a benchmark
        prints of them: a heading with ``note`` (what the recorded run held), the summary, the paths."""
        saved = self.save(folder)
        return f"recorded with the profiler ({note}):\n{self.summary()}\nsaved: " + ", ".join(map(str, saved))

    def _write_trace(self, path: Path) -> None:
        with gzip.open(path, "wt") as f:
            json.dump({"traceEvents": self.events, "units": self.units, "unit": self.unit}, f)


def load_trace(path: str | Path) -> Trace:
    """A trace saved by ``Trace.save`` (or any Chrome trace, plain or gzipped, as one unit)."""
    path = Path(path)
    opener = gzip.open if path.suffix == ".gz" else open
    try:
        with opener(path, "rt") as f:
            body = json.load(f)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable trace ({exc})") from exc
    name = path.name.removesuffix(".gz").removesuffix(".json").removesuffix(".trace")
    return Trace(name, body.get("traceEvents", []), body.get("units", 1), body.get("unit", "frame"))


@contextmanager
def profiled(name: str, units: int = 1, unit: str = "frame", enabled: bool = True):
    """Record the block with torch's profiler (the device's activity too where CUDA is there) and
    yield a ``Trace`` that holds the events once the block ends. The GPU is waited for at both
    ends, so the window holds the block's device work and nothing queued before it. ``units``:
    the frames (steps, views) the block runs, for figures per unit. ``enabled=False`` records
    nothing (the ``Trace`` stays empty)."""
    trace = Trace(name, units=units, unit=unit)
    if not enabled:
        yield trace
        return
    import torch
    from torch.profiler import ProfilerActivity, profile, record_function

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if torch.cuda.is_available() else [])
    try:  # every thread's operations (the stages' workers and writers), where torch can
        options = {"experimental_config": torch._C._profiler._ExperimentalConfig(profile_all_threads=True)}
    except (AttributeError, TypeError):
        options = {}
    with profile(activities=activities, **options) as prof:
        synchronize()
        timing._RANGES[0] = True
        try:
            with record_function(WINDOW_PREFIX + name):
                yield trace
                synchronize()
        finally:
            timing._RANGES[0] = False
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "trace.json"
        prof.export_chrome_trace(str(path))
        trace.events = json.loads(path.read_text()).get("traceEvents", [])


def _spans(events: list[dict]) -> list[tuple[float, float]]:
    """The (start, end) of complete events, in microseconds."""
    return [(float(e["ts"]), float(e["ts"]) + float(e.get("dur", 0.0))) for e in events]


def merged_spans(spans: list[tuple[float, float]], lo: float = float("-inf"),
                 hi: float = float("inf")) -> list[tuple[float, float]]:
    """The union of the spans as disjoint (start, end) spans in order, clipped to [lo, hi]
    (work on overlapping streams counts once)."""
    merged: list[list[float]] = []
    for a, b in sorted((max(a, lo), min(b, hi)) for a, b in spans):
        if b <= a:
            continue
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    return [(a, b) for a, b in merged]


def idle_gaps(busy: list[tuple[float, float]], lo: float, hi: float) -> list[tuple[float, float]]:
    """The (start, length) of each stretch of [lo, hi] that no busy span covers."""
    gaps, at = [], lo
    for a, b in busy:
        if a > at:
            gaps.append((at, a - at))
        at = max(at, b)
    if hi > at:
        gaps.append((at, hi - at))
    return gaps


def _window(events: list[dict]) -> tuple[float, float]:
    """The recorded block's host window: its own range, else the extent of all events."""
    own = [e for e in events if e.get("ph") == "X" and str(e.get("name", "")).startswith(WINDOW_PREFIX)]
    if own:
        return _spans(own[:1])[0]
    spans = _spans([e for e in events if e.get("ph") == "X" and "ts" in e])
    return (min(a for a, _ in spans), max(b for _, b in spans)) if spans else (0.0, 0.0)


def _step_of_launch(events: list[dict]) -> dict[int, str]:
    """Each device launch's correlation id -> the innermost named range (a ``Timings`` step) around
    the host call that queued it, on the same thread."""
    ranges = defaultdict(list)
    for e in events:
        if e.get("cat") == "user_annotation" and not str(e.get("name", "")).startswith(WINDOW_PREFIX):
            ranges[(e.get("pid"), e.get("tid"))].append((float(e["ts"]), float(e["ts"]) + float(e.get("dur", 0.0)),
                                                          str(e["name"])))
    starts = {}
    for key, spans in ranges.items():
        spans.sort()
        ranges[key] = spans
        starts[key] = [a for a, _, _ in spans]
    step = {}
    for e in events:
        correlation = e.get("args", {}).get("correlation")
        if e.get("cat") not in LAUNCH_CATEGORIES or correlation is None:
            continue
        key, t = (e.get("pid"), e.get("tid")), float(e["ts"])
        spans = ranges.get(key, [])
        # the innermost range holding t is the latest-starting one among those that contain it
        for a, b, name in reversed(spans[: bisect_right(starts.get(key, []), t)]):
            if a <= t <= b:
                step[correlation] = name
                break
    return step


def _self_times(events: list[dict]) -> list[tuple[str, float]]:
    """Each host operation's name and its time outside the operations it called (nested by their
    spans on the same thread), so a convolution's layers of dispatch are counted once."""
    threads = defaultdict(list)
    for e in events:
        threads[(e.get("pid"), e.get("tid"))].append(e)
    out = []
    for ops in threads.values():
        ops.sort(key=lambda e: (float(e["ts"]), -float(e.get("dur", 0.0))))
        own = [float(e.get("dur", 0.0)) for e in ops]
        stack: list[tuple[float, int]] = []  # (end, index) of the open operations
        for i, e in enumerate(ops):
            start = float(e["ts"])
            while stack and stack[-1][0] <= start:
                stack.pop()
            if stack:
                own[stack[-1][1]] -= float(e.get("dur", 0.0))
            stack.append((start + float(e.get("dur", 0.0)), i))
        out += [(str(e["name"]), t) for e, t in zip(ops, own, strict=True)]
    return out


def _short(name: str, width: int = 70) -> str:
    return name if len(name) <= width else name[: width - 3] + "..."


def summarize(events: list[dict], units: int = 1, unit: str = "frame", name: str = "trace", top: int = 8) -> str:
    """The figures that say where a recorded block's time went, per ``unit`` (``units`` of them in
    the block): the device's busy share of the window and its kernels, copies and fills; the
    host's waits for the device and its launches; the bytes each copy direction moved; device time
    by the step that queued it; the costliest kernels; the steps' host time. Without device events
    (a CPU run) the host's steps and its costliest operations."""
    units = max(int(units), 1)
    complete = [e for e in events if e.get("ph") == "X" and "ts" in e]
    lo, hi = _window(complete)
    per = _Per(units, unit)
    lines = [f"{name}: {units} {unit}{'s' if units != 1 else ''} in {(hi - lo) / 1000:.1f} ms "
             f"({per(hi - lo):.2f} ms a {unit})"]
    if any(e.get("cat") in DEVICE_CATEGORIES for e in complete):
        lines += _device_figures(complete, lo, hi, per, top)
    else:
        lines.append("no device activity in the trace (a CPU run): the host's figures only")
    return "\n".join(lines + _host_figures(complete, per, top))


@dataclass(frozen=True)
class _Per:
    """Microseconds in all -> milliseconds a unit, and counts in all -> a unit."""

    units: int
    unit: str

    def __call__(self, us: float) -> float:
        return us / 1000.0 / self.units

    def count(self, n: float) -> float:
        return n / self.units


def _totals(events: list[dict], key) -> dict[str, list[float]]:
    """[count, summed duration] of the events by ``key(event)``."""
    out = defaultdict(lambda: [0, 0.0])
    for e in events:
        out[key(e)][0] += 1
        out[key(e)][1] += float(e.get("dur", 0.0))
    return out


def _ranked(totals: dict[str, list[float]], per: _Per, top: int) -> list[str]:
    """The ``top`` entries by time: ms and count a unit, the name."""
    return [f"  {per(t):8.3f}  {per.count(c):6.1f}  {_short(k)}"
            for k, (c, t) in sorted(totals.items(), key=lambda kv: -kv[1][1])[:top]]


def _device_figures(complete: list[dict], lo: float, hi: float, per: _Per, top: int) -> list[str]:
    """The device's lines of ``summarize``."""
    unit, device = per.unit, [e for e in complete if e.get("cat") in DEVICE_CATEGORIES]
    spans = merged_spans(_spans(device), lo, hi)
    busy = sum(b - a for a, b in spans)
    kind = _totals(device, lambda e: e["cat"])
    lines = [f"device busy {per(busy):.2f} ms a {unit} ({100 * busy / max(hi - lo, 1e-9):.0f}% of the window): "
             f"kernels {per(kind['kernel'][1]):.2f}, copies {per(kind['gpu_memcpy'][1]):.2f}, "
             f"fills {per(kind['gpu_memset'][1]):.2f} ms"]
    gaps = [g for g in idle_gaps(spans, lo, hi) if g[1] >= GAP_US]
    lines.append(f"device idle in {per.count(len(gaps)):.1f} gaps of {GAP_US / 1000:g} ms or more a {unit}, "
                 f"{per(sum(g[1] for g in gaps)):.2f} ms; the longest "
                 + ", ".join(f"{g[1] / 1000:.2f} ms at +{(g[0] - lo) / 1000:.1f}"
                             for g in sorted(gaps, key=lambda g: -g[1])[:3]))
    runtime = [e for e in complete if e.get("cat") in LAUNCH_CATEGORIES]
    waits = _totals([e for e in runtime if HOST_WAIT.search(str(e.get("name", "")))], lambda e: str(e["name"]))
    launches = sum(1 for e in runtime if LAUNCHES.match(str(e.get("name", ""))))
    lines.append(f"host waits for the device: {per.count(sum(c for c, _ in waits.values())):.1f} a {unit}, "
                 f"{per(sum(t for _, t in waits.values())):.2f} ms"
                 + (" (" + ", ".join(f"{k} {per.count(c):.1f}" for k, (c, _) in sorted(waits.items())) + ")"
                    if waits else "")
                 + f"; {per.count(launches):.1f} kernel launches a {unit}")
    copies = defaultdict(lambda: [0, 0.0, 0.0])
    for e in device:
        if e["cat"] == "gpu_memcpy":
            found = COPY_DIRECTION.search(str(e.get("name", "")))
            c = copies[found.group(1) if found else "other"]
            c[0] += 1
            c[1] += float(e.get("args", {}).get("bytes", 0) or 0)
            c[2] += float(e.get("dur", 0.0))
    if copies:
        lines.append(f"copies a {unit}: " + "; ".join(
            f"{k} {per.count(c[0]):.1f} x, {per.count(c[1]) / 1e6:.1f} MB in {per(c[2]):.2f} ms"
            + (f" ({c[1] / c[2] / 1e3:.1f} GB/s)" if c[2] > 0 and c[1] > 0 else "")
            for k, c in sorted(copies.items())))
    step = _step_of_launch(complete)
    by_step = _totals(device, lambda e: step.get(e.get("args", {}).get("correlation"), "(no step)"))
    lines.append(f"device time by the step that queued it (ms a {unit}): " + ", ".join(
        f"{k} {per(t):.2f}" for k, (_, t) in sorted(by_step.items(), key=lambda kv: -kv[1][1])))
    lines.append(f"costliest kernels (ms a {unit}, launches a {unit}):")
    return lines + _ranked(_totals([e for e in device if e["cat"] == "kernel"], lambda e: str(e["name"])), per, top)


def _host_figures(complete: list[dict], per: _Per, top: int) -> list[str]:
    """The host's lines of ``summarize``: the steps' time and the costliest operations."""
    lines = []
    steps = _totals([e for e in complete if e.get("cat") == "user_annotation"
                     and not str(e.get("name", "")).startswith(WINDOW_PREFIX)], lambda e: str(e["name"]))
    if steps:
        lines.append(f"steps' host time (ms a {per.unit}): " + ", ".join(
            f"{k} {per(t):.2f}" for k, (_, t) in sorted(steps.items(), key=lambda kv: -kv[1][1])))
    ops = defaultdict(lambda: [0, 0.0])
    for op, own in _self_times([e for e in complete if e.get("cat") == "cpu_op"]):
        ops[op][0] += 1
        ops[op][1] += own
    if ops:
        lines.append(f"costliest host operations, by their own time (ms a {per.unit}, calls a {per.unit}):")
        lines += _ranked(ops, per, top)
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Read a saved profiler trace into its summary.")
    parser.add_argument("trace", help="a .trace.json.gz from profiled(...).save, or any Chrome trace")
    parser.add_argument("--units", type=int, help="frames (steps, views) in the trace (default: as saved)")
    parser.add_argument("--unit", help="what a unit is called (default: as saved)")
    parser.add_argument("--top", type=int, default=8, help="kernels and host operations listed")
    args = parser.parse_args(argv)
    trace = load_trace(args.trace)
    print(summarize(trace.events, args.units or trace.units, args.unit or trace.unit, trace.name, args.top))


if __name__ == "__main__":
    main()
