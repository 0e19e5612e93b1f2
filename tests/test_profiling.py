"""The profiler's reading of a trace: the device's busy share, the host's waits, the copies, and
the device time each step queued, on a made-up GPU trace whose figures are known; and a real
recording on the CPU with the stage timers' steps as named ranges."""

from __future__ import annotations

import re
from concurrent.futures import ThreadPoolExecutor

import pytest
import torch
import warp as wp

from pipeline import profiling
from pipeline.profiling import load_trace, merged_spans, profiled, summarize
from pipeline.timing import Timings


@wp.kernel
def double_values(values: wp.array(dtype=float)):
    i = wp.tid()
    values[i] = 2.0 * values[i] + 1.0


def test_the_union_counts_overlaps_once_and_clips_to_the_window():
    assert merged_spans([]) == []
    assert merged_spans([(20, 30), (0, 10), (5, 15)]) == [(0, 15), (20, 30)]
    assert merged_spans([(0, 10), (2, 3), (4, 5)]) == [(0, 10)]  # nested spans add nothing
    assert merged_spans([(0, 10), (20, 30)], lo=5, hi=25) == [(5, 10), (20, 25)]
    assert merged_spans([(0, 1), (1, 2), (3, 3)]) == [(0, 2)]  # touching spans join, empty ones drop


def _x(cat, name, ts, dur, tid=1, **args):
    return {"ph": "X", "cat": cat, "name": name, "pid": 1, "tid": tid, "ts": ts, "dur": dur, "args": args}


def _gpu_trace() -> list[dict]:
    """Two frames in a 10 ms window. Host: 'refine' holds 'network' (nested) and launches kernel 1
    inside 'network' and kernel 2 inside 'refine' only; 'shading' launches Warp's kernel 3 through
    the driver; a download and two waits. Device: kernels 1 and 2 overlap on two streams."""
    return [
        {"ph": "M", "name": "process_name", "pid": 1, "args": {"name": "python"}},
        _x("user_annotation", profiling.WINDOW_PREFIX + "render", 0, 10_000),
        _x("user_annotation", "refine", 100, 3000),
        _x("user_annotation", "network", 200, 1000),
        _x("cuda_runtime", "cudaLaunchKernel", 300, 5, correlation=1),
        _x("cuda_runtime", "cudaLaunchKernel", 2000, 5, correlation=2),
        _x("user_annotation", "shading", 4000, 2000),
        _x("cuda_driver", "cuLaunchKernel", 4100, 5, correlation=3),
        _x("cuda_driver", "cuMemcpyDtoHAsync_v2", 4200, 5, correlation=4),
        _x("cuda_driver", "cuStreamSynchronize", 4300, 1500),
        _x("cuda_runtime", "cudaStreamSynchronize", 7000, 500),
        _x("cuda_runtime", "cudaMemcpyAsync", 7600, 5, correlation=5),
        _x("cpu_op", "aten::conv2d", 250, 600),
        _x("kernel", "conv_kernel", 400, 2000, tid=7, correlation=1),
        _x("kernel", "add_kernel", 1400, 2000, tid=8, correlation=2),   # overlaps the conv by 1 ms
        _x("kernel", "shade_kernel", 4500, 1000, tid=7, correlation=3),
        _x("gpu_memcpy", "Memcpy DtoH (Device -> Pinned)", 5600, 400, tid=7, correlation=4, bytes=60_000_000),
        _x("gpu_memcpy", "Memcpy HtoD (Pageable -> Device)", 7700, 100, tid=7, correlation=5, bytes=2_000_000),
        _x("gpu_memset", "Memset (Device)", 7900, 100, tid=7),
        _x("kernel", "late_kernel", 9_900, 500, tid=7),   # runs past the window: 100 us of it count
    ]


def _figure(text: str, pattern: str) -> list[float]:
    found = re.search(pattern, text)
    assert found, f"{pattern!r} not in:\n{text}"
    return [float(g) for g in found.groups()]


