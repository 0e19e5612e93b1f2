"""One place that chooses the compute device for Warp and torch."""

from __future__ import annotations

import os
from contextlib import AbstractContextManager, nullcontext

ENV_VAR = "DEEP_SSFR_DEVICE"


def choose_device(requested: str = "auto") -> str:
    """Return ``"cuda"`` or ``"cpu"``.

    Precedence: the ``DEEP_SSFR_DEVICE`` environment variable, then ``requested`` from the config;
    ``"auto"`` picks CUDA only when both Warp and torch can use it, so the two libraries always
    share a device.
    """
    choice = os.environ.get(ENV_VAR, requested) or "auto"
    if choice not in ("auto", "cpu", "cuda"):
        raise ValueError(f"{ENV_VAR} must be auto, cpu or cuda, got {choice!r}")
    if choice == "cpu":
        return "cpu"
    cuda_ok = cuda_available()
    if choice == "cuda" and not cuda_ok:
        raise RuntimeError("device 'cuda' requested but Warp and torch do not both see a CUDA GPU")
    return "cuda" if cuda_ok else "cpu"


def cuda_available() -> bool:
    """Whether both Warp and torch can use a CUDA GPU."""
    try:
        import torch
        import warp as wp

        wp.init()
        return bool(torch.cuda.is_available() and wp.is_cuda_available())
    except Exception:
        return False


def native_bfloat16(device: str) -> bool:
    """Whether ``device`` multiplies bfloat16 natively: a CUDA GPU with bf16, a CPU with AVX512-BF16
    or AMX (where oneDNN's bf16 convolutions beat float32; elsewhere bf16 is emulated, and slower)."""
    import torch

    if str(device).startswith("cuda"):
        return torch.cuda.is_bf16_supported()
    return bool(getattr(torch.cpu, "_is_avx512_bf16_supported", bool)()
                or getattr(torch.cpu, "_is_amx_tile_supported", bool)())


def warp_device(device: str) -> str:
    """Warp's name for the device."""
    return "cuda:0" if device == "cuda" else "cpu"


def torch_waits_for_warp(device: str) -> None:
    """Order torch's current stream on ``device`` after the work Warp has queued there, so torch
    reads what Warp wrote (each library has its own CUDA stream; nothing to do on the CPU, where
    both run in call order)."""
    if str(device).startswith("cuda"):
        import warp as wp

        wp.stream_from_torch(device).wait_stream(wp.get_stream(device))


def warp_waits_for_torch(device: str) -> None:
    """Order Warp's stream on ``device`` after the work torch has queued there (the other way)."""
    if str(device).startswith("cuda"):
        import warp as wp

        wp.get_stream(device).wait_stream(wp.stream_from_torch(device))


def on_torch_stream(device) -> AbstractContextManager:
    """A ``with`` block in which Warp launches go on torch's current stream of ``device`` (a torch
    device), so Warp kernels on torch's tensors are ordered with torch's own work without waits
    between the streams (nothing to do on the CPU)."""
    import torch
    import warp as wp

    device = torch.device(device)
    if device.type != "cuda":
        return nullcontext()
    return wp.ScopedStream(wp.stream_from_torch(device))


def host_view(host, dtype):
    """A host array's pixels as a flat CPU Warp array of ``dtype`` (a scalar or a vector type), no copy:
    where a kernel on the CPU writes, or where a copy from a GPU lands."""
    import warp as wp

    length = wp.types.type_size(dtype)
    flat = host.reshape(-1) if length == 1 else host.reshape(-1, length)
    return wp.array(flat, dtype=dtype, device="cpu", copy=False)


def download(a, shape: tuple[int, ...], wait: bool = True):
    """A GPU array of float pixels (``float`` or a float vector type) in a new page-locked host array
    of ``shape`` (``vectors.host_empty``): one copy at the bus's speed. ``wait``: return once it has
    landed; without, the copy is only queued and the caller calls ``wait_for_downloads`` before the
    host reads it (several downloads then cost one wait)."""
    import warp as wp

    from pipeline.vectors import host_empty

    out = host_empty(shape, pinned=True)
    wp.copy(host_view(out, a.dtype), a)
    if wait:
        wait_for_downloads(a.device)
    return out


def wait_for_downloads(device) -> None:
    """Return once the copies queued on Warp's stream of ``device`` have landed in host memory. A
    copy into page-locked memory returns as soon as it is queued (into pageable memory only when it
    is done), so the host must wait before it reads one; nothing to do on the CPU."""
    import warp as wp

    device = wp.get_device(device)
    if device.is_cuda:
        wp.synchronize_stream(wp.get_stream(device))
