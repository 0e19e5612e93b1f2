#!/usr/bin/env bash
# Stages what the GPU machine (the `device` tool) lacks for benchmarks/gpu_check.sh, into the
# ignored folder .gpu/ (about 3 minutes here). Its image has torch, numpy, scipy, scikit-image,
# pyyaml, tqdm, matplotlib, filelock, typer, imageio and pytest for Python 3.12, and reaches no
# registry. The rest is installed here for that Python into one folder (Warp; OpenEXR, trimesh,
# pydantic with its three companions and meshio at this checkout's .venv versions; Taichi 1.7.4
# and dill for the side-by-side), packed as one xz stream and cut into pieces .gpu/p1 ... .gpu/pN:
# a device call carries at most 64 MiB, the working tree included (22.5 MB of it on 2026-12-02,
# the shipped weights mostly), so a piece is what the tree leaves free, less a margin.
# imageio-ffmpeg's wheel (68 MB) is not worth a call: nothing run there writes a video.
#
# The calls, each within 30 s of the last (the machine stays warm that long; /tmp stays with it),
# printed at the end with N filled in (4 on 2026-12-02: 144 MB in pieces of 42.5 MB):
#   1 .. N-1  `bash benchmarks/gpu_boot.sh park`, carry [".gpu/pK"], timeout_s 60: seconds each
#   N         `source benchmarks/gpu_boot.sh && bash benchmarks/gpu_check.sh $FIGURES`, carry
#             [".gpu/pN"], timeout_s 590: the issue's figures, at most 8.5 minutes
#   N + 1     `source benchmarks/gpu_boot.sh && bash benchmarks/gpu_check.sh render dataset`, no
#             carry, timeout_s 180: the per-part breakdowns, at most 2.2 minutes
# with FIGURES = gpu cuda_tests sim sim_stage render_stage dataset_stage taichi. With the machine's
# start (a minute or more) that is about 13 of a lease's 15 minutes. Each gpu_check call's OUT brings
# back summary.txt and gpu_check.tgz (the logs and profiler traces so far). A call refused for its
# size ("larger than 64 MiB") means the tree grew since staging: stage again.
# From the project root, after `make setup`:  bash benchmarks/gpu_stage.sh
set -euo pipefail
PY=${PYTHON:-.venv/bin/python}
G=.gpu
LIMIT=67108864       # 64 MiB a call
MARGIN=2097152       # for the files a session adds before its calls
grep -qx '/.gpu/' .git/info/exclude 2>/dev/null || echo '/.gpu/' >> .git/info/exclude
PINS=$("$PY" - <<'PY'
import re
from importlib.metadata import version
from pathlib import Path
names = ["pydantic", "pydantic-core", "annotated-types", "typing-inspection", "typing-extensions", "meshio",
         "OpenEXR", "trimesh"]
warp = re.search(r'"(warp-lang[^"]*)"', Path("pyproject.toml").read_text())
print(" ".join([f"{n}=={version(n)}" for n in names] + [warp.group(1) if warp else "warp-lang", "taichi==1.7.4",
                                                        "dill"]))
PY
)
tree=$( { git ls-files -z; git ls-files -z --others --exclude-standard; } | xargs -0 -r stat -c %s -- 2>/dev/null \
        | awk '{s += $1} END {print s + 0}')
piece=$(( LIMIT - tree - MARGIN ))
[ "$piece" -gt 8388608 ] || { echo "gpu_stage: the working tree ($tree bytes) leaves no room to carry" >&2; exit 1; }
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
PLAT=""
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 \
         manylinux_2_34_x86_64 manylinux_2_31_x86_64 manylinux1_x86_64; do PLAT="$PLAT --platform $p"; done
# shellcheck disable=SC2086
"$PY" -m pip install -q --no-deps --no-compile --only-binary=:all: --python-version 3.12 --implementation cp $PLAT \
    --target "$tmp/site" $PINS 2>&1 | grep -v '^WARNING' || true
for m in warp taichi OpenEXR trimesh pydantic pydantic_core meshio dill; do
    [ -e "$tmp/site/$m" ] || ls "$tmp/site/$m"* >/dev/null 2>&1 || { echo "gpu_stage: $m did not install" >&2; exit 1; }
done
rm -rf "$tmp/site/warp/examples" "$tmp/site/warp/tests" "$tmp/site/bin"
tar -C "$tmp/site" -cf - . | xz -T0 -6 > "$tmp/bundle.tar.xz"
rm -rf "$G" && mkdir -p "$G"
split -b "$piece" -d -a 1 "$tmp/bundle.tar.xz" "$tmp/piece_"
count=$(ls "$tmp"/piece_* | wc -l)
k=0
for f in "$tmp"/piece_*; do
    k=$((k + 1))
    mkdir -p "$G/p$k"
    mv "$f" "$G/p$k/piece_$k"
done
(cd "$G" && sha256sum p*/piece_* | sed 's#p[0-9]*/##') > "$tmp/SHA256SUMS"
for k in $(seq 1 "$count"); do cp "$tmp/SHA256SUMS" "$G/p$k/"; done
echo "tree $tree bytes; bundle $(stat -c %s "$tmp/bundle.tar.xz") bytes in $count pieces of at most $piece"
du -b -s "$G"/p*
FIGURES="gpu cuda_tests sim sim_stage render_stage dataset_stage taichi"
echo "the calls, each within 30 s of the last:"
for k in $(seq 1 $((count - 1))); do
    echo "  $k. command: bash benchmarks/gpu_boot.sh park    carry: [\".gpu/p$k\"]  timeout_s: 60"
done
echo "  $count. command: source benchmarks/gpu_boot.sh && bash benchmarks/gpu_check.sh $FIGURES    carry: [\".gpu/p$count\"]  timeout_s: 590"
echo "  $((count + 1)). command: source benchmarks/gpu_boot.sh && bash benchmarks/gpu_check.sh render dataset    no carry  timeout_s: 180"