def test_a_gpu_trace_reads_into_its_known_figures():
    text = summarize(_gpu_trace(), units=2, name="render")
    assert text.startswith("render: 2 frames in 10.0 ms (5.00 ms a frame)")
    # busy: kernels 400-3400 (two overlapping), 4500-5500, copy 5600-6000, 7700-7800, fill 7900-8000,
    # the late kernel's 100 us inside the window: 3000 + 1000 + 400 + 100 + 100 + 100 = 4700 us
    busy, share, kernels, copies, fills = _figure(
        text, r"device busy ([\d.]+) ms a frame \((\d+)% of the window\): kernels ([\d.]+), copies ([\d.]+), "
              r"fills ([\d.]+) ms")
    assert (busy, share) == (2.35, 47)
    assert (kernels, copies, fills) == (2.75, 0.25, 0.05)  # summed per kind, overlaps and all
    # idle: 0-400, 3400-4500, 5500-5600, 6000-7700, 7800-7900, 8000-9900 (with the busy time, the window)
    assert "device idle in 3.0 gaps of 0.1 ms or more a frame, 2.65 ms; the longest 1.90 ms at +8.0, " \
           "1.70 ms at +6.0, 1.10 ms at +3.4" in text
    waits, wait_ms, launches = _figure(text, r"host waits for the device: ([\d.]+) a frame, ([\d.]+) ms.*; "
                                             r"([\d.]+) kernel launches a frame")
    assert (waits, wait_ms, launches) == (1.0, 1.0, 1.5)  # the async copies are not counted as waits
    assert "cuStreamSynchronize 0.5" in text and "cudaStreamSynchronize 0.5" in text
    assert _figure(text, r"DtoH 0.5 x, ([\d.]+) MB in ([\d.]+) ms \(([\d.]+) GB/s\)") == [30.0, 0.2, 150.0]
    assert _figure(text, r"HtoD 0.5 x, ([\d.]+) MB") == [1.0]
    # kernel 1 was queued inside 'network' (the innermost range), kernel 2 inside 'refine' alone
    by_step = dict(re.findall(r"(\S+) ([\d.]+)", text.split("device time by the step that queued it (ms a frame): ")[1]
                                                      .splitlines()[0]))
    assert by_step == {"network": "1.00", "refine": "1.00", "shading": "0.70", "step)": "0.35"}
    assert text.index("conv_kernel") < text.index("shade_kernel") < text.index("late_kernel")
    assert "steps' host time (ms a frame): refine 1.50, shading 1.00, network 0.50" in text
    assert "aten::conv2d" in text


def test_a_trace_without_device_events_gives_the_hosts_figures():
    events = [e for e in _gpu_trace() if e.get("cat") in ("user_annotation", "cpu_op")]
    text = summarize(events, units=1, unit="view", name="dataset")
    assert "no device activity" in text and "device busy" not in text
    assert "steps' host time (ms a view): refine 3.00" in text


def test_a_recording_on_the_cpu_names_the_stage_timers_steps(tmp_path, capsys):
    """Steps timed with ``Timings`` inside ``profiled`` are named ranges of the trace; the trace
    and its summary are saved and read back the same."""
    t = Timings()
    x = torch.randn(64, 64)

    def write() -> None:  # a stage's writer or worker thread
        with t("write"):
            x.sum()

    with ThreadPoolExecutor(1) as pool, profiled("loop", units=3) as trace:
        for _ in range(3):
            with t("multiply"):
                y = x @ x
            with t("add"):
                y = y + 1.0
            pool.submit(write).result()
    assert trace.events, "the profiler recorded nothing"
    text = trace.summary()
    assert text.startswith("loop: 3 frames in ")
    steps = text.split("steps' host time (ms a frame): ")[1].splitlines()[0]
    assert "multiply" in steps and "add" in steps and "write" in steps
    assert "aten::mm" in text
    report = trace.report(tmp_path, "3 loops")
    gz, txt = tmp_path / "loop.trace.json.gz", tmp_path / "loop.txt"
    assert report == f"recorded with the profiler (3 loops):\n{text}\nsaved: {gz}, {txt}"
    assert txt.read_text().strip() == text
    again = load_trace(gz)
    assert (again.name, again.units, again.unit) == ("loop", 3, "frame")
    assert again.summary() == text
    profiling.main([str(gz), "--units", "1"])
    assert capsys.readouterr().out.startswith("loop: 1 frame in ")


