#!/usr/bin/env bash
# Our CPU ray caster and VTK's vtkFixedPointVolumeRayCastMapper, side by side in one run:
# the same volume, image size, transfer function, sample distance, thread count and camera
# path (bench/vtk_raycast_reference.cpp). Rounds alternate ours / VTK so that load on a
# shared machine hits both alike; each tool's figure is the median of its round medians.
# Prints one JSON object: per size both medians and the ratio VTK / ours.
#
# Usage: bench/render_vs_vtk.sh            (after: bash scripts/build.sh release)
# Environment (defaults): BUILD_DIR=build  SIZES="375x250 1280x800"  FRAMES=30 WARMUP=5
#   ROUNDS=3  THREADS=$(nproc)  SAMPLE_MM=1.0  TF=skin  VOLUME=data/t1_head_mne_ecog.nii.gz
#   MASK=  GPU=0 (1: also our GL ray caster and VTK's GPU mapper, both on Mesa llvmpipe with
#   LP_NUM_THREADS=THREADS, ratio VTK GPU / ours GL: issue 3)  FRAMES_DIR= (save one PNG each)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
BUILD_DIR=${BUILD_DIR:-build}
[[ $BUILD_DIR = /* ]] || BUILD_DIR=$root/$BUILD_DIR
SIZES=${SIZES:-375x250 1280x800}
FRAMES=${FRAMES:-30}
WARMUP=${WARMUP:-5}
ROUNDS=${ROUNDS:-3}
THREADS=${THREADS:-$(nproc)}
SAMPLE_MM=${SAMPLE_MM:-1.0}
TF=${TF:-skin}
VOLUME=${VOLUME:-$root/data/t1_head_mne_ecog.nii.gz}
MASK=${MASK:-}
GPU=${GPU:-0}
FRAMES_DIR=${FRAMES_DIR:-}

ours=$BUILD_DIR/cli/cortexfuse
vtk=$BUILD_DIR/bench/vtk_raycast_reference
for exe in "$ours" "$vtk"; do
  [ -x "$exe" ] || { echo "render_vs_vtk: $exe is missing: build first (bash scripts/build.sh release) or set BUILD_DIR" >&2; exit 1; }
done
command -v jq >/dev/null || { echo "render_vs_vtk: jq is missing (bash scripts/setup.sh)" >&2; exit 1; }
command -v xvfb-run >/dev/null || { echo "render_vs_vtk: xvfb-run is missing (bash scripts/setup.sh)" >&2; exit 1; }
[ -n "$FRAMES_DIR" ] && mkdir -p "$FRAMES_DIR"

common=(--volume "$VOLUME" --tf "$TF" --frames "$FRAMES" --warmup "$WARMUP" --threads "$THREADS" --sample-mm "$SAMPLE_MM" --json)
[ -n "$MASK" ] && common+=(--mask "$MASK")
# Debian's VTK renders through X only.
xvfb() { xvfb-run -a -s "-screen 0 1920x1080x24" "$@"; }

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
for size in $SIZES; do
  for ((r = 0; r < ROUNDS; r++)); do
    save_ours=() save_vtk=() save_gpu=() save_gl=()
    if [ -n "$FRAMES_DIR" ] && [ "$r" = 0 ]; then
      save_ours=(--save-frame "$FRAMES_DIR/ours_$size.png")
      save_vtk=(--save-frame "$FRAMES_DIR/vtk_fixedpoint_$size.png")
      save_gpu=(--save-frame "$FRAMES_DIR/vtk_gpu_$size.png")
      save_gl=(--save-frame "$FRAMES_DIR/ours_gl_$size.png")
    fi
    "$ours" bench render --renderer cpu --size "$size" "${common[@]}" "${save_ours[@]}" >>"$tmp/ours_$size.jsonl"
    xvfb "$vtk" --mapper fixedpoint --size "$size" "${common[@]}" "${save_vtk[@]}" >>"$tmp/vtk_$size.jsonl"
    if [ "$GPU" = 1 ]; then
      LP_NUM_THREADS=$THREADS "$ours" bench render --renderer gl --size "$size" "${common[@]}" "${save_gl[@]}" >>"$tmp/gl_$size.jsonl"
      xvfb "$vtk" --mapper gpu --size "$size" "${common[@]}" "${save_gpu[@]}" >>"$tmp/gpu_$size.jsonl"
    fi
  done
done

# One object: {"ours": ..., "vtk_fixedpoint": ..., "ratio_vtk_over_ours": ...} per size.
summarise() {  # file -> {median (of round medians), rounds, p90 (median of round p90s), peak_rss_mb (max)}
  jq -s '{ms_per_frame_median: (map(.ms_per_frame_median) | sort | .[(length - 1) / 2 | floor]),
          ms_per_frame_p90: (map(.ms_per_frame_p90) | sort | .[(length - 1) / 2 | floor]),
          round_medians: map(.ms_per_frame_median), peak_rss_mb: (map(.peak_rss_mb) | max),
          renderer: .[0].renderer, coverage: (.[0].coverage_fraction // .[0].nonblack_fraction)}' "$1"
}
result='{}'
for size in $SIZES; do
  o=$(summarise "$tmp/ours_$size.jsonl")
  v=$(summarise "$tmp/vtk_$size.jsonl")
  g=null gl=null
  if [ "$GPU" = 1 ]; then g=$(summarise "$tmp/gpu_$size.jsonl"); gl=$(summarise "$tmp/gl_$size.jsonl"); fi
  result=$(jq -n --argjson acc "$result" --arg size "$size" --argjson o "$o" --argjson v "$v" --argjson g "$g" --argjson gl "$gl" \
    '$acc + {($size): ({ours_cpu: $o, vtk_fixedpoint: $v,
                        ratio_vtk_over_ours: (($v.ms_per_frame_median / $o.ms_per_frame_median) * 100 | round / 100)}
                       + (if $g == null then {} else {vtk_gpu_llvmpipe: $g, ours_gl_llvmpipe: $gl,
                          ratio_vtk_gpu_over_ours: (($g.ms_per_frame_median / $o.ms_per_frame_median) * 100 | round / 100),
                          ratio_vtk_gpu_over_ours_gl: (($g.ms_per_frame_median / $gl.ms_per_frame_median) * 100 | round / 100)} end))}')
done
jq -n --argjson sizes "$result" --arg volume "$VOLUME" --arg tf "$TF" --argjson threads "$THREADS" \
  --argjson sample_mm "$SAMPLE_MM" --argjson frames "$FRAMES" --argjson warmup "$WARMUP" --argjson rounds "$ROUNDS" \
  --arg date "$(date -u +%Y-%m-%dT%H:%M:%SZ)" --arg host "$(nproc) cores, load $(cut -d' ' -f1-3 /proc/loadavg)" \
  '{benchmark: "render_vs_vtk", date: $date, machine: $host, volume: $volume, tf: $tf, threads: $threads,
    sample_mm: $sample_mm, frames: $frames, warmup: $warmup, rounds: $rounds, sizes: $sizes}'
