"""Every Warp kernel module also builds for CUDA, checked here without a GPU: Warp's bundled NVRTC
compiles each module to PTX for the H100's architecture (sm_90). A module is built whole on a GPU,
so one CPU-only construct (a GCC builtin, inline assembly) would stop every kernel in it there."""

from __future__ import annotations

import importlib

import pytest
import warp as wp

MODULES = ["pipeline.sim.kernels", "pipeline.sim.native", "pipeline.screen.kernels", "pipeline.screen.filters",
           "pipeline.screen.native", "pipeline.surface.kernels", "pipeline.surface.native",
           "pipeline.shading.kernels", "pipeline.metaball.kernels"]


def _sm90_compiler() -> bool:
    """Whether this Warp build carries NVRTC with the H100's architecture (no driver needed)."""
    wp.init()
    return 90 in (getattr(wp._src.context.runtime, "nvrtc_supported_archs", None) or ())


@pytest.mark.parametrize("name", MODULES)
def test_the_kernel_module_builds_for_cuda(name, tmp_path):
    if not _sm90_compiler():
        pytest.skip("this Warp build cannot compile CUDA code for sm_90")
    built = wp.compile_aot_module(importlib.import_module(name), arch=90, module_dir=tmp_path, use_ptx=True)
    assert built and all(path.suffix == ".ptx" and path.stat().st_size > 0 for path in built)