def test_timers_outside_a_recording_add_no_ranges():
    t = Timings()
    with profiled("off", enabled=False) as trace:
        with t("step"):
            pass
    assert trace.events == [] and t.count["step"] == 1


def test_an_unreadable_trace_names_its_file(tmp_path):
    bad = tmp_path / "broken.trace.json.gz"
    bad.write_bytes(b"not gzip")
    with pytest.raises(ValueError, match="broken.trace.json.gz"):
        load_trace(bad)


def test_idle_gaps_are_what_the_busy_spans_leave_of_the_window():
    busy = profiling.merged_spans([(2, 4), (3, 6), (8, 9)], lo=0, hi=10)
    assert busy == [(2, 6), (8, 9)]
    assert profiling.idle_gaps(busy, 0, 10) == [(0, 2), (6, 2), (9, 1)]
    assert profiling.idle_gaps([], 0, 10) == [(0, 10)]
    assert profiling.idle_gaps([(0, 10)], 0, 10) == []


def test_host_operations_are_ranked_by_their_own_time():
    """A convolution's layers of dispatch each count only the time outside the layer they call."""
    events = [_x("cpu_op", "aten::conv2d", 0, 100), _x("cpu_op", "aten::convolution", 10, 75),
              _x("cpu_op", "aten::mkldnn_convolution", 20, 60), _x("cpu_op", "aten::add", 100, 10),
              _x("cpu_op", "aten::add", 30, 40, tid=2)]  # another thread: no one's child
    own = sorted(profiling._self_times(events))
    assert own == [("aten::add", 10.0), ("aten::add", 40.0), ("aten::conv2d", 25.0), ("aten::convolution", 15.0),
                   ("aten::mkldnn_convolution", 60.0)]
    text = summarize(events, units=1)
    ranked = [line.split()[-1] for line in text.split("by their own time")[1].splitlines()[1:]]
    assert ranked == ["aten::mkldnn_convolution", "aten::add", "aten::conv2d", "aten::convolution"]


@pytest.mark.cuda
def test_a_gpu_recording_holds_warps_kernels_torchs_and_the_hosts_waits():
    """On a GPU the trace holds Warp's kernels (launched through the driver) beside torch's, each
    credited to the step that queued it, the downloads and the host's waits for them: what the
    GPU check's traces are read for."""
    t = Timings()
    values = wp.zeros(1 << 22, dtype=float, device="cuda:0")
    x = torch.randn(1024, 1024, device="cuda")
    wp.launch(double_values, values.shape, [values], device="cuda:0")  # loaded before the window
    with profiled("gpu", units=2) as trace:
        for _ in range(2):
            with t("warp"):
                wp.launch(double_values, values.shape, [values], device="cuda:0")
            with t("torch"):
                y = x @ x
            with t("download"):
                values.numpy()
                y.cpu()
    text = trace.summary()
    assert "device busy" in text, text
    kernels = text.split("costliest kernels")[1].split("steps' host time")[0]
    assert "double_values" in kernels, text
    by_step = dict(re.findall(r"(\S+) ([\d.]+)", text.split("device time by the step that queued it (ms a frame): ")[1]
                                                  .splitlines()[0]))
    assert float(by_step.get("warp", 0)) > 0 and float(by_step.get("torch", 0)) > 0, text
    copies, megabytes = map(float, re.search(r"DtoH ([\d.]+) x, ([\d.]+) MB", text).groups())
    assert copies >= 2 and abs(megabytes - 21.0) < 0.2, text  # a frame: 16.8 MB of Warp's floats, 4.2 of torch's
    waits = float(re.search(r"host waits for the device: ([\d.]+) a frame", text).group(1))
    assert waits >= 1, text
