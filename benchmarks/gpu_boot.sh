#!/usr/bin/env bash
# On the GPU machine (the `device` tool), from the repo root, with the pieces that
# benchmarks/gpu_stage.sh made here travelling one a call (carry [".gpu/pK"]):
#   bash benchmarks/gpu_boot.sh park     keeps this call's piece in /tmp/gpu (it stays while warm)
#   source benchmarks/gpu_boot.sh        keeps this call's piece too; once every piece is there,
#                                        checks them, unpacks Python 3.12's Warp, Taichi, OpenEXR,
#                                        trimesh, pydantic and meshio into /tmp/gpu/site (once), and
#                                        exports PYTHONPATH, DEEP_SSFR_DEVICE=cuda, PYTHONUNBUFFERED
G=${GPU_BOOT_DIR:-/tmp/gpu}  # where the pieces and the unpacked site stay while the machine is warm
mkdir -p "$G/pieces"
for d in .gpu/p*; do
    [ -d "$d" ] && cp "$d"/piece_* "$d"/SHA256SUMS "$G/pieces/"
done
if [ "${1:-}" = park ]; then
    echo "gpu_boot: kept $(ls "$G/pieces" | grep -c '^piece_') piece(s) in $G/pieces"
    exit 0
fi
if [ ! -f "$G/site/warp/bin/warp.so" ]; then
    want=$(grep -c ' piece_' "$G/pieces/SHA256SUMS" 2>/dev/null || echo 0)
    have=$(ls "$G/pieces" | grep -c '^piece_')
    if [ "$want" = 0 ] || [ "$have" != "$want" ]; then
        echo "gpu_boot: $have of $want pieces are here: the machine went cold or a call was missed; park them again" >&2
        return 1 2>/dev/null || exit 1
    fi
    (cd "$G/pieces" && sha256sum --quiet -c SHA256SUMS) || { echo "gpu_boot: a piece is damaged" >&2; return 1 2>/dev/null || exit 1; }
    mkdir -p "$G/site.tmp" && for k in $(seq 1 "$want"); do cat "$G/pieces/piece_$k"; done | xz -d | tar -C "$G/site.tmp" -xf - &&
        mv "$G/site.tmp" "$G/site" || { echo "gpu_boot: unpacking failed" >&2; return 1 2>/dev/null || exit 1; }
    echo "gpu_boot: unpacked $want pieces into $G/site"
fi
export PYTHONPATH=$G/site:$(pwd)${PYTHONPATH:+:$PYTHONPATH} DEEP_SSFR_DEVICE=cuda PYTHONUNBUFFERED=1
