#!/usr/bin/env bash
# Skull-stripping evaluation on a folder of real T1 heads: for each head found, the mask's
# Dice against a reference mask where one exists, its volume, the median strip time of ROUNDS
# runs, peak RSS and a check image. Prints a Markdown table on stdout and writes the same rows
# as JSON (OUT_DIR/skullstrip_eval.json). Not part of ctest: it needs the data folder.
#
# Usage: bench/skullstrip_eval.sh HEADS_DIR     (after: bash scripts/build.sh release)
#   HEADS_DIR holds any of (names as in ../shared/data): t1_head_mne_ecog.nii.gz (+
#   brainmask_mne_ecog_binary.nii.gz), t1_head_seg3d.nii.gz (+ brainmask_seg3d_intracranial.nii.gz),
#   t1_head_chris.nii.gz, mni152_fsl_t1_2mm_head.nii.gz, dicom/mr_head_t1_sag_siemens/.
# Environment (defaults): BUILD_DIR=build  OUT_DIR=skullstrip_eval  ROUNDS=3
#   EXTRA_ARGS= (more `cortexfuse skullstrip` options, e.g. "--bet-fraction 0.4")
#   RENDER=1: also ray-cast each head through its mask (cortex_t1 and surface_white, views left,
#   right, superior, anterior) into OUT_DIR/<head>_<target>_rendered.png (a 4x2 montage when
#   ImageMagick's `montage` is installed, else the eight PNGs): what `register` shows.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
heads=${1:?usage: bench/skullstrip_eval.sh HEADS_DIR}
[ -d "$heads" ] || { echo "skullstrip_eval: $heads: not a folder" >&2; exit 2; }
BUILD_DIR=${BUILD_DIR:-build}
[[ $BUILD_DIR = /* ]] || BUILD_DIR=$root/$BUILD_DIR
OUT_DIR=${OUT_DIR:-skullstrip_eval}
ROUNDS=${ROUNDS:-3}
RENDER=${RENDER:-1}
EXTRA_ARGS=${EXTRA_ARGS:-}
exe=$BUILD_DIR/cli/cortexfuse
[ -x "$exe" ] || { echo "skullstrip_eval: $exe missing (build first)" >&2; exit 2; }
command -v jq >/dev/null || { echo "skullstrip_eval: jq is needed" >&2; exit 2; }
mkdir -p "$OUT_DIR"

# name | volume (file or DICOM folder) | reference mask | target the reference describes
cases=(
  "mne_ecog|t1_head_mne_ecog.nii.gz|brainmask_mne_ecog_binary.nii.gz|brain"
  "seg3d|t1_head_seg3d.nii.gz|brainmask_seg3d_intracranial.nii.gz|intracranial"
  "chris|t1_head_chris.nii.gz||"
  "mni152_2mm|mni152_fsl_t1_2mm_head.nii.gz||"
  "dicom_mr_sag|dicom/mr_head_t1_sag_siemens||"
)

rows=()
for c in "${cases[@]}"; do
  IFS='|' read -r name vol ref ref_target <<<"$c"
  [ -e "$heads/$vol" ] || continue
  # Every head with the default target (brain); a head whose reference is intracranial also
  # with --target intracranial, so each Dice compares like with like.
  targets=(brain)
  [ "$ref_target" = intracranial ] && targets+=(intracranial)
  for target in "${targets[@]}"; do
    args=(skullstrip "$heads/$vol" --target "$target" --json --quiet)
    [ -n "$ref" ] && [ -e "$heads/$ref" ] && args+=(--reference "$heads/$ref")
    png=$OUT_DIR/${name}_${target}.png
    times=()
    row=
    for ((r = 0; r < ROUNDS; r++)); do
      extra=()
      [ $r -eq 0 ] && extra=(--check-png "$png")
      # shellcheck disable=SC2086
      if ! out=$(/usr/bin/time -f '%M' -o "$OUT_DIR/.rss" "$exe" "${args[@]}" --out "$OUT_DIR/${name}_${target}.nii.gz" \
                 "${extra[@]}" $EXTRA_ARGS 2>"$OUT_DIR/.err"); then
        row=$(jq -nc --arg head "$name" --arg target "$target" --arg error "$(tail -1 "$OUT_DIR/.err")" \
              '{head: $head, target: $target, error: $error}')
        break
      fi
      times+=("$(jq -r .seconds_strip <<<"$out")")
      row=$(jq -c --arg head "$name" --arg target "$target" --arg ref_target "$ref_target" \
            --argjson rss_kb "$(cat "$OUT_DIR/.rss")" --arg png "$png" \
            '{head: $head, target: $target, dice: .dice, reference_target: (if .dice then $ref_target else null end),
              brain_ml: .brain_ml, surface_model_ml: .surface_model_ml, working_spacing_mm: .working_spacing_mm,
              peak_rss_mb: ($rss_kb / 1024),
              check_png: $png}' <<<"$out")
    done
    if [ "$RENDER" = 1 ] && [ -z "$(jq -r '.error // empty' <<<"$row")" ]; then
      shots=()
      for tf in cortex_t1 surface_white; do
        for view in left right superior anterior; do
          shot=$OUT_DIR/${name}_${target}_${tf}_${view}.png
          "$exe" render "$heads/$vol" --mask "$OUT_DIR/${name}_${target}.nii.gz" --tf "$tf" --view "$view" \
            --size 500x400 --out "$shot" >/dev/null
          shots+=("$shot")
        done
      done
      if command -v montage >/dev/null; then
        montage "${shots[@]}" -tile 4x2 -geometry +2+2 "$OUT_DIR/${name}_${target}_rendered.png" && rm -f "${shots[@]}"
        row=$(jq -c --arg r "$OUT_DIR/${name}_${target}_rendered.png" '. + {rendered_png: $r}' <<<"$row")
      fi
    fi
    if [ ${#times[@]} -gt 0 ]; then
      med=$(printf '%s\n' "${times[@]}" | sort -g | awk '{a[NR]=$1} END {print (NR % 2) ? a[(NR+1)/2] : (a[NR/2] + a[NR/2+1]) / 2}')
      row=$(jq -c --argjson med "$med" --argjson n "${#times[@]}" '. + {seconds_median: $med, rounds: $n}' <<<"$row")
    fi
    rows+=("$row")
  done
done
rm -f "$OUT_DIR/.rss" "$OUT_DIR/.err"
[ ${#rows[@]} -gt 0 ] || { echo "skullstrip_eval: no known head in $heads" >&2; exit 2; }

printf '%s\n' "${rows[@]}" | jq -s --arg load "$(cut -d' ' -f1-3 /proc/loadavg)" --argjson cores "$(nproc)" \
  '{machine: {cores: $cores, loadavg: $load}, rows: .}' >"$OUT_DIR/skullstrip_eval.json"

echo "| head | target | Dice vs reference | mL | s (median of $ROUNDS) | peak RSS MB | check image | rendered |"
echo "|---|---|---|---|---|---|---|---|"
printf '%s\n' "${rows[@]}" | jq -r '
  if .error then "| \(.head) | \(.target) | error: \(.error) | | | | | |"
  else "| \(.head) | \(.target) | \(if .dice then "\(.dice * 10000 | round / 10000) (\(.reference_target) ref)" else "-" end) | \(.brain_ml | round) | \(.seconds_median * 10 | round / 10) | \(.peak_rss_mb | round) | \(.check_png) | \(.rendered_png // "-") |" end'
echo
echo "machine: $(nproc) cores, load average $(cut -d' ' -f1-3 /proc/loadavg); JSON: $OUT_DIR/skullstrip_eval.json"
