#!/bin/bash
# Rebuilds docs/gallery/: fused pictures of a phantom case made from the bundled MRI.
#   scripts/make-gallery.sh [BUILD_DIR]
# Steps: a plan of the bundled T1 (brain surface), one phantom case with truth, its
# registration, the overlay with the registered pose, and (for comparison) with the true one.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$root/build}
cf=$build/cli/cortexfuse
[ -x "$cf" ] || { echo "make-gallery: no $cf (build first)" >&2; exit 1; }
work=$(mktemp -d /tmp/cf_gallery.XXXXXX)
trap 'rm -rf "$work"' EXIT
out=$root/docs/gallery
mkdir -p "$out"

"$cf" plan --t1 "$root/data/t1_head_mne_ecog.nii.gz" --brain-mask "$root/data/brainmask_mne_ecog_binary.nii.gz" \
  --out "$work/plan" --max-triangles 150000
"$cf" phantom "$work/ph" --n 1 --seed 21 --size 750x500 --fixed-size --dslr-fraction 0 --gauze-prob 0 --blood-prob 0 --quiet
case=$work/ph/case_0000
"$cf" register "$case" --out "$work/result.json"
"$cf" overlay "$case" "$work/result.json" --out "$work/overlay" --mesh "$work/plan/brain_surface.ply" \
  --opacity 0.5 --yaw -35 --yaw 35 --pitch 30
# The photo itself, for comparison.
photo=$(ls "$case"/photo.* | head -n1)
cp "$photo" "$out/photo.${photo##*.}"
for f in fused_camera fused_yaw-35 fused_yaw35 fused_pitch30; do
  cp "$work/overlay/$f.png" "$out/$f.png"
done
cp "$work/overlay/overlay.json" "$out/overlay.json"
echo "make-gallery: wrote $(ls "$out" | wc -l) files to $out"
