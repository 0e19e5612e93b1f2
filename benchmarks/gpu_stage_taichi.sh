#!/usr/bin/env bash
# Stages Taichi 1.7.4 for the GPU machine's side-by-side step (benchmarks/gpu_check.sh taichi) into
# .gpu/t: its cp312 wheel and the pure-Python wheels it imports (the GPU image has numpy only). It
# travels in a call of its own: with the second half of Warp's wheel it would pass the 64 MiB a
# device call may carry. From the project root, after ../shared/gpu/stage.sh:
#     bash benchmarks/gpu_stage_taichi.sh
set -euo pipefail
T=.gpu/t
grep -qx '/.gpu/' .git/info/exclude 2>/dev/null || echo '/.gpu/' >> .git/info/exclude
rm -rf "$T" && mkdir -p "$T"
PLAT="--platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64"
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp $PLAT -d "$T" \
    taichi==1.7.4 colorama dill rich markdown-it-py mdurl pygments 2>&1 | grep -v '^WARNING' || true
ls "$T"/taichi-1.7.4-*.whl >/dev/null
du -sh "$T"
echo "staged Taichi in $T: carry it alone in a third call (benchmarks/gpu_check.sh says how)"
