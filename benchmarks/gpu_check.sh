#!/usr/bin/env bash
# Issue 13's GPU measurements on the GPU machine (the `device` tool), about 10.5 minutes in all:
# the cuda-marked tests, the simulator against its own stage at 50k particles, the dataset and
# render benchmarks on CUDA, the dataset stage's views/s at 512, the render stage's frames/s at
# 1024, and Taichi side by side on the same GPU when its wheel came along.
# Each step writes its log and prints its exit status and last line, so one failing step costs
# only itself. The stage benchmarks also record a short run with torch's profiler
# (pipeline/profiling.py): the trace and its summary (the device's busy share and idle gaps, the
# host's waits, the copies, device time by step, the costliest kernels), for reading where the time
# went once the machine is gone. The device tool brings back at most 8 files, so after every step
# the logs and traces are packed into OUT/gpu_check.tgz, and the step lines go to OUT/summary.txt
# (`tar xzf gpu_check.tgz` gives <step>.txt and traces/; `python -m pipeline.profiling
# traces/render_stage.trace.json.gz` reads a trace again).
# Stage what the machine lacks first (`bash benchmarks/gpu_stage.sh`: Warp, Taichi and the wheels
# its image lacks, packed into pieces that travel one a call) and make the calls it prints; from
# the repo root there:
#
#     bash benchmarks/gpu_check.sh                    # every step (about 10.5 minutes: more than a
#                                                     # call may take); OUT defaults to $OUT (the
#                                                     # device tool's) or /tmp/gpu_check
#     bash benchmarks/gpu_check.sh taichi render ...  # only the steps named, in the script's order: gpu
#                                                     # cuda_tests sim sim_stage render_stage
#                                                     # dataset_stage taichi render dataset
#
# GPU_CHECK_DEVICE=cpu runs the same steps on the CPU (a dry run of the script; minutes longer).
#
# On the lent machine the issue's figures are one call, at most 8.5 minutes (gpu cuda_tests sim
# sim_stage render_stage dataset_stage taichi), and the two per-part breakdowns a second (render
# dataset, at most 2.2 minutes), so a lease cut short by the machine's start loses the breakdowns
# first. The nccl path of `make train-ddp` needs one GPU per process, so a one-GPU machine cannot
# run it (a world of one process makes no process group).
set -uo pipefail
OUT=${OUT:-/tmp/gpu_check}
WORK=${GPU_CHECK_WORK:-/tmp/gpu_check_work}  # the logs and traces, packed into OUT after each step
PY=${PYTHON:-python3}
DEVICE=${GPU_CHECK_DEVICE:-cuda}
mkdir -p "$OUT" "$WORK/traces"
export DEEP_SSFR_DEVICE=$DEVICE PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}

ONLY=" $* "
step() {  # step NAME SECONDS COMMAND...: run with a time limit, keep its output (only those named, if any)
    local name=$1 limit=$2
    shift 2
    [ "$ONLY" = "  " ] || [[ "$ONLY" == *" $name "* ]] || return 0
    local start=$SECONDS
    timeout "$limit" "$@" >"$WORK/$name.txt" 2>&1
    local rc=$?
    printf '%-18s exit %3d  %4d s  %s\n' "$name" "$rc" $((SECONDS - start)) "$(tail -n 1 "$WORK/$name.txt" | tr "\r" "\n" | tail -n 1)" \
        | tee -a "$OUT/summary.txt"
    tar -czf "$OUT/.gpu_check.tgz.tmp" -C "$WORK" . && mv "$OUT/.gpu_check.tgz.tmp" "$OUT/gpu_check.tgz"
}
TRACES=$WORK/traces

# the limits add up to under the device tool's 10 minutes a command; the cuda tests come first, so
# their compilation of every kernel module for the GPU is cached for the later steps, then the
# issue's figures (the stages' rates), then the per-part breakdowns: a lease that ends early (the
# device time is shared with the machine's start) loses the breakdowns first
step gpu 10 nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
step cuda_tests 120 "$PY" -m pytest -q -m cuda -p no:cacheprovider tests
step sim 45 "$PY" benchmarks/bench_sim.py --device "$DEVICE" --particles 50000 --steps 400
step sim_stage 85 "$PY" benchmarks/bench_sim_stage.py --particle-radius 0.00888 --trace "$TRACES"
step render_stage 60 "$PY" benchmarks/bench_render_stage.py --device "$DEVICE" --size 1024 --frames 30 \
    --trace "$TRACES"
step dataset_stage 70 "$PY" benchmarks/bench_dataset_stage.py --size 512 --frames 16 --trace "$TRACES"
if "$PY" -c "import taichi" 2>/dev/null; then
    step taichi 120 "$PY" benchmarks/bench_sim.py --peers --device "$DEVICE" --particles 50000 --steps 400 --repeat 2
elif [ "$ONLY" = "  " ] || [[ "$ONLY" == *" taichi "* ]]; then
    echo "taichi             skipped: no taichi here (benchmarks/gpu_stage.sh packs it with Warp)"
fi
# bench_render's per-stage columns with every step waiting for the GPU (DEEP_SSFR_SYNC_TIMINGS), so
# each holds its own work; bench_render_stage's frames/s keep the overlap
step render 60 env DEEP_SSFR_SYNC_TIMINGS=1 "$PY" benchmarks/bench_render.py --device "$DEVICE" --sizes 1024 --splat ellipsoid --repeat 10
step dataset 70 "$PY" benchmarks/bench_dataset.py --device "$DEVICE"
echo "outputs in $OUT (summary.txt; gpu_check.tgz: the logs and traces)"
