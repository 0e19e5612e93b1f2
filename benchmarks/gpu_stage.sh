#!/usr/bin/env bash
# Stages everything the GPU machine (the `device` tool) needs to run benchmarks/gpu_check.sh, into
# the ignored folder .gpu/ (about 3 minutes). Its image has torch, numpy, scipy, scikit-image,
# pyyaml, tqdm, matplotlib, filelock, typer, imageio and pytest, and reaches no registry; the rest
# travels as wheels:
#   .gpu/a, .gpu/b   Warp's native libraries in two halves (../shared/gpu/stage.sh)
#   .gpu/py          Warp's Python files, boot.sh, and the wheels the image lacks: OpenEXR and trimesh
#                    (the shared script's own), pydantic with its three companions and meshio (which
#                    two test modules import), at the versions this checkout's .venv has
#   .gpu/t           Taichi 1.7.4 and dill, for the side-by-side step alone: with .gpu/b they would
#                    pass the 64 MiB a device call may carry
# imageio-ffmpeg's wheel (68 MB) cannot travel at all, so nothing run there writes a video.
# The calls, while the machine stays warm (30 s after each):
#   1. `bash .gpu/a/boot.sh keep`                                   carry [".gpu/a"]
#   2. `source .gpu/py/boot.sh && bash benchmarks/gpu_check.sh gpu cuda_tests sim sim_stage render_stage
#      dataset_stage`                                               carry [".gpu/b", ".gpu/py"]
#   3. `export PYTHONPATH=/tmp/gpu/site:$PWD DEEP_SSFR_DEVICE=cuda && bash benchmarks/gpu_check.sh taichi
#      render dataset`                                              carry [".gpu/t"]
# Each call's OUT brings back summary.txt and gpu_check.tgz (the logs and profiler traces so far).
# From the project root, after `make setup`:  bash benchmarks/gpu_stage.sh
set -euo pipefail
PY=${PYTHON:-.venv/bin/python}
PINS=$("$PY" - <<'PY'
from importlib.metadata import version
names = ["pydantic", "pydantic-core", "annotated-types", "typing-inspection", "typing-extensions", "meshio"]
print(" ".join(f"{n}=={version(n)}" for n in names))
PY
)
GPU_EXTRA_WHEELS="$PINS" bash ../shared/gpu/stage.sh
T=.gpu/t
mkdir -p "$T"
PLAT="--platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64"
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp $PLAT -d "$T" \
    taichi==1.7.4 dill 2>&1 | grep -v '^WARNING' || true
ls "$T"/taichi-1.7.4-*.whl >/dev/null
du -sh .gpu/a .gpu/b .gpu/py "$T"
echo "staged: the three calls are in this script's header"
